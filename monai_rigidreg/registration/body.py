"""The patient's body in a CT or CBCT, and what lies outside it (the couch), to exclude from the match.

The CT's couch and the treatment couch in the CBCT are rigid objects of the room: when the patient moves between
the planning CT and the CBCT, they do not, and a registration that matches them is pulled toward zero motion.
:func:`exclude_outside_body` sets everything farther than a margin outside the body to air in a copy of the image;
the registration applies it to both the CT and the CBCT before matching. :func:`couch_mask` shows what was removed.

:func:`body_mask`, on a working grid: the image block-averaged (``BinShrink``) by integer factors to a spacing of at
most ``working_spacing_mm`` (4 mm; a 3 mm grid is used as is):

1. threshold: above ``threshold_hu`` (-400 HU: soft tissue, fat and bone in; air, lung and couch foam out);
2. a binary opening with a ball about ``2 * opening_radius_mm`` wide (12-15 mm by default): plates, shells and rails
   thinner than that (couch tops, thermoplastic masks, the bright ring at a CBCT's field-of-view edge) vanish, and
   with them the thin bridges where the couch touches the patient;
3. the largest connected component (components of at least ``min_component_fraction`` of its volume are kept too);
4. a closing with a ball about ``2 * closing_radius_mm`` wide (skin folds, the navel, gas under the skin), then hole
   filling in every axial slice (across the index axis closest to LPS z): lungs, trachea and bowel gas stay inside.
   Slice by slice, because in 3D the airways open to the image border through the trachea or the nose;
5. an optional dilation by ``dilation_mm``; the mask is brought back to the input grid by trilinear interpolation
   thresholded at 0.5 (within 1-2 mm of the skin on a 4 mm working grid; Dice 0.99 with the truth on the tests'
   torsos).

Limits, measured on ``tests/test_body.py``'s torsos:

- where the couch touches the patient, the opening cannot separate them right at the contact: a strip of the couch
  top along the contact stays in the body. A couch touching an ellipsoidal torso at a point: 7 % of the couch's
  high-HU voxels in the body mask (0.4 % with a 1-2 mm gap), 9 % (1 %) left by :func:`exclude_outside_body`; a
  cylinder lying on it along its whole length, the worst case: 16 % (3 %), 19 % (4.5 %), all within 35 mm of the
  line of contact. A couch 10 mm away is removed entirely;
- air cavities separated from the outside by less than the opening's width (a chest wall thinner than 12-14 mm on
  the 4 mm working grid) are not holes after the opening and stay outside the body in those slices (the two real
  CTs of ``../shared/data``, thorax and abdomen, keep their lungs and bowel gas);
- CBCTs: outside the cylindrical field of view the reconstruction holds air (-1000 HU) and is outside the body; a
  body truncated by the field of view stays one component. Images whose outside-of-field value is not air (0, or
  padding above the threshold) need ``fov`` (a mask of the field of view). A lung cut by the edge of the field of
  view is not a hole in those slices either: it stays outside the body, and :func:`exclude_outside_body` sets its
  parenchyma and vessels to air in that image only.

Runtime: the opening, closing and dilation are numpy ORs / ANDs of shifted views over the ball's voxels
(:func:`_ball_filter`; the ball is ITK's own and the results are ITK's voxel for voxel, ``tests/test_body.py``):
:func:`coarse_body_mask` of the 256x256x141 thorax CT 0.06 s against 0.27 s with ITK's binary morphology filters
(``python -m benchmarks.speed.bench_network_paths``, 2 threads; ``docs/results.md``, "Speed").
"""

from __future__ import annotations

import functools
import hashlib
import logging
import math
from collections import OrderedDict

import numpy as np
import SimpleITK as sitk
import torch
import torch.nn.functional as F

__all__ = [
    "BODY_THRESHOLD_HU",
    "BodyMaskCache",
    "image_key",
    "body_mask",
    "couch_mask",
    "exclude_outside_body",
    "coarse_body_mask",
    "without_couch",
]

logger = logging.getLogger(__name__)

BODY_THRESHOLD_HU: float = -400.0
"""Default HU threshold between air (and lung, and couch foam) and the patient's tissue."""


