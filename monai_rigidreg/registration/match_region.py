"""The match region: where on the planning CT the registration looks (clip box, bone match, couch excluded).

Treatment-machine CBCT matching lets the user restrict the match to the target region (a "clip box" or a
structure) and choose a bone or soft-tissue match; anatomy that changed between the scans (bladder, rectum,
breathing) and the couches, which do not move with the patient, should not pull the result. This module turns
those choices into one weight image on the CT (fixed) grid, values in [0, 1]:

* ``roi``: a box ``(x0, y0, z0, x1, y1, z1)`` in CT LPS millimetres, or a mask image (any grid overlapping the CT;
  non-zero = inside), or ``None`` (everywhere);
* ``match="bone"``: only the CT's bone (above ``bone_hu``) and a few millimetres around it; ``"soft"`` (default):
  all tissue;
* ``body``: an optional body mask (the patient without the couch, :mod:`monai_rigidreg.registration.body`); outside it
  the weight is 0.

:class:`~monai_rigidreg.registration.RigidRegistrar` resamples the weight onto the network grid and passes it to
the network (``fixed_weight``): it weighs the learned network's cells in the rigid fit and the Gauss-Newton
residuals; the global search and the learned estimate's placement do not depend on it.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.core.grid_sampling import sitk_on_grid

__all__ = ["MATCH_MODES", "parse_roi", "match_weight", "roi_center", "weight_on_grid"]

MATCH_MODES = ("soft", "bone")
"""``soft``: all tissue (default); ``bone``: the CT's bone and its surroundings only."""

RoiLike = Sequence[float] | sitk.Image | str | Path | None


def parse_roi(roi: RoiLike) -> tuple[float, float, float, float, float, float] | sitk.Image | None:
    """A box (six numbers, or a string ``"x0,y0,z0,x1,y1,z1"``, LPS mm) or a mask (image or path), checked.

    Raises:
        InputError: not six numbers, an empty box, a mask file that cannot be read, a mask that is not a 3D scalar
            image or has no non-zero voxel.
    """
    if roi is None:
        return roi
    if isinstance(roi, sitk.Image):
        return _check_mask(roi)
    if isinstance(roi, (str, Path)):
        text = str(roi)
        if Path(text).exists():
            from monai_rigidreg.io.volumes import (
                load_volume,  # the volumes' reader and checks (truncated NIfTI included)
            )

            try:
                mask = load_volume(text, pixel_type=None, check_finite=False)
            except InputError as exc:
                raise InputError(f"the ROI mask: {exc.reason}", text) from exc
            return _check_mask(mask, text)
        try:
            roi = [float(v) for v in text.replace(";", ",").split(",")]
        except ValueError as exc:
            raise InputError(f"--roi must be a mask file or six numbers x0,y0,z0,x1,y1,z1 (CT LPS mm), got {text!r}: "
                             "no such file, and not six numbers") from exc
    values = [float(v) for v in roi]
    if len(values) != 6 or not all(np.isfinite(values)):
        raise InputError(f"an ROI box needs six finite numbers x0,y0,z0,x1,y1,z1 (CT LPS mm), got {values}")
    lo = np.minimum(values[:3], values[3:])
    hi = np.maximum(values[:3], values[3:])
    if np.any(hi - lo <= 0):
        raise InputError(f"the ROI box {values} is empty along an axis")
    return (*[float(v) for v in lo], *[float(v) for v in hi])


def _check_mask(mask: sitk.Image, path: str | None = None) -> sitk.Image:
    """An ROI mask as :func:`parse_roi` takes it: a 3D scalar image with at least one non-zero voxel.

    Raises:
        InputError: another dimension, vector voxels, or no voxel inside.
    """
    if mask.GetDimension() != 3 or mask.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"the ROI mask must be a 3D scalar image, got a {mask.GetDimension()}D image of size "
                         f"{mask.GetSize()} with {mask.GetNumberOfComponentsPerPixel()} component(s) per voxel", path)
    if not np.any(sitk.GetArrayViewFromImage(mask)):
        raise InputError("the ROI mask is empty (no non-zero voxel)", path)
    return mask


