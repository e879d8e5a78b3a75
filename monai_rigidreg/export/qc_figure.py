"""Quality-control figure of a registration, after the reference paper's Fig. 4/5.

Columns: (a) moving CBCT on the fixed grid before registration, (b) registered CBCT, (c) fixed CT, (d) difference
before, (e) difference after (both with a colour bar), (f) overlay (fixed in red, registered in green); rows:
axial, coronal, sagittal slices through the CBCT's centre (its isocentre) as placed by the registration, or the
fixed image centre without a transform. Every panel carries the patient-orientation letters of its edges (from the
fixed image's direction cosines, LPS: L/R, P/A, S/I), and the CBCT's field of view as registered is outlined
(yellow) on the panels that show it: dark outside it is truncation, not misalignment.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.io.volumes import check_output_path, resample

__all__ = ["qc_figure", "orthogonal_slices", "resampled_slices", "edge_letters", "percentiles"]

_LETTERS = (("R", "L"), ("A", "P"), ("I", "S"))
"""(negative, positive) end of each LPS axis: -x is patient right, +x left; -y anterior, +y posterior; -z inferior,
+z superior."""


def _axis_letter(direction_column: np.ndarray, positive: bool) -> str:
    """Letter(s) of the end an index axis points to (direction column in LPS; oblique axes get two letters)."""
    col = np.asarray(direction_column, dtype=np.float64) * (1.0 if positive else -1.0)
    order = np.argsort(-np.abs(col))
    letters = [_LETTERS[a][int(col[a] > 0)] for a in order[:2] if abs(col[a]) > 0.25]
    return "".join(letters) or "?"


def edge_letters(image: sitk.Image) -> list[dict[str, str]]:
    """Orientation letters of the four edges (``left``, ``right``, ``top``, ``bottom``) of the axial, coronal and
    sagittal slices of :func:`orthogonal_slices`, from the image's direction cosines (LPS)."""
    d = np.asarray(image.GetDirection(), dtype=np.float64).reshape(3, 3)  # column i: physical direction of index i
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return [
        {"left": _axis_letter(x, False), "right": _axis_letter(x, True), "top": _axis_letter(y, False),
         "bottom": _axis_letter(y, True)},  # axial: rows index y downwards, columns index x
        {"left": _axis_letter(x, False), "right": _axis_letter(x, True), "top": _axis_letter(z, True),
         "bottom": _axis_letter(z, False)},  # coronal: rows index z flipped (up), columns index x
        {"left": _axis_letter(y, False), "right": _axis_letter(y, True), "top": _axis_letter(z, True),
         "bottom": _axis_letter(z, False)},  # sagittal: rows index z flipped, columns index y
    ]