def _above(image: sitk.Image, threshold: float) -> sitk.Image:
    """uint8 mask of ``image > threshold``, for any scalar pixel type.

    Compared in float32 (exact for HU): ``sitk.BinaryThreshold`` with an infinite upper bound silently clips it to 0
    on an int16 CT, and a comparison with a constant casts the constant to the pixel type (-400.5 to -400 on int16, a
    negative one wrapped on uint16).
    """
    if image.GetPixelID() not in (sitk.sitkFloat32, sitk.sitkFloat64):
        image = sitk.Cast(image, sitk.sitkFloat32)
    return sitk.Cast(image > threshold, sitk.sitkUInt8)


def _ball_radius_vox(radius_mm: float, spacing: tuple[float, ...]) -> list[int]:
    """Per-axis kernel radius (voxels) of a ball about ``2 * radius_mm`` wide: ``floor(radius_mm / spacing)``, at least
    1, so the kernel's width ``(2 floor(r / s) + 1) s`` lies in ``(2 r - s, 2 r + s]``."""
    return [max(1, int(radius_mm / s + 1e-6)) for s in spacing]


def _radius_vox(radius_mm: float, spacing: tuple[float, ...]) -> list[int]:
    """Per-axis kernel radius (voxels) of a ball reaching at least ``radius_mm``: ``ceil(radius_mm / spacing)``."""
    return [max(1, math.ceil(radius_mm / s - 1e-6)) for s in spacing]


@functools.lru_cache(maxsize=32)
def _ball_offsets(radius_xyz: tuple[int, int, int]) -> tuple[tuple[int, int, int], ...]:
    """Array-index offsets ``(z, y, x)``, from the kernel's corner, of SimpleITK's ball structuring element of per-axis
    radius ``radius_xyz`` (voxels, x y z order): read off by dilating a single voxel with ``sitk.BinaryDilate``, so the
    kernel is ITK's own (``tests/test_body.py`` checks the filters below against ITK's)."""
    r = radius_xyz[::-1]
    one = np.zeros([2 * a + 1 for a in r], dtype=np.uint8)
    one[tuple(r)] = 1
    kernel = sitk.BinaryDilate(sitk.GetImageFromArray(one), kernelRadius=list(radius_xyz), kernelType=sitk.sitkBall,
                               backgroundValue=0, foregroundValue=1)
    return tuple(tuple(int(i) for i in o) for o in np.argwhere(sitk.GetArrayViewFromImage(kernel)))


def _ball_filter(mask: np.ndarray, radius_xyz: list[int], dilate: bool, outside: bool) -> np.ndarray:
    """Binary dilation (``dilate``) or erosion of a bool ``[z, y, x]`` array by the ball of ``radius_xyz`` voxels,
    voxels beyond the array counting as ``outside``.

    One OR (AND) of shifted views per kernel voxel: the thorax CT's whole coarse body mask takes 0.07 s this way
    against 0.27 s with ITK's binary morphology filters (``benchmarks/speed/bench_network_paths.py``). Kernels are
    symmetric, so the shifted views need no mirroring.
    """
    r = radius_xyz[::-1]
    nz, ny, nx = mask.shape
    padded = np.pad(mask, [(a, a) for a in r], constant_values=outside)
    out = np.zeros_like(mask) if dilate else np.ones_like(mask)
    for dz, dy, dx in _ball_offsets(tuple(int(a) for a in radius_xyz)):
        view = padded[dz : dz + nz, dy : dy + ny, dx : dx + nx]
        if dilate:
            out |= view
        else:
            out &= view
    return out


def _opening(mask: np.ndarray, radius_xyz: list[int]) -> np.ndarray:
    """``sitk.BinaryMorphologicalOpening`` with a ball (erosion with the outside as foreground, then dilation)."""
    return _ball_filter(_ball_filter(mask, radius_xyz, False, True), radius_xyz, True, False)


def _closing(mask: np.ndarray, radius_xyz: list[int]) -> np.ndarray:
    """``sitk.BinaryMorphologicalClosing(safeBorder=True)`` with a ball: padded by the radius, dilated, eroded,
    cropped (the border does not erode what touches it)."""
    r = radius_xyz[::-1]
    padded = np.pad(mask, [(a, a) for a in r])
    closed = _ball_filter(_ball_filter(padded, radius_xyz, True, False), radius_xyz, False, True)
    return closed[r[0] : r[0] + mask.shape[0], r[1] : r[1] + mask.shape[1], r[2] : r[2] + mask.shape[2]]


