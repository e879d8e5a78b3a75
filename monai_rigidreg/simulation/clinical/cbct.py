"""The CBCT of a clinical-geometry pair: the moved (and deformed) patient resampled from the CT into the scanner frame
(:func:`moved_object`), projected, degraded and reconstructed with FDK (:func:`simulate_clinical_cbct`).

Frames and units: :mod:`monai_rigidreg.simulation.clinical`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch
import torch.nn.functional as F

from monai_rigidreg.core.device import resolve_device
from monai_rigidreg.core.geometry import (
    Grid,
    invert_matrix,
    mask_points,
    params_to_matrix,
    transform_points,
)
from monai_rigidreg.simulation.clinical.planning_ct import PlanningCT
from monai_rigidreg.simulation.clinical.sampling import SmoothDeformation
from monai_rigidreg.simulation.clinical.spec import ClinicalCBCTSpec
from monai_rigidreg.simulation.phantoms import mu_to_hu
from monai_rigidreg.simulation.physics import apply_cbct_physics, centre_line_integral, effective_photons, fov_mask
from monai_rigidreg.simulation.projector import cone_forward, grid_axes
from monai_rigidreg.simulation.reconstruction import fdk
from monai_rigidreg.simulation.scanner import ConeBeamGeometry

__all__ = ["moved_object", "simulate_clinical_cbct"]


def _detector_half_height(spec: ClinicalCBCTSpec) -> float:
    """Half-height (mm on the detector) that covers the field of view's slab: every voxel of the CBCT grid within
    the cylinder, seen from the nearest source position (the project's ``ConeBeamGeometry.fitted`` margin)."""
    half_h = 0.5 * spec.length_mm + spec.spacing
    return spec.sdd * half_h / (spec.sod - 0.5 * spec.fov_diameter_mm) * 1.05


def _object_grid(ct: PlanningCT, matrix: np.ndarray, isocenter: np.ndarray, spec: ClinicalCBCTSpec,
                 margin_mm: float) -> Grid:
    """The scanner-frame grid the projector needs: the whole moved patient in ``x, y`` (every ray through the field
    of view crosses it) and, axially, as far as the cone reaches at the far side of the patient."""
    body_pts = mask_points(sitk.BinaryThreshold(ct.image, -900.0, 1e9, 1, 0), max_points=40000, seed=1)
    # the continuation beyond the end slices: the first and last slices' content, repeated
    grid = ct.grid
    idx = transform_points(grid.physical_to_index(), body_pts)
    axis = grid.direction_matrix[:, 2] * grid.spacing[2]
    ends = []
    for k_end, sign in ((0.0, -1.0), (grid.size[2] - 1.0, 1.0)):
        near_end = body_pts[np.abs(idx[:, 2] - k_end) <= 2.0]
        for step in np.linspace(0.0, spec.extension_mm / grid.spacing[2], 6):
            ends.append(near_end + sign * step * axis)
    pts = transform_points(matrix, np.concatenate([body_pts, *ends])) - isocenter
    rho = np.linalg.norm(pts[:, :2], axis=1)
    r_all = min(float(rho.max()) + margin_mm, 0.9 * spec.sod)
    z_reach = _detector_half_height(spec) * (spec.sod + r_all) / spec.sdd + 2 * spec.spacing
    in_slab = np.abs(pts[:, 2]) <= z_reach + margin_mm
    r = float(rho[in_slab].max(initial=0.0)) + margin_mm
    r = max(min(r, 0.9 * spec.sod), 0.5 * spec.fov_diameter_mm + spec.spacing)
    sp = spec.spacing
    return Grid.centered((2 * math.ceil(r / sp), 2 * math.ceil(r / sp), 2 * math.ceil(z_reach / sp)), (sp, sp, sp))


def moved_object(
    ct: PlanningCT,
    matrix: np.ndarray,
    isocenter: Sequence[float],
    object_grid: Grid,
    deformation: SmoothDeformation | None = None,
    extension_mm: float = 100.0,
    device: str | torch.device | None = "cpu",
    chunk_slices: int = 8,
) -> torch.Tensor:
    """The patient as the CBCT scanner sees it: attenuation ``[nx, ny, nz]`` (1/mm) on ``object_grid`` (scanner
    frame, isocentre at the origin).

    ``mu(s) = mu_CT(x)`` with ``x = y - v(y)``, ``y = T^-1(s + p)`` (``T = matrix``, fixed -> moving; ``v`` the
    deformation's pull-back displacement, or 0): one trilinear resampling of the CT. Beyond the CT's first and last
    slices the end slices continue for ``extension_mm``; elsewhere outside the CT is air.
    """
    dev = resolve_device(device)
    mu = ct.mu(min(object_grid.spacing), dev)
    nk, nj, ni = mu.shape
    grid = ct.grid
    inv = torch.as_tensor(invert_matrix(matrix), dtype=torch.float64, device=dev)
    to_index = torch.as_tensor(grid.physical_to_index(), dtype=torch.float64, device=dev)
    p = torch.as_tensor(np.asarray(isocenter, dtype=np.float64), device=dev)
    xs, ys, zs = (o + s * torch.arange(n, dtype=torch.float64, device=dev)
                  for o, s, n in zip(object_grid.origin, object_grid.spacing, object_grid.size))
    ext = float(extension_mm) / grid.spacing[2]
    out = torch.empty(tuple(object_grid.size), dtype=torch.float32, device=dev)
    vol = mu[None, None]
    for z0 in range(0, len(zs), chunk_slices):
        zc = zs[z0 : z0 + chunk_slices]
        s = torch.stack(torch.meshgrid(xs, ys, zc, indexing="ij"), -1)  # [nx, ny, c, 3] scanner frame
        y = (s + p) @ inv[:3, :3].T + inv[:3, 3]  # CT frame of the day of treatment
        x = y - deformation.displacement_torch(y) if deformation is not None else y
        idx = x @ to_index[:3, :3].T + to_index[:3, 3]  # continuous (i, j, k)
        k = idx[..., 2]
        beyond = (k < -ext) | (k > nk - 1 + ext)
        k = torch.where(beyond, torch.full_like(k, -4.0), k.clamp(0.0, nk - 1.0))
        norm = torch.stack([
            idx[..., 0] * (2.0 / max(ni - 1, 1)) - 1.0,
            idx[..., 1] * (2.0 / max(nj - 1, 1)) - 1.0,
            torch.where(beyond, torch.full_like(k, -4.0), k * (2.0 / max(nk - 1, 1)) - 1.0),
        ], -1).to(torch.float32)
        out[:, :, z0 : z0 + len(zc)] = F.grid_sample(vol, norm[None], mode="bilinear", padding_mode="zeros",
                                                     align_corners=True)[0, 0]
    return out


def simulate_clinical_cbct(
    ct: PlanningCT,
    isocenter: Sequence[float],
    params_isocenter: Sequence[float],
    deformation: SmoothDeformation | None = None,
    spec: ClinicalCBCTSpec | None = None,
    seed: int = 0,
    device: str | torch.device | None = "cpu",
) -> tuple[sitk.Image, sitk.Image, dict[str, Any]]:
    """The CBCT of the (deformed and) moved patient, centred on the isocentre.

    Args:
        ct: the planning CT.
        isocenter: ``p`` (LPS mm, CT frame).
        params_isocenter: the setup error ``T`` (fixed -> moving) ``(tx, ty, tz, rx, ry, rz)`` about ``p``.
        deformation: the anatomy's change before the setup error, or ``None``.
        spec: the acquisition (default :class:`ClinicalCBCTSpec`).
        seed: noise seed.
        device: torch device of the projector.

    Returns:
        ``(cbct, fov, info)``: the CBCT (float32 HU, grid centred on ``p``, CBCT frame), its field-of-view mask
        (uint8, same grid) and ``{"object_grid": size, "detector": ..., "photons": I0, "centre_line_integral": p}``
        (``I0`` after the automatic exposure control, photons per pixel and view, ``None`` without quantum noise;
        ``p`` the ideal line integral through the isocentre,
        :func:`~monai_rigidreg.simulation.physics.centre_line_integral`).
    """
    spec = ClinicalCBCTSpec() if spec is None else spec
    dev = resolve_device(device)
    p = np.asarray(isocenter, dtype=np.float64)
    m = params_to_matrix(params_isocenter, p)
    margin = spec.spacing * 2 + (0.0 if deformation is None else deformation.peak())
    obj_grid = _object_grid(ct, m, p, spec, margin)
    obj = moved_object(ct, m, p, obj_grid, deformation, spec.extension_mm, dev)
    # the detector: wide enough for the whole patient (no truncation), tall enough for the field of view's slab
    xs, ys, _ = grid_axes(obj_grid, dev)
    occupied = (obj > 1e-5).any(2)
    r_obj = float(torch.sqrt(xs[:, None] ** 2 + ys[None, :] ** 2)[occupied].max()) if bool(occupied.any()) else 0.0
    r_obj = max(r_obj + spec.spacing, 0.5 * spec.fov_diameter_mm + spec.spacing)
    geom = ConeBeamGeometry(sod=spec.sod, sdd=spec.sdd, num_views=spec.views).fitted(r_obj, 0.0, spec.spacing)
    pitch = geom.pixel_pitch[1]
    geom = replace(geom, detector_shape=(geom.detector_shape[0],
                                         2 * math.ceil(_detector_half_height(spec) / pitch) + 2))
    proj = cone_forward(obj, obj_grid, geom, dev)
    del obj
    photons = effective_photons(proj, spec.physics) if spec.physics.photons else None  # None: no quantum noise
    p_centre = centre_line_integral(proj)
    gen = torch.Generator(device=dev).manual_seed(int(seed))
    proj = apply_cbct_physics(proj, geom, spec.physics, gen)
    scanner_grid = spec.grid()
    fov = fov_mask(scanner_grid, geom, spec.physics, dev)
    rec = fdk(proj, geom, scanner_grid, spec.window, dev, columns=fov.any(2))  # the rest is masked to 0 below
    del proj
    rec = torch.where(fov, rec, torch.zeros_like(rec))
    out_grid = spec.grid(p)
    arr = mu_to_hu(rec.detach().to("cpu", torch.float32)).numpy().transpose(2, 1, 0)
    cbct = out_grid.apply_to(sitk.GetImageFromArray(np.ascontiguousarray(arr.astype(np.float32))))
    fov_img = out_grid.apply_to(sitk.GetImageFromArray(
        np.ascontiguousarray(fov.cpu().numpy().transpose(2, 1, 0).astype(np.uint8))))
    info = {"object_grid": list(obj_grid.size), "object_spacing_mm": spec.spacing,
            "detector": [int(v) for v in geom.detector_shape], "detector_pitch_mm": list(geom.pixel_pitch),
            "photons": photons, "centre_line_integral": p_centre}
    return cbct, fov_img, info
