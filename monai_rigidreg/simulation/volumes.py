"""Simulation of single volumes and of one case: a planning CT ("Sim-CT") and a CBCT of a moved object.

The Sim-CT of an object (a phantom or a real CT) is simulated unmoved: fan-beam projection slice by slice and FBP
(:func:`simulate_simct`). For a case the object is moved by a rigid motion ``M`` (a body point at ``p`` goes to
``M(p)``; ``M`` about the isocentre = the Sim-CT centre = the origin), then the CBCT is projected (cone beam),
degraded (:class:`~monai_rigidreg.simulation.physics.CBCTPhysics`) and reconstructed with FDK
(:func:`simulate_cbct`). With fixed = Sim-CT and moving = CBCT, the registration transform (fixed -> moving points,
``sitk.Resample(cbct, simct, T)`` aligns them) is ``T = M``.

:func:`simulate_case` simulates and writes one case of a :class:`~monai_rigidreg.simulation.config.SimulationConfig`
(the building block of :func:`~monai_rigidreg.simulation.simulate_dataset` and
:func:`~monai_rigidreg.simulation.simulate_pair`); volumes are written in HU, atomically (:func:`save_volume_hu`).
The simulation runs about the isocentre (0, 0, 0) with identity direction (LPS); the volumes are written there, or,
with a CT as the phantom (and ``ct_frame``, the default), moved by :func:`frame_offset` into the CT's own frame, so
that a CBCT registers against the input CT itself. The motion is the same about the moved Sim-CT centre.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.core.device import resolve_device
from monai_rigidreg.core.geometry import Grid, invert_matrix, params_to_matrix
from monai_rigidreg.core.warp import warp_volume
from monai_rigidreg.simulation.config import SimulationConfig
from monai_rigidreg.simulation.phantoms import PHANTOMS, ct_center, make_phantom, mu_to_hu
from monai_rigidreg.simulation.physics import CBCTPhysics, apply_cbct_physics, fov_mask
from monai_rigidreg.simulation.projector import cone_forward, fan_forward, grid_axes
from monai_rigidreg.simulation.reconstruction import fbp_fan, fdk
from monai_rigidreg.simulation.scanner import ConeBeamGeometry, FanBeamGeometry

__all__ = ["simulate_simct", "simulate_cbct", "moved_object", "fitted_cone_geometry", "save_volume_hu",
           "save_fov_mask", "write_simct", "simulate_case", "stream_seed", "frame_offset"]


# ---------------------------------------------------------------------------------------------------------------
# Single volumes
# ---------------------------------------------------------------------------------------------------------------
def simulate_simct(
    mu: torch.Tensor,
    grid: Grid,
    views: int = 360,
    sod: float = 800.0,
    sdd: float = 1200.0,
    window: str = "shepp-logan",
    photons: float | None = None,
    seed: int = 0,
    device: str | torch.device | None = "auto",
) -> torch.Tensor:
    """Fan-beam CT of an attenuation volume: slice-by-slice projection (one detector row per slice) and FBP.

    Args:
        mu: ``[nx, ny, nz]`` attenuation (1/mm) on ``grid``.
        grid: axis-aligned grid; the reconstruction is on the same grid.
        views: projections over 360 degrees.
        sod, sdd: distances, mm.
        window: FBP filter window.
        photons: photons per detector pixel for Poisson noise (``None``: noise-free).
        seed: noise seed.
        device: torch device.

    Returns:
        ``[nx, ny, nz]`` float32 reconstructed attenuation (1/mm) on ``device``.
    """
    dev = resolve_device(device)
    radius = _support_radius(mu, grid, xy_only=True) + 2 * max(grid.spacing)
    geom = FanBeamGeometry(sod=sod, sdd=sdd, num_views=views).fitted(radius, min(grid.spacing[:2]))
    sino = fan_forward(mu, grid, geom, dev)
    if photons:
        gen = torch.Generator(device=dev).manual_seed(int(seed))
        counts = torch.poisson(photons * torch.exp(-sino), generator=gen)
        sino = -torch.log(counts.clamp_min(1.0) / photons)
    return fbp_fan(sino, geom, grid, window, dev)


def _support_radius(mu: torch.Tensor, grid: Grid, xy_only: bool = False, threshold: float = 1e-5) -> float:
    """Largest distance (mm) from the isocentre (or the z axis) of a voxel with ``mu > threshold``."""
    xs, ys, zs = grid_axes(grid, mu.device)
    occ = mu > threshold
    if not bool(occ.any()):
        return float(max(grid.spacing))
    r2 = xs[:, None] ** 2 + ys[None, :] ** 2
    r_xy = float(r2[occ.any(2)].max().sqrt())
    if xy_only:
        return r_xy
    return float(math.sqrt(r_xy**2 + float((zs[occ.any(0).any(0)] ** 2).max())))


def moved_object(
    mu_object: torch.Tensor,
    object_grid: Grid,
    params: Any,
    center: Any = (0.0, 0.0, 0.0),
    padding_mode: str = "zeros",
    device: str | torch.device | None = "cpu",
) -> torch.Tensor:
    """``mu_object`` moved by the rigid motion ``M = params`` about ``center``: ``obj(M^-1(y))`` on ``object_grid``
    (trilinear; ``[nx, ny, nz]`` float32 on ``device``), the object a CBCT of the motion sees."""
    m = params_to_matrix(params, center)
    obj = mu_object.to(device=device, dtype=torch.float32)[None, None]
    if np.allclose(m, np.eye(4)):
        return obj[0, 0]
    inv = torch.as_tensor(invert_matrix(m), dtype=torch.float64, device=obj.device)[None]
    return warp_volume(obj, inv, object_grid, object_grid, "bilinear", padding_mode)[0, 0]


def fitted_cone_geometry(object_grid: Grid, cbct_grid: Grid, radius_mm: float, views: int = 360, sod: float = 800.0,
                         sdd: float = 1200.0) -> ConeBeamGeometry:
    """The cone-beam geometry of :func:`simulate_cbct`: its detector fitted to cover ``radius_mm`` about the axis and
    the CBCT grid's height (plus a slice), at the object grid's finest spacing back-projected to the isocentre."""
    half_h = 0.5 * cbct_grid.size[2] * cbct_grid.spacing[2] + cbct_grid.spacing[2]
    return ConeBeamGeometry(sod=sod, sdd=sdd, num_views=views).fitted(radius_mm, half_h, min(object_grid.spacing))


def simulate_cbct(
    mu_object: torch.Tensor,
    object_grid: Grid,
    cbct_grid: Grid,
    params: Any = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    center: Any = (0.0, 0.0, 0.0),
    views: int = 360,
    sod: float = 800.0,
    sdd: float = 1200.0,
    physics: CBCTPhysics | None = None,
    window: str = "shepp-logan",
    seed: int = 0,
    detector_radius_mm: float | None = None,
    mask_outside_fov: bool = True,
    padding_mode: str = "zeros",
    device: str | torch.device | None = "auto",
) -> tuple[torch.Tensor, torch.Tensor, ConeBeamGeometry]:
    """CBCT of an object moved by the rigid motion ``M = params`` (a body point at ``p`` goes to ``M(p)``).

    The moved object is ``obj(M^-1(y))`` (trilinear resampling on ``object_grid``), projected with the cone
    beam, degraded by ``physics`` and reconstructed with FDK on ``cbct_grid``.

    Args:
        mu_object: ``[nx, ny, nz]`` attenuation (1/mm) on ``object_grid`` (axis-aligned).
        object_grid: grid of ``mu_object``; it should leave room for the motion.
        cbct_grid: reconstruction grid.
        params: motion ``(tx, ty, tz, rx, ry, rz)``, mm / degrees, about ``center`` (LPS mm).
        center: rotation centre, mm (the Sim-CT centre, the isocentre).
        views: projections over 360 degrees.
        sod, sdd: distances, mm.
        physics: degradations (default :class:`CBCTPhysics` defaults; ``CBCTPhysics.ideal()`` for none).
        window: FDK filter window.
        seed: noise seed.
        detector_radius_mm: radius about the axis the detector must cover (``None``: the moved object's).
            The detector pitch at the isocentre is ``object_grid`` spacing.
        mask_outside_fov: set voxels outside the field of view to 0 (air).
        padding_mode: what the moved object has where it comes from outside ``object_grid``
            (``"zeros"`` or ``"border"``).
        device: torch device.

    Returns:
        ``(mu [nx, ny, nz] float32 1/mm, fov [nx, ny, nz] bool, geometry)`` on ``device``.
    """
    dev = resolve_device(device)
    physics = CBCTPhysics() if physics is None else physics
    moved = moved_object(mu_object, object_grid, params, center, padding_mode, dev)
    radius = detector_radius_mm
    if radius is None:
        radius = _support_radius(moved, object_grid, xy_only=True) + max(object_grid.spacing)
    geom = fitted_cone_geometry(object_grid, cbct_grid, radius, views, sod, sdd)
    proj = cone_forward(moved, object_grid, geom, dev)
    del moved
    gen = torch.Generator(device=dev).manual_seed(int(seed))
    proj = apply_cbct_physics(proj, geom, physics, gen)
    fov = fov_mask(cbct_grid, geom, physics, dev)
    # masked to the field of view, only the columns it touches need reconstructing (the rest is set to 0 anyway)
    rec = fdk(proj, geom, cbct_grid, window, dev, columns=fov.any(2) if mask_outside_fov else None)
    if mask_outside_fov:
        rec = torch.where(fov, rec, torch.zeros_like(rec))
    return rec, fov, geom


def save_volume_hu(mu: torch.Tensor, grid: Grid, path: str | Path, dtype: str = "int16") -> Path:
    """Write an attenuation volume ``[nx, ny, nz]`` (1/mm) as a NIfTI in HU (atomically).

    ``dtype="int16"`` (default) stores whole HU, clipped to the int16 range, as CT scanners and DICOM do: a
    rounding error of at most 0.5 HU, far below the noise, for smaller files read in about half the time of
    compressed float32 (``benchmarks/speed/bench_inference_speed.py``). ``"float32"`` keeps the reconstruction's values
    exactly.
    """
    if dtype not in ("int16", "float32"):
        raise ValueError(f"dtype must be 'int16' or 'float32', got {dtype!r}")
    arr = mu_to_hu(mu.detach().to("cpu", torch.float32)).numpy().transpose(2, 1, 0)
    if dtype == "int16":
        info = np.iinfo(np.int16)
        arr = np.clip(np.rint(arr), info.min, info.max).astype(np.int16)
    img = grid.apply_to(sitk.GetImageFromArray(np.ascontiguousarray(arr)))
    return _write_atomic(img, Path(path))


def save_fov_mask(fov: torch.Tensor, grid: Grid, path: str | Path) -> Path:
    """Write a boolean field-of-view mask ``[nx, ny, nz]`` as a uint8 NIfTI on ``grid`` (atomically)."""
    arr = fov.detach().cpu().numpy().transpose(2, 1, 0).astype(np.uint8)
    return _write_atomic(grid.apply_to(sitk.GetImageFromArray(np.ascontiguousarray(arr))), Path(path))


def _write_atomic(img: sitk.Image, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    try:
        sitk.WriteImage(img, str(tmp), True)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)  # after a failure or an interrupt: no half-written file left behind
    return path


# ---------------------------------------------------------------------------------------------------------------
# One case of a configuration
# ---------------------------------------------------------------------------------------------------------------
def stream_seed(*keys: int) -> int:
    """A seed derived from the master seed and the stream keys (0 objects, 1 CBCT noise, 2 Sim-CT noise; index)."""
    return int(np.random.SeedSequence([int(k) for k in keys]).generate_state(1)[0])


def frame_offset(cfg: SimulationConfig) -> np.ndarray:
    """Where the written volumes of ``cfg`` lie relative to the simulation's frame (LPS mm): with a CT as the phantom
    and ``cfg.ct_frame``, the CT's centre less the Sim-CT grid's (the Sim-CT then lies where the CT does); else 0."""
    if cfg.phantom in PHANTOMS or not cfg.ct_frame:
        return np.zeros(3)
    return ct_center(cfg.phantom) - cfg.simct_grid.center()


def _placed(grid: Grid, offset: np.ndarray) -> Grid:
    """``grid`` moved by ``offset`` (LPS mm): the grid a volume simulated on ``grid`` is written on."""
    return dataclasses.replace(grid, origin=tuple(float(v) for v in np.add(grid.origin, offset)))


def _object_volume(cfg: SimulationConfig, k: int, grid: Grid, device: torch.device) -> torch.Tensor:
    mu, _ = make_phantom(cfg.phantom, grid, stream_seed(cfg.seed, 0, k), cfg.supersample, cfg.radius_mm, device)
    return mu


def _detector_radius(cfg: SimulationConfig, obj_grid: Grid, mu: torch.Tensor) -> float:
    """One detector per object: covers the object (3D radius about the isocentre) plus the largest translation."""
    t_max = cfg.max_translation * math.sqrt(3)
    radius = _support_radius(mu, obj_grid) + t_max + max(obj_grid.spacing)
    return min(radius, 0.9 * cfg.sod)


def write_simct(cfg: SimulationConfig, object_index: int, path: str | Path) -> Path:
    """Simulate the (unmoved) Sim-CT of object ``object_index`` of ``cfg`` and write it to ``path`` (HU)."""
    dev = resolve_device(cfg.device)
    grid = cfg.simct_grid
    mu = _object_volume(cfg, object_index, grid, dev)
    rec = simulate_simct(
        mu,
        grid,
        cfg.simct_views,
        cfg.sod,
        cfg.sdd,
        cfg.simct_filter,
        cfg.simct_photons,
        stream_seed(cfg.seed, 2, object_index),
        dev,
    )
    return save_volume_hu(rec, _placed(grid, frame_offset(cfg)), path, cfg.volume_dtype)


def simulate_case(
    cfg: SimulationConfig,
    case: Mapping[str, Any],
    output_dir: str | Path,
    write_fixed: bool = True,
    object_cache: dict[tuple, Any] | None = None,
) -> dict[str, Path]:
    """Simulate and write one case of ``cfg``: the Sim-CT of its object and the CBCT of the moved object.

    Deterministic: the object, the Sim-CT noise and the CBCT noise are seeded from ``cfg.seed`` and the case's
    object and case numbers, so a case gives the same files wherever and in whatever order it is simulated. The
    field-of-view mask is written before the CBCT: a CBCT file marks a finished case.

    Args:
        cfg: the configuration.
        case: the case record: ``"index"`` (case number), ``"object_index"`` (object number), ``"params"`` (the
            motion ``(tx, ty, tz, rx, ry, rz)``, mm / degrees, about the isocentre) and the paths, relative to
            ``output_dir``, of the ``"fixed"`` Sim-CT, the ``"moving"`` CBCT and its ``"moving_fov"`` mask.
        output_dir: folder the paths are relative to (sub-folders are created).
        write_fixed: also simulate and write the Sim-CT (a dataset writes it once per object, see
            :func:`write_simct`).
        object_cache: a dict that keeps the last object volume (and its detector size) between calls, so that
            consecutive cases of one object voxelize it once.

    Returns:
        ``{"fixed", "moving", "moving_fov"}``: the paths written (``"fixed"`` only with ``write_fixed``).
    """
    dev = resolve_device(cfg.device)
    out = Path(output_dir)
    k = int(case["object_index"])
    written: dict[str, Path] = {}
    if write_fixed:
        written["fixed"] = write_simct(cfg, k, out / case["fixed"])
    key = (json.dumps(cfg.identity(), sort_keys=True), k, str(dev))
    if object_cache is not None and key in object_cache:
        grid, mu, radius = object_cache[key]
    else:
        grid = cfg.object_grid()
        mu = _object_volume(cfg, k, grid, dev)
        radius = _detector_radius(cfg, grid, mu)
        if object_cache is not None:
            object_cache.clear()
            object_cache[key] = (grid, mu, radius)
    rec, fov, _ = simulate_cbct(
        mu,
        grid,
        cfg.cbct_grid,
        list(case["params"]),
        (0.0, 0.0, 0.0),
        cfg.cbct_views,
        cfg.sod,
        cfg.sdd,
        cfg.cbct_physics,
        cfg.cbct_filter,
        seed=stream_seed(cfg.seed, 1, case["index"]),
        detector_radius_mm=radius,
        mask_outside_fov=cfg.mask_outside_fov,
        padding_mode="zeros" if cfg.phantom in PHANTOMS else "border",
        device=dev,
    )
    cbct_grid = _placed(cfg.cbct_grid, frame_offset(cfg))  # the CT's frame, where the phantom is a CT (ct_frame)
    written["moving_fov"] = save_fov_mask(fov, cbct_grid, out / case["moving_fov"])
    # written last: its presence marks a finished case
    written["moving"] = save_volume_hu(rec, cbct_grid, out / case["moving"], cfg.volume_dtype)
    return written