def _like(array: np.ndarray, reference: sitk.Image) -> sitk.Image:
    """uint8 image of a bool ``[z, y, x]`` array on ``reference``'s grid."""
    out = sitk.GetImageFromArray(array.astype(np.uint8))
    out.CopyInformation(reference)
    return out


def _dilate(mask: sitk.Image, radius_mm: float) -> sitk.Image:
    """A uint8 0/1 mask dilated by a ball of ``radius_mm`` (rounded up to whole voxels per axis): ``sitk.BinaryDilate``
    with a ball, as shifted ORs (:func:`_ball_filter`)."""
    arr = sitk.GetArrayFromImage(mask) != 0
    return _like(_ball_filter(arr, _radius_vox(radius_mm, mask.GetSpacing()), True, False), mask)


def _axial_axis(image: sitk.Image) -> int:
    """Index axis (0, 1 or 2) closest to the physical (LPS) z axis: the slices of hole filling are across it."""
    direction = np.array(image.GetDirection()).reshape(3, 3)
    return int(np.argmax(np.abs(direction[2])))


def _fill_holes_slicewise(mask: sitk.Image, axis: int) -> sitk.Image:
    """Fill the holes of a uint8 0/1 mask in every 2-D slice across index axis ``axis``.

    The slices are stacked into one 2-D image, one background row between neighbours, and filled by a single
    ``BinaryFillhole``: a separator row touches the image border, so it plays the border's part for both slices and
    no hole spans two slices. numpy does the stacking (a reshape), which saves one filter call per slice.
    """
    arr = np.moveaxis(sitk.GetArrayFromImage(mask), 2 - axis, 0)  # [slice, rows, cols]; array axes are z, y, x
    n, rows, cols = arr.shape
    stacked = np.zeros((n, rows + 1, cols), dtype=np.uint8)
    stacked[:, :rows] = arr != 0
    filled = sitk.BinaryFillhole(sitk.GetImageFromArray(stacked.reshape(n * (rows + 1), cols)), fullyConnected=False,
                                 foregroundValue=1)
    back = sitk.GetArrayFromImage(filled).reshape(n, rows + 1, cols)[:, :rows]
    out = sitk.GetImageFromArray(np.ascontiguousarray(np.moveaxis(back, 0, 2 - axis)).astype(np.uint8))
    out.CopyInformation(mask)
    return out


def _block_factors(image: sitk.Image, working_spacing_mm: float) -> list[int]:
    """Integer block sizes per axis that bring ``image``'s spacing to at most ``working_spacing_mm``."""
    return [max(1, int(working_spacing_mm / s + 1e-6)) for s in image.GetSpacing()]


def _shrink(image: sitk.Image, factors: list[int]) -> sitk.Image:
    """float32 copy of ``image`` block-averaged by ``factors`` (``BinShrink``: voxel centres at the block centres)."""
    small = sitk.BinShrink(image, factors) if max(factors) > 1 else image
    return sitk.Cast(small, sitk.sitkFloat32)


def _expand(mask: sitk.Image, factors: list[int], reference: sitk.Image, linear: bool = True) -> sitk.Image:
    """uint8 0/1 mask on ``reference``'s grid from a 0/1 mask on its ``BinShrink`` grid of block sizes ``factors``.

    ``linear``: trilinear interpolation thresholded at 0.5 (the boundary passes half-way between coarse voxel
    centres); otherwise every block takes its coarse voxel's value. Voxels past the last whole block take the last
    block's values. torch ``interpolate`` and numpy rather than ``sitk.Resample``: the grids are aligned blocks, and
    on a 512x512x112 CT this takes 0.45 s instead of 1.0-1.4 s (one thread).
    """
    small = sitk.GetArrayFromImage(mask).astype(np.float32)  # [z, y, x]
    f_zyx = factors[::-1]
    if max(factors) == 1:
        up = small >= 0.5
    elif linear:
        size = [n * f for n, f in zip(small.shape, f_zyx)]
        t = F.interpolate(torch.from_numpy(small)[None, None], size=size, mode="trilinear", align_corners=False)
        up = (t[0, 0] >= 0.5).numpy()
    else:
        up = small >= 0.5
        for axis, f in enumerate(f_zyx):
            up = up.repeat(f, axis=axis)
    full = sitk.GetArrayViewFromImage(reference).shape
    up = np.pad(up, [(0, n - m) for n, m in zip(full, up.shape)], mode="edge")
    out = sitk.GetImageFromArray(up.astype(np.uint8))
    out.CopyInformation(reference)
    return out


