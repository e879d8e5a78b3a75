"""The CT's bone on the CBCT's brightest voxels: a signal for anatomy that is not the CT's.

At a right pose the CT's bone lands on the brightest voxels of the CBCT; on another patient's anatomy, registered
as well as it goes, much of it does not (skulls differ in shape and thickness). A CBCT's values are not the CT's
Hounsfield units (scatter and beam hardening read the simulated CBCTs' skull several hundred HU below the CT's), so
the CBCT side is ranked rather than thresholded: :func:`bone_agreement` takes the CT's bone voxels in
view (above :data:`BONE_HU`), as many of the CBCT's brightest voxels among the same body voxels, and returns the
share of the CT's bone among them. Both volumes are smoothed by a 3-voxel box first (CBCT noise). Frames: both on
one grid in the CT frame, the CBCT resampled through the estimate (as :mod:`~monai_rigidreg.registration.tissue_air`).

Recorded in ``details.signals`` (``bone_share``, ``bone_agreement``) for the calibration; it flags nothing yet.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["BONE_HU", "BODY_HU", "bone_agreement"]

BONE_HU = 300.0
"""CT voxels above this (HU, after the box smoothing) are bone for :func:`bone_agreement`."""
BODY_HU = -300.0
"""CT voxels above this (HU, after the box smoothing) are the body whose CBCT voxels are ranked."""


def _box3(volume: torch.Tensor) -> torch.Tensor:
    """``[x, y, z]`` mean over each voxel's 3 x 3 x 3 box (edges replicated), as three sums of shifted slices instead
    of ``F.avg_pool3d`` with ``count_include_pad=False`` (the same values away from the grid's outer layer; on a 64^3
    grid 3.9 against 13 ms on one thread, measured once ad hoc on a loaded 2-core machine)."""
    out = volume
    for dim in range(3):
        n = out.shape[dim]
        pad = [0, 0, 0, 0, 0, 0]
        pad[2 * (2 - dim)] = pad[2 * (2 - dim) + 1] = 1
        padded = F.pad(out[None, None], pad, mode="replicate")[0, 0]
        out = (padded.narrow(dim, 0, n) + padded.narrow(dim, 1, n) + padded.narrow(dim, 2, n)) / 3.0
    return out


def bone_agreement(
    fixed: torch.Tensor, moved: torch.Tensor, fov: torch.Tensor, hu_range: tuple[float, float] = (-1000.0, 2000.0),
) -> tuple[float, float]:
    """``(bone_share, agreement)``: the CT's bone share of the body in view, and the share of that bone on the CBCT's
    brightest voxels.

    Args:
        fixed: ``[x, y, z]`` CT on the grid, HU normalized from ``hu_range`` to ``[0, 1]``.
        moved: ``[x, y, z]`` CBCT resampled through the estimate onto the same grid (any monotone intensity scale).
        fov: ``[x, y, z]`` the CBCT's field of view on the grid (> 0.5 inside), restricted to where the CT has data.
        hu_range: the CT's normalization window.

    ``bone_share`` is the CT's bone voxels (above :data:`BONE_HU`) over its body voxels (above :data:`BODY_HU`) in
    view; ``agreement`` the share of those bone voxels whose CBCT value is among the CBCT's ``k`` largest over the same
    body voxels, ``k`` the number of bone voxels (1.0: every bone voxel on the CBCT's brightest). NaN where fewer than
    1000 body or 100 bone voxels are in view (``bone_share`` NaN only without the body).

    >>> ct = torch.zeros(12, 12, 12) + 1000.0 / 3000.0  # water: 0 HU in the (-1000, 2000) window
    >>> ct[3:6] = 1700.0 / 3000.0  # a slab of bone, 700 HU, three planes of twelve
    >>> share, agree = bone_agreement(ct, ct.clone(), torch.ones(12, 12, 12))
    >>> round(share, 2), round(agree, 2)
    (0.25, 1.0)
    >>> round(bone_agreement(ct, ct.roll(6, 0), torch.ones(12, 12, 12))[1], 2)  # the CBCT's bone elsewhere
    0.0
    """
    lo, hi = hu_range
    f, m = _box3(fixed.float()), _box3(moved.float())
    body = (f > (BODY_HU - lo) / (hi - lo)) & (fov > 0.5)
    n = int(body.sum())
    if n < 1000:
        return float("nan"), float("nan")
    f_body, m_body = f[body], m[body]
    bone = f_body > (BONE_HU - lo) / (hi - lo)
    k = int(bone.sum())
    if k < 100:
        return k / n, float("nan")
    threshold = torch.kthvalue(m_body, n - k).values  # the k largest lie above it
    return k / n, float((m_body[bone] > threshold).float().mean())