def _box_mask(fixed: sitk.Image, box: Sequence[float]) -> np.ndarray:
    """``[z, y, x]`` bool array of the CT voxels whose centres lie in the LPS box (any direction cosines)."""
    grid = Grid.from_sitk(fixed)
    nx, ny, nz = grid.size
    to_mm = grid.index_to_physical()
    inside = np.ones((nz, ny, nx), dtype=bool)
    i = np.arange(nx, dtype=np.float64)[None, None, :]
    j = np.arange(ny, dtype=np.float64)[None, :, None]
    k = np.arange(nz, dtype=np.float64)[:, None, None]
    for axis in range(3):  # p_axis = o + i a + j b + k c, broadcast over [z, y, x]
        coord = to_mm[axis, 3] + i * to_mm[axis, 0] + j * to_mm[axis, 1] + k * to_mm[axis, 2]
        inside &= (coord >= box[axis]) & (coord <= box[axis + 3])
    return inside


def match_weight(
    fixed: sitk.Image,
    roi: RoiLike = None,
    match: str = "soft",
    body: sitk.Image | None = None,
    bone_hu: float = 250.0,
    bone_margin_mm: float = 4.0,
) -> sitk.Image | None:
    """The match-region weight on the CT grid (float32 in [0, 1]), or ``None`` where nothing restricts the match.

    Args:
        fixed: planning CT (HU).
        roi: box (LPS mm) or mask (see :func:`parse_roi`); ``None``: no restriction.
        match: ``"soft"`` or ``"bone"`` (see :data:`MATCH_MODES`).
        body: optional body mask on any grid (patient without couch); outside it the weight is 0.
        bone_hu: the bone threshold of ``match="bone"``.
        bone_margin_mm: bone is dilated by this much (its edges carry the match).

    Raises:
        InputError: an unknown ``match``, an ROI that does not overlap the CT, or no bone in the region.
    """
    if match not in MATCH_MODES:
        raise InputError(f"match must be one of {MATCH_MODES}, got {match!r}")
    roi = parse_roi(roi)
    if roi is None and match == "soft" and body is None:
        return None
    size = fixed.GetSize()
    weight = np.ones((size[2], size[1], size[0]), dtype=bool)
    if isinstance(roi, sitk.Image):
        on_ct = sitk.Resample(roi, fixed, sitk.Transform(), sitk.sitkNearestNeighbor, 0.0, sitk.sitkFloat32)
        weight &= sitk.GetArrayViewFromImage(on_ct) > 0
    elif roi is not None:
        weight &= _box_mask(fixed, roi)
    if not weight.any():
        raise InputError("the region of interest does not overlap the CT (box in CT LPS millimetres, or a mask on "
                         "the CT's physical space)")
    if body is not None:
        on_ct = sitk.Resample(body, fixed, sitk.Transform(), sitk.sitkNearestNeighbor, 0.0, sitk.sitkUInt8)
        weight &= sitk.GetArrayViewFromImage(on_ct) > 0
    if match == "bone":
        bone = sitk.BinaryThreshold(fixed, bone_hu, 1e9, 1, 0)
        radius = [max(1, int(round(bone_margin_mm / s))) for s in fixed.GetSpacing()]
        bone = sitk.BinaryDilate(bone, radius)
        bone_arr = sitk.GetArrayViewFromImage(bone) > 0
        if not (weight & bone_arr).any():
            raise InputError(f"match='bone': no CT voxel above {bone_hu:g} HU in the match region")
        weight &= bone_arr
    out = sitk.GetImageFromArray(weight.astype(np.float32))
    out.CopyInformation(fixed)
    return out


def roi_center(fixed: sitk.Image, weight: sitk.Image | None) -> np.ndarray | None:
    """Centroid (LPS mm) of the weight image's non-zero voxels, or ``None`` without a weight."""
    if weight is None:
        return None
    arr = sitk.GetArrayViewFromImage(weight)
    idx = np.argwhere(arr > 0)[:, ::-1].astype(np.float64)  # (x, y, z) indices
    if len(idx) == 0:
        return None
    to_mm = Grid.from_sitk(fixed).index_to_physical()
    return idx.mean(0) @ to_mm[:3, :3].T + to_mm[:3, 3]


def weight_on_grid(weights: Sequence[sitk.Image], grid: Grid) -> torch.Tensor | None:
    """The product of CT-frame weight images (match region, body; any grids) resampled onto ``grid``:
    ``[1, *grid.size]`` float32, or ``None`` without weights."""
    out = None
    for image in weights:
        on = sitk_on_grid(image, grid, "bilinear", 0.0)
        out = on if out is None else out * on
    return out