def _dilate_fast(mask: sitk.Image, radius_mm: float, working_spacing_mm: float) -> sitk.Image:
    """``mask`` (0/1) dilated by at least ``radius_mm`` and at most ``radius_mm`` plus two voxels of the working grid.

    A ball of 4 mm on a 512x512x112 grid of 0.7 x 0.6 x 3 mm costs about 3 s; on the working grid (blocks holding any
    mask voxel, dilated, expanded back, joined with the mask) it costs a fraction of a second.
    """
    factors = _block_factors(mask, working_spacing_mm)
    binary = sitk.Cast(mask != 0, sitk.sitkUInt8)
    if max(factors) == 1:
        return _dilate(binary, radius_mm)
    any_in_block = sitk.Cast(_shrink(binary, factors) > 0, sitk.sitkUInt8)
    return sitk.Or(_expand(_dilate(any_in_block, radius_mm), factors, mask, linear=False), binary)


def body_mask(
    image: sitk.Image,
    threshold_hu: float = BODY_THRESHOLD_HU,
    opening_radius_mm: float = 6.0,
    closing_radius_mm: float = 8.0,
    dilation_mm: float = 0.0,
    working_spacing_mm: float = 4.0,
    min_component_fraction: float = 1.0,
    fov: sitk.Image | None = None,
) -> sitk.Image:
    """uint8 mask (0/1) of the patient's body on ``image``'s grid: the steps of the module docstring.

    Args:
        image: a CT or CBCT in HU, any pixel type and geometry (the geometry decides only the slicing axis of the hole
            filling: the index axis closest to LPS z).
        threshold_hu: voxels above it are tissue.
        opening_radius_mm: half the width of the opening's ball (mm): structures thinner than about twice it are
            cut. On the working grid of spacing ``s`` the ball is ``2 floor(r / s) + 1`` voxels wide (at least 3):
            6 mm gives 12 mm on a 4 mm grid, 15 mm on 3 mm, 14 mm on 2 mm.
        closing_radius_mm: half the width of the closing's ball (mm, same rounding: 8 mm gives 20, 15 and 18 mm); 0
            skips the closing.
        dilation_mm: final dilation of the body (mm, on the working grid, rounded up to whole voxels); 0 for none.
        working_spacing_mm: the image is block-averaged by integer factors to a spacing of at most this (a 1 mm grid
            is processed at 4 mm, a 3 mm grid as is).
        min_component_fraction: components of the opened mask whose volume is at least this fraction of the largest
            one's are kept too (1.0: only the largest; 0.3 would keep the second leg of a scan below the pelvis).
        fov: optional mask on ``image``'s grid of the field of view; voxels outside it are never body.

    Returns:
        uint8 image, 1 in the body, same size, spacing, origin and direction as ``image``; all 0 (with a warning)
        when nothing above ``threshold_hu`` survives the opening.
    """
    factors = _block_factors(image, working_spacing_mm)
    work = _shrink(image, factors)
    spacing = work.GetSpacing()
    mask = _above(work, threshold_hu)
    fov_full = None if fov is None else sitk.Cast(fov != 0, sitk.sitkUInt8)
    if fov_full is not None:  # a working voxel is in the field of view when most of its block is
        mask = sitk.And(mask, sitk.Cast(_shrink(fov_full, factors) >= 0.5, sitk.sitkUInt8))
    if opening_radius_mm > 0:
        mask = _like(_opening(sitk.GetArrayFromImage(mask) != 0, _ball_radius_vox(opening_radius_mm, spacing)), mask)
    relabel = sitk.RelabelComponentImageFilter()  # labels 1, 2, ... by decreasing size (voxels of one grid: volume)
    relabel.SetSortByObjectSize(True)
    labels = relabel.Execute(sitk.ConnectedComponent(mask))
    counts = list(relabel.GetSizeOfObjectsInPixels())
    if not counts:
        logger.warning("nothing above %s HU survived the opening: empty body mask", threshold_hu)
        return _expand(mask * 0, factors, image)
    keep = sum(1 for c in counts if c >= min_component_fraction * counts[0])
    mask = sitk.BinaryThreshold(labels, lowerThreshold=1, upperThreshold=keep, insideValue=1, outsideValue=0)
    if closing_radius_mm > 0:
        mask = _like(_closing(sitk.GetArrayFromImage(mask) != 0, _ball_radius_vox(closing_radius_mm, spacing)), mask)
    mask = _fill_holes_slicewise(mask, _axial_axis(work))
    if dilation_mm > 0:
        mask = _dilate(mask, dilation_mm)
    out = _expand(mask, factors, image)
    return out if fov_full is None else sitk.And(out, fov_full)