def orthogonal_slices(image: sitk.Image, center_index: tuple[int, int, int] | None = None) -> list[np.ndarray]:
    """Axial, coronal and sagittal 2D slices (display orientation: anterior/superior up) of a 3D image."""
    arr = sitk.GetArrayViewFromImage(image)  # [z, y, x], no copy of the volume (the slices below are copied)
    z, y, x = (s // 2 for s in arr.shape) if center_index is None else center_index[::-1]
    axial = arr[z].copy()  # rows y (posterior grows downwards), columns x
    coronal = np.flipud(arr[:, y, :]).copy()  # rows z, superior up
    sagittal = np.flipud(arr[:, :, x]).copy()  # rows z, columns y
    return [axial, coronal, sagittal]


def resampled_slices(moving: sitk.Image, fixed: sitk.Image, transform: sitk.Transform | None,
                     center_index: tuple[int, int, int] | None = None, interpolator: str = "linear",
                     default_value: float | None = None) -> list[np.ndarray]:
    """:func:`orthogonal_slices` of ``moving`` resampled onto ``fixed``'s grid under ``transform`` (fixed -> moving;
    identity if ``None``), computed on the three slices only: each is a one-voxel-thick grid cut out of ``fixed``'s
    (same spacing and direction, its origin at the slice's first voxel), so the values are those of the whole
    resampled volume at those voxels (:func:`~monai_rigidreg.io.resample`) without resampling the other ~99 %."""
    size = fixed.GetSize()
    x, y, z = (s // 2 for s in size) if center_index is None else center_index
    if default_value is None:
        stats = sitk.MinimumMaximumImageFilter()
        stats.Execute(moving)
        default_value = stats.GetMinimum()
    out = []
    for start, extent in (((0, 0, z), (size[0], size[1], 1)), ((0, y, 0), (size[0], 1, size[2])),
                          ((x, 0, 0), (1, size[1], size[2]))):
        grid = Grid(extent, fixed.GetSpacing(), fixed.TransformIndexToPhysicalPoint(start), fixed.GetDirection())
        out.append(sitk.GetArrayFromImage(resample(moving, grid, transform, interpolator, default_value)))
    # the same orientation as orthogonal_slices: axial rows y, columns x; coronal and sagittal superior up
    return [out[0][0], np.flipud(out[1][:, 0, :]), np.flipud(out[2][:, :, 0])]


def _window(img: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return np.clip((img - lo) / max(hi - lo, 1e-6), 0.0, 1.0)


_DIFF_ANCHORS = np.array([[0.0, 0.0, 0.3], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0], [1.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
"""The diverging colour map of the difference panels (matplotlib's ``seismic``: dark blue, blue, white, red, dark
red at -1, -0.5, 0, 0.5, 1), as a 256-entry table."""
_DIFF_LUT = np.stack([np.interp(np.linspace(0.0, 1.0, 256), np.linspace(0.0, 1.0, 5), _DIFF_ANCHORS[:, c])
                      for c in range(3)], 1)
_YELLOW, _PANEL, _GAP, _BAR, _MIN_ROW = (255, 255, 0), 220, 14, 10, 72
"""Outline and letter colour; the largest panel side, the gap between panels, the colour bar width and the least
height of a row (pixels)."""


def _font(size: int):  # noqa: ANN202 - a PIL font
    """DejaVu Sans (the font matplotlib ships, found without importing matplotlib) or Pillow's default font."""
    import importlib.util

    from PIL import ImageFont

    spec = importlib.util.find_spec("matplotlib")
    for folder in (spec.submodule_search_locations or []) if spec is not None else []:
        path = Path(folder) / "mpl-data" / "fonts" / "ttf" / "DejaVuSans.ttf"
        if path.is_file():
            return ImageFont.truetype(str(path), size)
    return ImageFont.load_default(size)


def _to_rgb(img: np.ndarray, kind: str) -> np.ndarray:
    """``[h, w]`` (or ``[h, w, 3]`` overlay) display values -> ``[h, w, 3]`` uint8: ``gray`` in [0, 1], ``diff`` in
    [-1, 1] through :data:`_DIFF_LUT`, ``rgb`` channels in [0, 1]."""
    if kind == "diff":
        idx = np.clip(np.rint((img + 1.0) * 127.5), 0, 255).astype(np.intp)
        return (_DIFF_LUT[idx] * 255.0 + 0.5).astype(np.uint8)
    rgb = img if kind == "rgb" else np.repeat(img[..., None], 3, -1)
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _outline(mask: np.ndarray) -> np.ndarray:
    """Pixels of ``mask`` with a 4-neighbour outside it (the border of the image counts as inside)."""
    m = mask.astype(bool)
    pad = np.pad(m, 1, mode="edge")
    inner = pad[:-2, 1:-1] & pad[2:, 1:-1] & pad[1:-1, :-2] & pad[1:-1, 2:]
    return m & ~inner


def percentiles(values: np.ndarray, q: Sequence[float]) -> np.ndarray:
    """``np.percentile(values, q)`` (its default, linear interpolation), the same numbers by the same arithmetic,
    without its call of ``np.unique``, whose first use imports ``numpy.ma`` (about 50 ms of a ``register`` command's
    start on a loaded 2-core machine, for the QC figure's window alone)."""
    a = np.asarray(values).ravel()
    n = a.size
    qs = np.true_divide(np.asanyarray(q, dtype=np.float64), 100)
    virtual = (n - 1) * qs  # numpy's virtual index of the linear method
    previous = np.floor(virtual)
    above, below = virtual >= n - 1, virtual < 0
    prev_i = np.where(above, -1, np.where(below, 0, previous)).astype(np.intp)
    next_i = np.where(above, -1, np.where(below, 0, previous + 1)).astype(np.intp)
    part = np.partition(a, sorted({0, n - 1, *(prev_i % n).tolist(), *(next_i % n).tolist()}))
    lo, hi = part[prev_i], part[next_i]
    gamma = np.asanyarray(virtual - prev_i)
    diff = hi - lo
    out = np.add(lo, diff * gamma)
    np.subtract(hi, diff * (1 - gamma), out=out, where=gamma >= 0.5, casting="unsafe", dtype=type(out.dtype))
    return out


def qc_figure(
    fixed: sitk.Image,
    moving: sitk.Image,
    registered: sitk.Image,
    path: str | Path,
    title: str = "",
    overwrite: bool = False,
    window: tuple[float, float] | None = None,
    transform: sitk.Transform | None = None,
    names: tuple[str, str] | None = None,
) -> Path:
    """Write the QC PNG.

    Args:
        fixed: planning CT.
        moving: CBCT on its own grid (shown resampled onto the fixed grid with the identity: "before").
        registered: the CBCT resampled onto the fixed grid with the registration transform ("after").
        path: output PNG path.
        title: figure title (e.g. the six parameters).
        overwrite: allow replacing an existing file.
        window: display window (default: the 1st-99th percentile of the fixed image).
        transform: the registration (fixed -> moving); with it the slices pass through the CBCT centre as
            registered and the CBCT's field of view (its grid's extent) is outlined on panels (b), (e) and (f).
        names: display names of the fixed and moving inputs (e.g. file names), shown under the title.

    Drawn with Pillow (panels, colour bars, the orientation letters and the titles): with matplotlib (its imports,
    24 axes to build and draw) the figure's share of a ``register`` command on 2 cores was 1.10 s, with Pillow
    0.14-0.22 s (the difference of ``benchmarks/speed/bench_speed.py``'s command rows with and without ``--no-qc``).
    """
    from PIL import Image, ImageDraw

    p = check_output_path(path, overwrite)
    arr_f = sitk.GetArrayViewFromImage(fixed)
    # the window from every 8th voxel (2 per axis): the percentiles of a 256^3 CT to within a few HU, in 1/8 the time
    lo, hi = window if window is not None else (float(v) for v in percentiles(arr_f[::2, ::2, ::2], [1, 99]))
    center_index, fov = None, None
    if transform is not None:
        # the CBCT centre c_m sits at T^-1(c_m) in the fixed frame once registered
        c_m = moving.TransformContinuousIndexToPhysicalPoint([(n - 1) / 2 for n in moving.GetSize()])
        c_f = transform.GetInverse().TransformPoint(c_m)
        idx = fixed.TransformPhysicalPointToIndex(c_f)
        center_index = tuple(int(np.clip(i, 0, n - 1)) for i, n in zip(idx, fixed.GetSize()))
        ones = sitk.Image(moving.GetSize(), sitk.sitkUInt8) + 1
        ones.CopyInformation(moving)
        fov = resampled_slices(ones, fixed, transform, center_index, "nearest", 0)
    # "before": the CBCT on the CT grid with the identity, on the three slices only
    slices = [resampled_slices(moving, fixed, None, center_index), orthogonal_slices(registered, center_index),
              orthogonal_slices(fixed, center_index)]
    letters = edge_letters(fixed)
    sx, sy, sz = fixed.GetSpacing()
    # display size of each row's slices: physical proportions, the longer side _PANEL pixels
    extents = [(slices[2][0].shape[1] * sx, slices[2][0].shape[0] * sy),
               (slices[2][1].shape[1] * sx, slices[2][1].shape[0] * sz),
               (slices[2][2].shape[1] * sy, slices[2][2].shape[0] * sz)]
    sizes = [(max(1, round(_PANEL * w / max(w, h))), max(1, round(_PANEL * h / max(w, h)))) for w, h in extents]
    titles = ["(a) moving (before)", "(b) registered", "(c) fixed", "(d) diff before", "(e) diff after",
              "(f) overlay R=fixed G=reg."]
    views = ["axial", "coronal", "sagittal"]
    font, small, big = _font(12), _font(9), _font(14)
    bar_space = _BAR + 34  # the colour bar and its tick labels right of a difference panel
    col_w = [_PANEL + (bar_space if c in (3, 4) else 0) for c in range(6)]
    left, top = 26, 22 + (20 if title else 0) + (18 if names else 0)
    width = left + sum(col_w) + _GAP * 6
    # each row as tall as its slices (at least _MIN_ROW pixels, for its label and colour bars)
    row_h = [max(h, _MIN_ROW) for _, h in sizes]
    row_y = [top + sum(row_h[k] + _GAP for k in range(r)) for r in range(3)]
    height = row_y[2] + row_h[2] + 6
    canvas = Image.new("RGB", (width, height), "white")
    draw = ImageDraw.Draw(canvas)
    subtitle = f"fixed: {names[0]}   moving: {names[1]}" if names else ""
    y = 4
    for line, f in ((title, big), (subtitle, font)):
        if line:
            draw.text((width / 2, y), line, fill="black", font=f, anchor="ma")
            y += 20 if f is big else 18
    xs = [left + sum(col_w[:c]) + _GAP * c for c in range(6)]
    for c, name in enumerate(titles):
        draw.text((xs[c] + _PANEL / 2, top - 4), name, fill="black", font=font, anchor="md")
    for r in range(3):
        b, g, f = (_window(s[r], lo, hi) for s in slices)
        panels = [(b, "gray"), (g, "gray"), (f, "gray"), (b - f, "diff"), (g - f, "diff"),
                  (np.stack([f, g, np.zeros_like(f)], -1), "rgb")]
        w, h = sizes[r]
        y0 = row_y[r] + (row_h[r] - h) // 2
        label = Image.new("RGB", (row_h[r], 16), "white")
        ImageDraw.Draw(label).text((row_h[r] / 2, 8), views[r], fill="black", font=font, anchor="mm")
        canvas.paste(label.rotate(90, expand=True), (4, row_y[r]))
        outline = None
        if fov is not None and fov[r].min() == 0 and fov[r].max() > 0:
            mask = Image.fromarray((fov[r] > 0).astype(np.uint8) * 255).resize((w, h), Image.Resampling.NEAREST)
            outline = _outline(np.asarray(mask) > 0)
        for c, (img, kind) in enumerate(panels):
            x0 = xs[c] + (_PANEL - w) // 2
            tile = np.asarray(Image.fromarray(_to_rgb(img, kind)).resize((w, h), Image.Resampling.NEAREST)).copy()
            if outline is not None and c in (1, 4, 5):
                tile[outline] = _YELLOW
            canvas.paste(Image.fromarray(tile), (x0, y0))
            if kind == "diff":
                draw.rectangle((x0 - 1, y0 - 1, x0 + w, y0 + h), outline="black")
                _colour_bar(draw, xs[c] + (_PANEL + w) // 2 + 6, row_y[r], row_h[r], small)
            _letter_edges(draw, letters[r], (x0, y0, w, h), small)
    # the colour bars' meaning, once: the difference in units of the display window
    draw.text((xs[4] + _PANEL + 4, top - 4), "diff / window", fill="black", font=small, anchor="ld")
    canvas.save(p, format="PNG", compress_level=1)
    return p


def _colour_bar(draw, x: int, y: int, height: int, font) -> None:  # noqa: ANN001 - PIL objects
    """A vertical colour bar of the difference map from -1 (bottom) to 1 (top), with ticks at -1, -0.5, 0, 0.5, 1."""
    for k in range(height):
        value = 1.0 - 2.0 * k / max(height - 1, 1)
        rgb = _to_rgb(np.array([[value]]), "diff")[0, 0]
        draw.line((x, y + k, x + _BAR - 1, y + k), fill=tuple(int(v) for v in rgb))
    draw.rectangle((x, y, x + _BAR - 1, y + height - 1), outline="black")
    for value in (-1.0, -0.5, 0.0, 0.5, 1.0):
        ty = y + round((1.0 - value) / 2.0 * (height - 1))
        draw.line((x + _BAR, ty, x + _BAR + 2, ty), fill="black")
        draw.text((x + _BAR + 4, ty), f"{value:g}", fill="black", font=font, anchor="lm")


def _letter_edges(draw, letters: dict[str, str], box: tuple[int, int, int, int], font) -> None:  # noqa: ANN001
    """Orientation letters at the middle of each edge of a panel ``box`` = ``(x0, y0, width, height)`` pixels,
    yellow with a black outline."""
    x0, y0, w, h = box
    style = {"fill": _YELLOW, "font": font, "stroke_width": 1, "stroke_fill": "black"}
    draw.text((x0 + 2, y0 + h / 2), letters["left"], anchor="lm", **style)
    draw.text((x0 + w - 2, y0 + h / 2), letters["right"], anchor="rm", **style)
    draw.text((x0 + w / 2, y0 + 1), letters["top"], anchor="ma", **style)
    draw.text((x0 + w / 2, y0 + h - 1), letters["bottom"], anchor="md", **style)
