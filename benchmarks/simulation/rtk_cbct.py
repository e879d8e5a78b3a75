"""A cone-beam CBCT of a simulated case made with RTK's projector and FDK instead of the package's (``itk-rtk``, CPU):
an independent reconstruction of the same moved object, on the same grid, for cross-checking what the package's
simulator gives (``benchmarks/accuracy/bench_rtk_crosscheck.py``).

What is shared with the package's CBCT of the case: the object (the CT resampled onto the simulation's object grid by
:func:`monai_rigidreg.simulation.make_phantom`), the motion applied to it (the package's
:func:`~monai_rigidreg.simulation.volumes.moved_object`), the geometry (SOD, SDD, views over 360 degrees, the
detector's size and pitch fitted to the object) and, with ``physics``, the package's degradations of the line
integrals (noise, scatter, beam hardening; pixel-wise or symmetric, so RTK's detector orientation does not matter to
them). What is RTK's: the forward projection (Joseph's method) and the
reconstruction (FDK, ramp filter without apodisation).

Frames: the package's scanner turns about the LPS ``z`` axis, RTK's about its ``y`` axis. The volume is handed to RTK
in the frame ``(X, Y, Z) = (x, z, -y)`` (a proper rotation), by an exact permutation and flip of the voxel array of a
grid centred on the rotation axis, and the reconstruction is turned back the same way.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

__all__ = ["rtk_available", "rtk_cbct", "rtk_version"]


def rtk_available() -> bool:
    """Whether ``itk-rtk`` is installed (the ``bench`` extra)."""
    try:
        from itk import RTK  # noqa: F401
    except Exception:  # noqa: BLE001 - absent or broken: the cross-check is skipped with the reason
        return False
    return True


def rtk_version() -> str:
    from importlib.metadata import version

    return version("itk-rtk")


def _to_rtk(volume: np.ndarray, origin: Any, spacing: Any):
    """An ITK float image in RTK's frame of the LPS volume ``volume [nx, ny, nz]`` (origin / spacing in LPS mm)."""
    import itk

    arr = np.ascontiguousarray(volume[:, ::-1, :].transpose(1, 2, 0), dtype=np.float32)  # [Z, Y, X] = [-y, z, x]
    img = itk.image_from_array(arr)
    ny = volume.shape[1]
    img.SetOrigin([float(origin[0]), float(origin[2]), -float(origin[1] + (ny - 1) * spacing[1])])
    img.SetSpacing([float(spacing[0]), float(spacing[2]), float(spacing[1])])
    return img


def _from_rtk(img) -> np.ndarray:
    """The LPS voxel array ``[nx, ny, nz]`` of an RTK-frame image made by :func:`_to_rtk`'s grid mapping."""
    import itk

    arr = itk.array_from_image(img)  # [Z, Y, X]
    return np.ascontiguousarray(arr.transpose(2, 0, 1)[:, ::-1, :])


def _blank(size: Any, origin: Any, spacing: Any):
    import itk

    img = itk.image_from_array(np.zeros(tuple(int(s) for s in size[::-1]), dtype=np.float32))
    img.SetOrigin([float(v) for v in origin])
    img.SetSpacing([float(v) for v in spacing])
    return img