def couch_mask(
    image: sitk.Image,
    body: sitk.Image | None = None,
    threshold_hu: float = BODY_THRESHOLD_HU,
    margin_mm: float = 3.0,
    working_spacing_mm: float = 4.0,
) -> sitk.Image:
    """uint8 mask (0/1) of what is above ``threshold_hu`` but not the body: couch, rails, devices outside the body.

    Args:
        image: a CT or CBCT in HU.
        body: its body mask (:func:`body_mask`); computed with the defaults when ``None``.
        threshold_hu: voxels above it are tissue or couch.
        margin_mm: voxels within this distance (mm) of the body are not couch: the body mask's boundary is that of
            the working grid (within 1-2 mm of the skin), and without a margin the skin itself shows as a rim of
            "couch". 0: none.
        working_spacing_mm: grid of the margin's dilation (the margin is exact to two voxels of it).

    Returns:
        uint8 image on ``image``'s grid.
    """
    if body is None:
        body = body_mask(image, threshold_hu=threshold_hu, working_spacing_mm=working_spacing_mm)
    if margin_mm > 0:
        body = _dilate_fast(body, margin_mm, working_spacing_mm)
    return sitk.And(_above(image, threshold_hu), sitk.Cast(body == 0, sitk.sitkUInt8))


def exclude_outside_body(
    image: sitk.Image,
    body: sitk.Image | None = None,
    margin_mm: float = 3.0,
    fill_hu: float = -1000.0,
    working_spacing_mm: float = 4.0,
) -> sitk.Image:
    """Copy of ``image`` with every voxel more than ``margin_mm`` outside the body set to ``fill_hu``.

    Body voxels and those within the margin (which keeps the skin's edge whole for the matching) are unchanged;
    the couch, its rails and devices away from the body become air.

    Args:
        image: a CT or CBCT in HU.
        body: its body mask (undilated); when ``None``, :func:`body_mask` ``(image, dilation_mm=margin_mm)``.
        margin_mm: dilation of the body (mm), at least this much. Done on the working grid: a given mask grows by
            ``margin_mm`` to ``margin_mm`` plus two working voxels (in the tests, a 4 mm margin on a 2 mm grid kept
            4.9-7.2 mm); the default mask by ``margin_mm`` rounded up to whole working voxels (3 mm: 3 mm on a 3 mm
            grid, 4 mm on a 4 mm one).
        fill_hu: value written outside (air).
        working_spacing_mm: grid of the body mask and of the dilation.

    Returns:
        image of ``image``'s pixel type and grid; ``image`` itself when the body mask is empty (nothing to protect:
        blanking the whole image would be worse), with a warning.
    """
    if body is None:
        keep = body_mask(image, dilation_mm=margin_mm, working_spacing_mm=working_spacing_mm)
    elif margin_mm > 0:
        keep = _dilate_fast(body, margin_mm, working_spacing_mm)
    else:
        keep = sitk.Cast(body != 0, sitk.sitkUInt8)
    if not np.any(sitk.GetArrayViewFromImage(keep)):
        logger.warning("empty body mask: nothing excluded")
        return image
    return sitk.Mask(image, keep, outsideValue=fill_hu, maskingValue=0)


