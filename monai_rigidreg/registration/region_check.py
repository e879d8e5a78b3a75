"""Residual displacement of the structures inside a match region after a rigid estimate (block matching).

With a region of interest (``--roi``) the registrar is asked to match the target region; on anatomy that changed
between the scans no rigid transform matches all of it, and on flat soft tissue (a head's brain plateau) every
image-similarity signal can sit at an optimum that leaves the region's structures millimetres off. This check asks
the structures themselves: the region is cut into blocks (a 3 x 3 x 3 layout of 24 mm cubes by default), the CT
block and the CBCT mapped through the estimate are compared at every integer shift within +-10 mm by normalized
cross-correlation (one grouped 3D convolution for all blocks), the peak is refined to sub-voxel precision by a
parabola per axis, and the blocks with structure (CT contrast >= 50 HU standard deviation, peak NCC >= 0.5, the
search window inside the CBCT's field of view) vote. The weighted median of their shifts (per axis; weights
``contrast^2 * peak^2``) is how far, in the CT frame, the estimate leaves the region's structures from where the
CBCT shows them: ``T_true ~ T_est o translate(shift)``.

Why a median of block shifts and not a correction: measured on the clinical-geometry deformed pairs (seeds 1500 and
2500, 20 pairs; ``python -m benchmarks.confidence.bench_confidence_clinical --pairs-dir ... --groups deformed``), the
median shift is 0.1-2.1 mm on every pair whose landmark error is within 2 mm of the best rigid fit and 3.5-4.1 mm on the
failures it votes on (``docs/results.md``, "Confidence"), while applying the shift as a translation (iterated; an
experiment, not kept) made two head pairs worse: the blocks on flat tissue are reliable enough to say "off by more than
a clinical tolerance", not to steer. In the same (ad-hoc, unscripted) experiment a weighted mean
instead of the median let one flat block's spurious peak push a correct pair far past the limit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
import torch
import torch.nn.functional as F

from monai_rigidreg.core.geometry import Grid, transform_points
from monai_rigidreg.core.grid_sampling import sitk_on_grid
from monai_rigidreg.core.image_ops import subvoxel_peaks

__all__ = ["REGION_SHIFT_LIMIT_MM", "MIN_BLOCKS", "BlockShifts", "region_bounds", "block_shifts"]

REGION_SHIFT_LIMIT_MM = 3.0
"""Median residual shift of the region's structures (mm) that scores 0.5 in
:func:`~monai_rigidreg.registration.confidence.confidence_score`: a common clinical action level for a target-region
match. On the 20 clinical-geometry deformed pairs of seeds 1500 and 2500 the successes measured 0.1-2.1 mm and the
failures it voted on 3.5-4.1 mm (module docstring)."""
MIN_BLOCKS = 5
"""Fewer blocks with structure than this: the check abstains (NaN): a shift voted by one or two blocks on flat tissue
is not evidence (on the head pairs' flat brain one or two blocks often vote, and their reading there is noise)."""


@dataclass
class BlockShifts:
    """Per-block results of :func:`block_shifts` (``B`` blocks).

    Attributes:
        centers: ``[B, 3]`` block centres, CT LPS mm.
        shifts: ``[B, 3]`` shift ``d`` (mm, CT frame) that best aligns the CT block at ``x`` with the CBCT at
            ``T_est(x + d)``.
        peak: ``[B]`` peak NCC.
        contrast: ``[B]`` standard deviation of the CT block (HU).
        used: ``[B]`` whether the block votes (structure, a clear peak, inside the field of view and the region).
    """

    centers: np.ndarray
    shifts: np.ndarray
    peak: np.ndarray
    contrast: np.ndarray
    used: np.ndarray

    @property
    def count(self) -> int:
        """Number of voting blocks."""
        return int(self.used.sum())

    def median_shift(self, min_blocks: int = MIN_BLOCKS) -> np.ndarray:
        """Weighted median per axis of the voting blocks' shifts (``[3]`` mm, CT frame; weights ``contrast^2 *
        peak^2``), NaN with fewer than ``min_blocks`` voting blocks."""
        if self.count < max(1, min_blocks):
            return np.full(3, np.nan)
        w = (self.contrast[self.used] / 100.0) ** 2 * self.peak[self.used] ** 2
        out = np.empty(3)
        for a in range(3):
            x = self.shifts[self.used, a]
            order = np.argsort(x)
            cw = np.cumsum(w[order])
            out[a] = x[order][int(np.searchsorted(cw, 0.5 * cw[-1]))]
        return out


def region_bounds(region: sitk.Image) -> tuple[np.ndarray, np.ndarray] | None:
    """Axis-aligned LPS bounding box ``(lo, hi)`` (mm) of a mask's non-zero voxel centres, ``None`` if empty."""
    arr = sitk.GetArrayViewFromImage(region)
    nz = np.argwhere(arr > 0.5)
    if len(nz) == 0:
        return None
    lo_i, hi_i = nz.min(0)[::-1], nz.max(0)[::-1]  # (x, y, z) indices
    corners = np.array(np.meshgrid(*[[lo_i[a], hi_i[a]] for a in range(3)], indexing="ij")).reshape(3, -1).T
    pts = transform_points(Grid.from_sitk(region).index_to_physical(), corners.astype(np.float64))
    return pts.min(0), pts.max(0)


def block_shifts(fixed: sitk.Image, moving: sitk.Image, fixed_to_moving: np.ndarray, region: sitk.Image,
                 moving_fov: sitk.Image | None = None, spacing_mm: float = 2.0, block_mm: float = 24.0,
                 search_mm: float = 10.0, blocks_per_axis: int = 3, hu_window: tuple[float, float] = (-1000.0, 1000.0),
                 min_contrast_hu: float = 50.0, min_peak: float = 0.5) -> BlockShifts:
    """Block matching inside a match region after a rigid estimate.

    Args:
        fixed: planning CT (HU).
        moving: CBCT (HU).
        fixed_to_moving: 4x4 estimate, CT LPS mm -> CBCT LPS mm.
        region: CT-frame mask (any grid; > 0.5 inside): the blocks tile its axis-aligned bounding box and a block
            votes only if at least half of its voxels lie inside it.
        moving_fov: CBCT field-of-view mask (CBCT frame); a block votes only if its whole search window lies
            inside (``None``: no such restriction).
        spacing_mm: sampling grid spacing (an axis-aligned LPS grid in the CT frame).
        block_mm: block edge length; ``search_mm``: the largest shift tried along each axis.
        blocks_per_axis: the most blocks along each axis (their centres spread evenly over the region's box, no
            closer than half a block; a box smaller than a block gets one block on that axis).
        hu_window: intensities are clipped to this window before matching.
        min_contrast_hu: a block whose CT standard deviation is below this (flat tissue) does not vote.
        min_peak: a block whose best NCC is below this does not vote.

    Returns:
        :class:`BlockShifts`.
    """
    bounds = region_bounds(region)
    if bounds is None:
        raise ValueError("the match region is empty")
    lo, hi = bounds
    b = max(3, int(round(block_mm / spacing_mm)))
    r = max(1, int(round(search_mm / spacing_mm)))
    half = (b - 1) / 2.0 * spacing_mm
    centers_axes = []
    for a in range(3):
        c0, c1 = lo[a] + half, hi[a] - half
        # at most blocks_per_axis, and no closer than half a block: on a small box, heavily overlapping blocks would
        # count one structure (or one spurious peak) several times towards MIN_BLOCKS and the median
        n = min(blocks_per_axis, 1 + int(np.floor((c1 - c0) / (half + 0.5 * spacing_mm) + 1e-9))) if c1 > c0 else 1
        centers_axes.append(np.linspace(c0, c1, n) if n > 1 else np.array([(lo[a] + hi[a]) / 2.0]))
    centers = np.array(np.meshgrid(*centers_axes, indexing="ij")).reshape(3, -1).T
    # one sampling grid over every block and its search margin; each block's corner snapped to it
    g_lo = centers.min(0) - half - r * spacing_mm
    size = np.ceil((centers.max(0) + half + r * spacing_mm - g_lo) / spacing_mm).astype(int) + 1
    grid = Grid(tuple(int(s) for s in size), (spacing_mm,) * 3, tuple(g_lo))
    # both images on the grid through grid_sampling (the one resampling path; plain trilinear, no anti-aliasing:
    # the blocks are compared at the CBCT's own 2 mm)
    f = sitk_on_grid(fixed, grid, "bilinear", hu_window[0], antialias=False)[0]
    m = sitk_on_grid(moving, grid, "bilinear", hu_window[0], antialias=False, matrix=fixed_to_moving)[0]
    f, m = f.clamp(*hu_window), m.clamp(*hu_window)
    reg = sitk_on_grid(region, grid, "nearest", 0.0)[0] > 0.5
    fov = None
    if moving_fov is not None:
        fov = sitk_on_grid(moving_fov, grid, "nearest", 0.0, matrix=fixed_to_moving)[0] > 0.5
    corner = np.round((centers - half - g_lo) / spacing_mm).astype(int)  # block start (index) per block
    templates, windows, in_region, in_fov = [], [], [], []
    for i, j, k in corner:
        templates.append(f[i:i + b, j:j + b, k:k + b])
        windows.append(m[i - r:i + b + r, j - r:j + b + r, k - r:k + b + r])
        in_region.append(float(reg[i:i + b, j:j + b, k:k + b].float().mean()) >= 0.5)
        in_fov.append(True if fov is None else bool(fov[i - r:i + b + r, j - r:j + b + r, k - r:k + b + r].all()))
    t = torch.stack(templates)  # [B, b, b, b]
    s = torch.stack(windows)[None]  # [1, B, S, S, S]
    n = float(b**3)
    contrast = t.flatten(1).std(1)
    tz = (t - t.flatten(1).mean(1)[:, None, None, None]) / contrast.clamp_min(1e-6)[:, None, None, None]
    # NCC at every shift: sum(s * tz) / (n * std(s)); local sums of s and s^2 by average pooling
    num = F.conv3d(s, tz[:, None], groups=t.shape[0])[0]  # [B, 2r+1, 2r+1, 2r+1]
    mean_s = F.avg_pool3d(s, b, stride=1)[0]
    var_s = (F.avg_pool3d(s * s, b, stride=1)[0] - mean_s**2)
    # windows without contrast (air, a flat plateau) give no peak: NCC -1 there (20 HU standard deviation)
    ncc = torch.where(var_s > 400.0, num / (n * var_s.clamp_min(1e-6).sqrt()), torch.full_like(var_s, -1.0))
    sub, peak_np = subvoxel_peaks(ncc)  # the best shift per block, sub-voxel (a parabola per axis)
    shifts = (sub - r) * spacing_mm
    contrast_np = contrast.double().numpy()
    used = (contrast_np >= min_contrast_hu) & (peak_np >= min_peak) & np.array(in_region) & np.array(in_fov)
    # the block centres on the sampling grid (the snapped corners)
    snapped = g_lo + (corner + (b - 1) / 2.0) * spacing_mm
    return BlockShifts(snapped, shifts, peak_np, contrast_np, used)