def rtk_cbct(
    mu_object: torch.Tensor,
    object_grid: Any,
    cbct_grid: Any,
    params: Any,
    geometry: Any,
    physics: Any = None,
    degrade: bool = True,
    seed: int = 0,
    padding_mode: str = "border",
) -> tuple[np.ndarray, np.ndarray]:
    """The CBCT ``[nx, ny, nz]`` (1/mm) of ``mu_object`` moved by ``params`` (about the origin), by RTK.

    Args:
        mu_object: ``[nx, ny, nz]`` attenuation (1/mm) on ``object_grid`` (centred on the origin, the isocentre).
        object_grid, cbct_grid: :class:`monai_rigidreg.simulation.Grid` of the object and of the reconstruction
            (both centred on the rotation axis).
        params: motion ``(tx, ty, tz, rx, ry, rz)``, mm / degrees, about the origin (a body point ``p`` goes to
            ``M(p)``), as :func:`monai_rigidreg.simulation.volumes.simulate_cbct` takes it.
        geometry: a complete :class:`monai_rigidreg.simulation.ConeBeamGeometry` (SOD, SDD, views, detector).
        physics: the case's :class:`monai_rigidreg.simulation.CBCTPhysics`: its field of view, and with ``degrade``
            its degradations of the line integrals (``None``: the defaults).
        degrade: apply ``physics``' noise, scatter and beam hardening (``False``: ideal line integrals).
        seed: noise seed.
        padding_mode: what the moved object has where it comes from outside ``object_grid``.

    Returns:
        ``(mu [nx, ny, nz] float32, fov [nx, ny, nz] bool)``: the reconstruction, 0 outside the field of view, and
        the field of view (the package's :func:`~monai_rigidreg.simulation.physics.fov_mask` of the geometry).
    """
    import itk
    from itk import RTK as rtk

    from monai_rigidreg.simulation.physics import CBCTPhysics, apply_cbct_physics, fov_mask
    from monai_rigidreg.simulation.volumes import moved_object

    physics = CBCTPhysics() if physics is None else physics
    for g in (object_grid, cbct_grid):
        if not np.allclose(g.center(), 0.0, atol=1e-6):
            raise ValueError(f"the grids must be centred on the rotation axis (the origin), got centre {g.center()}")
    moved = moved_object(mu_object, object_grid, params, (0.0, 0.0, 0.0), padding_mode, "cpu")
    vol = _to_rtk(moved.numpy(), object_grid.origin, object_grid.spacing)

    nu, nv = geometry.detector_shape
    du, dv = geometry.pixel_pitch
    geo = rtk.ThreeDCircularProjectionGeometry.New()
    for k in range(geometry.num_views):
        geo.AddProjection(float(geometry.sod), float(geometry.sdd),
                          float(geometry.start_angle + k * geometry.arc / geometry.num_views))
    proj0 = _blank((nu, nv, geometry.num_views), (-(nu - 1) / 2 * du, -(nv - 1) / 2 * dv, 0.0), (du, dv, 1.0))
    image = itk.Image[itk.F, 3]
    fp = rtk.JosephForwardProjectionImageFilter[image, image].New()
    fp.SetInput(0, proj0)
    fp.SetInput(1, vol)
    fp.SetGeometry(geo)
    fp.Update()
    proj = torch.from_numpy(itk.array_from_image(fp.GetOutput()).copy())  # [views, nv, nu]
    if degrade:
        proj = apply_cbct_physics(proj, geometry, physics, torch.Generator().manual_seed(int(seed)))
    proj_img = itk.image_from_array(np.ascontiguousarray(proj.numpy(), dtype=np.float32))
    proj_img.SetOrigin(proj0.GetOrigin())
    proj_img.SetSpacing(proj0.GetSpacing())

    nx, ny, nz = cbct_grid.size
    sx, sy, sz = cbct_grid.spacing
    ox, oy, oz = cbct_grid.origin
    rec0 = _blank((nx, nz, ny), (ox, oz, -(oy + (ny - 1) * sy)), (sx, sz, sy))
    fdk = rtk.FDKConeBeamReconstructionFilter[image].New()
    fdk.SetInput(0, rec0)
    fdk.SetInput(1, proj_img)
    fdk.SetGeometry(geo)
    fdk.GetRampFilter().SetTruncationCorrection(0.0)
    fdk.GetRampFilter().SetHannCutFrequency(0.0)
    fdk.Update()
    rec = _from_rtk(fdk.GetOutput())
    fov = fov_mask(cbct_grid, geometry, physics, "cpu").numpy()
    return np.where(fov, rec, 0.0).astype(np.float32), fov
