"""Overlay images of registered cases for the evaluation's ``report.html``: the fixed CT in red, the moving CBCT
resampled with a method's estimate in green, axial/coronal/sagittal through the CBCT centre as registered.

:class:`OverlayGallery` draws them while :func:`~monai_rigidreg.evaluation.evaluate.evaluate_datalist` has the
volumes in memory: every failed or flagged case, plus up to ``max_others`` of the rest, so that a large evaluation
writes a bounded number of small PNGs.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.geometry import Grid, params_to_sitk
from monai_rigidreg.evaluation.report import CaseResult
from monai_rigidreg.export.qc_figure import orthogonal_slices
from monai_rigidreg.io.volumes import resample

__all__ = [
    "OverlayGallery",
    "overlay_image",
    "write_overlay_png",
    "overlay_methods",
    "needs_attention",
    "OVERLAY_DIR",
    "OVERLAY_MAX_PX",
    "OVERLAY_MAX_BYTES",
    "DEFAULT_MAX_OVERLAYS",
]

OVERLAY_DIR = "report_files"
"""Folder (next to ``report.html``) that holds the overlay PNGs."""

OVERLAY_MAX_PX = 160
"""Longest side, in pixels, of each of the three views of an overlay (the fixed image's extent at that size)."""

OVERLAY_MAX_BYTES = 60_000
"""Size an overlay PNG should stay under (its intensity levels are reduced until it does)."""

DEFAULT_MAX_OVERLAYS = 20
"""Overlays drawn for cases that neither failed nor were flagged (those always get theirs)."""

_FILE_PATTERN = re.compile(r"^\d{5}_[A-Za-z0-9._+-]*\.png$")
_UNSAFE = re.compile(r"[^A-Za-z0-9._+-]+")
_GAP_PX = 2


def needs_attention(case: CaseResult) -> bool:
    """Whether a result failed (TRE not below :data:`SUCCESS_TRE_MM`, or not finite) or was flagged."""
    return (not case.success) or bool(case.extra.get("flagged", False))


def overlay_methods(methods: Iterable[str]) -> list[str]:
    """Methods whose results get overlays in cases that neither failed nor were flagged (within the cap): the network
    methods run, or every method when none of them is a network. A failed or flagged result gets one whatever its
    method (a baseline's failure too)."""
    methods = list(dict.fromkeys(methods))
    network = [m for m in methods if m.startswith("network")]
    return network or methods


def _display_grid(fixed: sitk.Image, max_px: int) -> Grid:
    """Isotropic grid over the fixed image's extent (same direction and centre), at most ``max_px`` voxels along
    an axis and never finer than the fixed image's finest spacing."""
    size = np.asarray(fixed.GetSize(), dtype=np.float64)
    spacing = np.asarray(fixed.GetSpacing(), dtype=np.float64)
    length = size * spacing
    step = max(float(spacing.min()), float(length.max()) / max(int(max_px), 1))
    n = np.maximum(1, np.round(length / step)).astype(int)
    direction = np.asarray(fixed.GetDirection(), dtype=np.float64).reshape(3, 3)
    center = Grid.from_sitk(fixed).center()
    origin = center - direction @ ((n - 1) / 2.0 * step)
    return Grid(tuple(n), (step, step, step), tuple(origin), fixed.GetDirection())


def _smoothed_for(image: sitk.Image, step: float) -> sitk.Image:
    """``image`` low-passed before it is sampled at ``step`` mm when that is much coarser than its voxels."""
    finest = min(image.GetSpacing())
    if step <= 1.5 * finest:
        return image
    return sitk.SmoothingRecursiveGaussian(sitk.Cast(image, sitk.sitkFloat32), 0.5 * step)


def _window(arr: np.ndarray) -> np.ndarray:
    """``arr`` scaled to [0, 1] between its 1st and 99th percentiles (NaN, outside the field of view, to 0)."""
    finite = arr[np.isfinite(arr)]
    if finite.size == 0:
        return np.zeros(arr.shape, dtype=np.float32)
    lo, hi = np.percentile(finite, [1, 99])
    out = np.clip((arr - lo) / max(float(hi - lo), 1e-6), 0.0, 1.0)
    return np.nan_to_num(out, nan=0.0).astype(np.float32)


def _fixed_display(fixed: sitk.Image, max_px: int) -> tuple[sitk.Image, np.ndarray]:
    """The fixed image on its display grid, and that image windowed to [0, 1] (``[z, y, x]``)."""
    grid = _display_grid(fixed, max_px)
    ref = resample(_smoothed_for(fixed, grid.spacing[0]), grid, None, pixel_type=sitk.sitkFloat32)
    return ref, _window(sitk.GetArrayFromImage(ref))


def overlay_image(
    fixed: sitk.Image,
    moving: sitk.Image,
    params: Sequence[float],
    center: Sequence[float],
    max_px: int = OVERLAY_MAX_PX,
    _display: tuple[sitk.Image, np.ndarray] | None = None,
) -> np.ndarray:
    """RGB overlay (uint8 ``[rows, columns, 3]``) of the fixed CT (red) and the moving CBCT resampled onto it
    with ``params`` about ``center`` (green; yellow where both are bright): axial, coronal and sagittal views side
    by side, through the CBCT's centre as registered, at an isotropic display spacing (``max_px`` pixels at most
    along the fixed image's longest side). The CBCT is dark outside its field of view.

    Args:
        fixed, moving: the volumes (``SimpleITK.Image``, LPS).
        params: ``(tx, ty, tz, rx, ry, rz)`` (mm / degrees), fixed -> moving, about ``center``.
        center: rotation centre (LPS mm), as in the evaluation (the fixed image centre).
        max_px: longest side of a view, in pixels.
    """
    ref, fixed_disp = _fixed_display(fixed, max_px) if _display is None else _display
    tfm = params_to_sitk(params, center)
    moved = resample(_smoothed_for(moving, ref.GetSpacing()[0]), ref, tfm, default_value=float("nan"),
                     pixel_type=sitk.sitkFloat32)
    # the CBCT centre c_m lies at T^-1(c_m) in the fixed frame once registered
    c_m = moving.TransformContinuousIndexToPhysicalPoint([(n - 1) / 2.0 for n in moving.GetSize()])
    idx = ref.TransformPhysicalPointToIndex(tfm.GetInverse().TransformPoint(c_m))
    center_index = tuple(int(np.clip(i, 0, n - 1)) for i, n in zip(idx, ref.GetSize()))
    red_img = sitk.GetImageFromArray(fixed_disp)
    red_img.CopyInformation(ref)
    green_img = sitk.GetImageFromArray(_window(sitk.GetArrayFromImage(moved)))
    green_img.CopyInformation(ref)
    views = [np.stack([r, g, np.zeros_like(r)], axis=-1)
             for r, g in zip(orthogonal_slices(red_img, center_index), orthogonal_slices(green_img, center_index))]
    rows = max(v.shape[0] for v in views)
    cols = sum(v.shape[1] for v in views) + _GAP_PX * (len(views) - 1)
    out = np.full((rows, cols, 3), 0.25, dtype=np.float32)  # dark grey gaps and padding
    x = 0
    for v in views:
        top = (rows - v.shape[0]) // 2
        out[top: top + v.shape[0], x: x + v.shape[1]] = v
        x += v.shape[1] + _GAP_PX
    return np.round(out * 255).astype(np.uint8)


def write_overlay_png(rgb: np.ndarray, path: str | Path, max_bytes: int = OVERLAY_MAX_BYTES) -> Path:
    """Write a uint8 ``[rows, columns, 3]`` array as a compressed PNG (SimpleITK's writer; no plotting stack).

    The intensities are stored at 64 levels per channel (invisible in an overlay, and a quarter smaller than 256);
    should the file still exceed ``max_bytes``, at 32, then 16, 8 levels.
    """
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    rgb = np.asarray(rgb, dtype=np.uint8)
    for step in (4, 8, 16, 32):
        levels = (rgb // step) * step + step // 2
        img = sitk.GetImageFromArray(np.ascontiguousarray(levels, dtype=np.uint8), isVector=True)
        sitk.WriteImage(img, str(p), True)
        if p.stat().st_size <= max_bytes:
            break
    return p


class OverlayGallery:
    """Overlays of the evaluated cases, drawn case by case while the volumes are loaded.

    Every result that failed or was flagged gets an overlay, whatever its method (SimpleITK's and elastix's
    failures too), and so do :func:`overlay_methods`'s results of its case, to compare; of the other cases, the
    first ``max_others`` get overlays of :func:`overlay_methods`'s results. One PNG per result drawn, named
    ``NNNNN_<case>_<method>.png`` (``NNNNN``:
    the result's index in the list of results). After the last case, :meth:`finish` removes PNGs of that pattern
    left in ``folder`` by an earlier run, so that it holds this run's overlays only; after a failure,
    :meth:`discard` removes this run's PNGs and the folders it made, so that a failed run leaves no partial output.

    Args:
        folder: where the PNGs go (``<output_dir>/report_files``).
        methods: the evaluated methods (filtered with :func:`overlay_methods`).
        max_others: overlays for cases that neither failed nor were flagged (0: problem cases only).
        max_px: longest side of a view, in pixels.

    Attributes:
        images: result index -> PNG path. omitted: results of the overlay methods left without one (the cap).
    """

    def __init__(self, folder: str | Path, methods: Iterable[str], max_others: int = DEFAULT_MAX_OVERLAYS,
                 max_px: int = OVERLAY_MAX_PX) -> None:
        if isinstance(max_others, bool) or not isinstance(max_others, (int, np.integer)) or max_others < 0:
            raise ValueError(f"max_others must be a whole number >= 0, got {max_others!r}")
        self.folder = Path(folder)
        self.methods = overlay_methods(methods)
        self.max_others = int(max_others)
        self.max_px = int(max_px)
        self.images: dict[int, Path] = {}
        self.omitted = 0
        self._others = 0
        self._made: list[Path] = []
        self._display_key: tuple[int, tuple] | None = None
        self._display: tuple[sitk.Image, np.ndarray] | None = None

    def add(self, fixed: sitk.Image, moving: sitk.Image, center: Sequence[float],
            results: Sequence[tuple[int, CaseResult]]) -> list[Path]:
        """Draw the overlays of one case: ``results`` are its ``(index, CaseResult)`` pairs (one per method)."""
        attention = [(i, c) for i, c in results if needs_attention(c)]  # failed or flagged, any method
        others = [(i, c) for i, c in results if c.method in self.methods and not needs_attention(c)]
        if not attention:  # nothing went wrong in this case: the overlay methods' results, within the cap
            if not others:
                return []
            if self._others >= self.max_others:
                self.omitted += len(others)
                return []
            self._others += 1
        chosen = sorted(attention + others, key=lambda item: item[0])
        display = self._display_of(fixed)
        written = []
        for i, c in chosen:
            rgb = overlay_image(fixed, moving, c.params_pred, center, self.max_px, _display=display)
            name = _UNSAFE.sub("_", f"{c.case_id}_{c.method}").strip("_")[:80]
            written.append(self._write(rgb, self.folder / f"{i:05d}_{name}.png"))
            self.images[i] = written[-1]
        return written

    def _display_of(self, fixed: sitk.Image) -> tuple[sitk.Image, np.ndarray]:
        """The fixed image on the display grid, windowed; kept while consecutive cases share the fixed image."""
        key = (id(fixed), fixed.GetSize(), fixed.GetOrigin(), fixed.GetSpacing())
        if self._display is None or key != self._display_key:
            self._display_key, self._display = key, _fixed_display(fixed, self.max_px)
        return self._display

    def _write(self, rgb: np.ndarray, path: Path) -> Path:
        if not self.folder.is_dir():
            self._made += [d for d in (self.folder, *self.folder.parents) if not d.exists()][::-1]
            self.folder.mkdir(parents=True, exist_ok=True)
        return write_overlay_png(rgb, path)

    def finish(self) -> None:
        """Remove overlay PNGs that an earlier run left in the folder (this run's are kept)."""
        if not self.folder.is_dir():
            return
        keep = {p.name for p in self.images.values()}
        for old in self.folder.iterdir():
            if old.is_file() and _FILE_PATTERN.match(old.name) and old.name not in keep:
                old.unlink()

    def discard(self) -> None:
        """Remove this run's PNGs, and the folders :meth:`add` made where they are left empty."""
        for p in self.images.values():
            p.unlink(missing_ok=True)
        self.images.clear()
        for d in reversed(self._made):  # deepest first
            try:
                d.rmdir()
            except OSError:  # not empty: something else lives there
                pass
        self._made = []


# ---------------------------------------------------------------------------------------------------------------
# The page
# ---------------------------------------------------------------------------------------------------------------