def coarse_body_mask(
    image: sitk.Image,
    fov: sitk.Image | None = None,
    margin_mm: float = 4.0,
    working_spacing_mm: float = 4.0,
    threshold_hu: float = BODY_THRESHOLD_HU,
) -> sitk.Image | None:
    """The body (dilated by ``margin_mm``) as a uint8 mask on the coarse working grid, not brought back to the
    input grid: what the registration multiplies into the volumes it resamples onto its own, coarser grids
    (the network grid, the global search), so the couch is excluded without a full-resolution pass.

    Args:
        image: a CT or CBCT in HU.
        fov: optional field-of-view mask on ``image``'s grid (a CBCT whose outside is not air).
        margin_mm: dilation (keeps the skin's edge for the matching).
        working_spacing_mm: the coarse grid (``BinShrink`` by integer factors).
        threshold_hu: tissue threshold of :func:`body_mask`.

    Returns:
        uint8 mask on the block-averaged grid, or ``None`` when nothing is body (then nothing should be excluded).
    """
    factors = _block_factors(image, working_spacing_mm)
    work = _shrink(image, factors)
    fov_work = None
    if fov is not None:
        fov_work = sitk.Cast(_shrink(sitk.Cast(fov != 0, sitk.sitkUInt8), factors) >= 0.5, sitk.sitkUInt8)
    mask = body_mask(work, threshold_hu=threshold_hu, dilation_mm=margin_mm, working_spacing_mm=working_spacing_mm,
                     fov=fov_work)
    if not np.any(sitk.GetArrayViewFromImage(mask)):
        logger.warning("empty body mask: the couch is not excluded")
        return None
    return mask


def without_couch(volume: torch.Tensor, body: torch.Tensor, hu_range: tuple[float, float]) -> torch.Tensor:
    """``volume`` (normalized HU) with its tissue-like voxels (above :data:`BODY_THRESHOLD_HU`)
    outside ``body`` (a mask sampled on the same grid) set to air. Only tissue-like voxels: a CBCT's lung cut by its
    field of view lies outside its body mask (not a hole there) but keeps its parenchyma; its vessels are lost."""
    level = (BODY_THRESHOLD_HU - hu_range[0]) / (hu_range[1] - hu_range[0])
    return torch.where((body < 0.5) & (volume > level), torch.zeros_like(volume), volume)


def image_key(image: sitk.Image) -> tuple:
    """A key that tells two images apart by geometry, pixel type and content (a SHA-256 digest of the voxels: with
    the CPU's SHA instructions faster than BLAKE2b, 0.031 s against 0.041 s for the 256x256x141 thorax CT,
    ``benchmarks/speed/bench_network_paths.py``'s image-key row)."""
    digest = hashlib.sha256(np.ascontiguousarray(sitk.GetArrayViewFromImage(image)).data).hexdigest()
    return (image.GetSize(), image.GetSpacing(), image.GetOrigin(), image.GetDirection(),
            image.GetPixelIDValue(), digest)


class BodyMaskCache:
    """:func:`coarse_body_mask` of the last ``maxsize`` CTs, keyed by :func:`image_key`.

    A clinic registers the CBCT of every fraction to the same planning CT: the CT's body mask (0.4 s for the
    256x256x141 thorax CT on 2 cores, ``benchmarks/speed/bench_speed.py``) is computed for its first CBCT only. Not
    thread-safe on its own (the registrar calls it under its lock).
    """

    def __init__(self, maxsize: int = 4) -> None:
        self.maxsize = int(maxsize)
        self._masks: OrderedDict[tuple, sitk.Image | None] = OrderedDict()
        self.hits = 0

    def __call__(self, image: sitk.Image) -> sitk.Image | None:
        """The coarse body mask of ``image`` (``None`` when nothing is body), computed on the first call."""
        key = image_key(image)
        if key in self._masks:
            self._masks.move_to_end(key)
            self.hits += 1
            return self._masks[key]
        mask = coarse_body_mask(image)
        self._masks[key] = mask
        while len(self._masks) > self.maxsize:
            self._masks.popitem(last=False)
        return mask
