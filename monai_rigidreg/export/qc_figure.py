"""Quality-control figure of a registration, after the reference paper's Fig. 4/5.

Columns: (a) moving CBCT on the fixed grid before registration, (b) registered CBCT, (c) fixed CT, (d) difference
CT - CBCT before, (e) difference CT - registered CBCT (both in HU over a stated window, with a colour bar; grey
outside the CBCT's field of view, where there is nothing to compare), (f) overlay (fixed in red, registered in
green); rows: axial, coronal, sagittal slices. The "before" panels (a, d) pass through the CBCT's own centre on the
CT grid, the others through the CBCT's centre as registered, or the fixed image centre without a transform. Each
panel is zoomed to the CBCT's field of view (a 128 mm CBCT of a 500 mm CT fills its panel), whose outline is drawn in
yellow: dark outside it is truncation, not misalignment. Every panel carries the patient-orientation letters of its
edges (from the fixed image's direction cosines, LPS: L/R, P/A, S/I). :func:`qc_panels` computes what is drawn.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.geometry import Grid, sitk_to_matrix
from monai_rigidreg.io.volumes import check_output_path, resample

__all__ = ["qc_figure", "qc_panels", "orthogonal_slices", "resampled_slices", "edge_letters", "percentiles"]

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
    [-1, 1] through :data:`_DIFF_LUT` (NaN: :data:`_NEUTRAL`), ``rgb`` channels in [0, 1]."""
    if kind == "diff":  # NaN (outside the CBCT's field of view): _NEUTRAL
        idx = np.clip(np.rint((np.nan_to_num(img) + 1.0) * 127.5), 0, 255).astype(np.intp)
        rgb = (_DIFF_LUT[idx] * 255.0 + 0.5).astype(np.uint8)
        rgb[np.isnan(img)] = _NEUTRAL
        return rgb
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


_NEUTRAL = (150, 150, 150)
"""The colour of a difference panel outside the CBCT's field of view (no value of the colour map is grey)."""
FOV_MARGIN_MM = 2.0
"""The CBCT's field of view is its grid's inscribed cylinder less this margin (as the registration's)."""


def _fov_slices(fixed: sitk.Image, moving: sitk.Image, transform: sitk.Transform | None,
                center_index: tuple[int, int, int]) -> list[np.ndarray]:
    """Boolean masks of the three slices of :func:`orthogonal_slices`: the pixels inside the CBCT's field of view
    (the inscribed cylinder of its grid, axis along its z index, less :data:`FOV_MARGIN_MM`) when ``transform``
    (fixed -> moving; ``None``: the identity) places it."""
    o, sp = np.asarray(fixed.GetOrigin()), np.asarray(fixed.GetSpacing())
    d = np.asarray(fixed.GetDirection(), dtype=np.float64).reshape(3, 3)
    m = np.eye(4) if transform is None else sitk_to_matrix(transform)
    om, sm = np.asarray(moving.GetOrigin()), np.asarray(moving.GetSpacing())
    dm = np.asarray(moving.GetDirection(), dtype=np.float64).reshape(3, 3)
    n = np.asarray(moving.GetSize(), dtype=np.float64)
    half = (n - 1) / 2
    radius = min(half[0] * sm[0], half[1] * sm[1]) - FOV_MARGIN_MM
    nx, ny, nz = fixed.GetSize()
    x, y, z = center_index

    def inside(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray) -> np.ndarray:
        idx = np.stack(np.broadcast_arrays(ix, iy, iz)).reshape(3, -1).astype(np.float64)
        points = o + (d @ (sp[:, None] * idx)).T  # fixed voxels, LPS mm
        k = ((points @ m[:3, :3].T + m[:3, 3] - om) @ dm) / sm  # continuous indices in the CBCT
        r2 = ((k[:, 0] - half[0]) * sm[0]) ** 2 + ((k[:, 1] - half[1]) * sm[1]) ** 2
        keep = (r2 <= radius**2) & (k[:, 2] >= -0.5) & (k[:, 2] <= n[2] - 0.5)
        return keep.reshape(np.broadcast_shapes(np.shape(ix), np.shape(iy), np.shape(iz)))

    rows_y, cols_x = np.mgrid[0:ny, 0:nx]
    rows_z, cols = np.mgrid[0:nz, 0:nx]
    rows_zs, cols_y = np.mgrid[0:nz, 0:ny]
    return [inside(cols_x, rows_y, np.array(z)), np.flipud(inside(cols, np.array(y), rows_z)),
            np.flipud(inside(np.array(x), cols_y, rows_zs))]


def _crop_box(mask: np.ndarray | None, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
    """``(row0, row1, col0, col1)``: the bounding box of ``mask`` with a margin (6 % of its side, at least 2 pixels),
    within ``shape``; the whole slice without a mask or where the field of view misses it."""
    if mask is None or not mask.any():
        return 0, shape[0], 0, shape[1]
    box = []
    for axis in (1, 0):  # rows: pixels of any column; columns: of any row
        hit = np.flatnonzero(mask.any(axis))
        pad = max(2, round(0.06 * (hit[-1] + 1 - hit[0])))
        box += [max(0, hit[0] - pad), min(mask.shape[1 - axis], hit[-1] + 1 + pad)]
    return tuple(int(v) for v in box)  # type: ignore[return-value]


def _center_of(image: sitk.Image, point: Any) -> tuple[int, int, int]:
    idx = image.TransformPhysicalPointToIndex(tuple(float(v) for v in point))
    return tuple(int(np.clip(i, 0, n - 1)) for i, n in zip(idx, image.GetSize()))  # type: ignore[return-value]


def qc_panels(fixed: sitk.Image, moving: sitk.Image, registered: sitk.Image,
              window: tuple[float, float] | None = None, transform: sitk.Transform | None = None) -> dict[str, Any]:
    """What the QC figure shows, before it is drawn (:func:`qc_figure`'s arguments).

    Returns:
        ``{"window": (lo, hi) HU, "diff_window_hu": X, "titles": six column titles (and "subtitles"), "centers":
        {"before", "after"} slice indices on the fixed grid, "fov": {"before", "after"}: three boolean masks each
        (``None`` without a transform), "boxes": {"before", "after"}: three ``(row0, row1, col0, col1)`` crops each,
        "pixel_mm": three ``(column, row)`` pixel sizes (mm), "panels": three rows of six ``(values, kind)``}``:
        ``kind`` ``"gray"`` (values in [0, 1]), ``"diff"`` (CT - CBCT over ``X`` HU, in [-1, 1]; NaN outside the
        field of view, drawn grey) or ``"rgb"``; the values already cropped to their box (panels a, d: "before").
    """
    arr_f = sitk.GetArrayViewFromImage(fixed)
    # the window from every 8th voxel (2 per axis): the percentiles of a 256^3 CT to within a few HU, in 1/8 the time
    lo, hi = window if window is not None else (float(v) for v in percentiles(arr_f[::2, ::2, ::2], [1, 99]))
    diff_hu = max(10.0, round((hi - lo) / 20.0) * 10.0)  # half the display window, to 10 HU
    centers = {"before": None, "after": None}
    fov: dict[str, Any] = {"before": None, "after": None}
    if transform is not None:
        c_m = moving.TransformContinuousIndexToPhysicalPoint([(n - 1) / 2 for n in moving.GetSize()])
        # before: the CBCT where it lies on the CT grid; after: its centre c_m sits at T^-1(c_m) once registered
        centers = {"before": _center_of(fixed, c_m),
                   "after": _center_of(fixed, transform.GetInverse().TransformPoint(c_m))}
        fov = {k: _fov_slices(fixed, moving, t, centers[k]) for k, t in (("before", None), ("after", transform))}
    before = resampled_slices(moving, fixed, None, centers["before"])
    fixed_before = orthogonal_slices(fixed, centers["before"])
    after, fixed_after = orthogonal_slices(registered, centers["after"]), orthogonal_slices(fixed, centers["after"])
    boxes = {k: [_crop_box(None if fov[k] is None else fov[k][r], fixed_after[r].shape) for r in range(3)]
             for k in ("before", "after")}
    sx, sy, sz = fixed.GetSpacing()
    panels = []
    for r in range(3):
        b, fb, g, f = (_window(v[r], lo, hi) for v in (before, fixed_before, after, fixed_after))
        d_before, d_after = (fb - b) * (hi - lo) / diff_hu, (f - g) * (hi - lo) / diff_hu  # CT - CBCT, in HU / X
        if fov["after"] is not None:
            d_before = np.where(fov["before"][r], d_before, np.nan)
            d_after = np.where(fov["after"][r], d_after, np.nan)
        row = [(b, "gray", "before"), (g, "gray", "after"), (f, "gray", "after"), (np.clip(d_before, -1, 1), "diff",
               "before"), (np.clip(d_after, -1, 1), "diff", "after"), (np.stack([f, g, np.zeros_like(f)], -1), "rgb",
               "after")]
        panels.append([(v[slice(*boxes[k][r][:2]), slice(*boxes[k][r][2:])], kind) for v, kind, k in row])
    x_hu = f"{diff_hu:.0f}"
    return {
        "window": (lo, hi), "diff_window_hu": diff_hu, "centers": centers, "fov": fov, "boxes": boxes,
        "pixel_mm": [(sx, sy), (sx, sz), (sy, sz)], "panels": panels,
        "titles": ["(a) moving (before)", "(b) registered", "(c) fixed", "(d) difference = CT - CBCT before",
                   "(e) difference = CT - registered CBCT", "(f) overlay R=fixed G=reg."],
        "subtitles": ["", "", "", f"window \u00b1{x_hu} HU, grey: no CBCT", f"window \u00b1{x_hu} HU, grey: no CBCT",
                      ""],
    }


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
        window: display window (default: the 1st-99th percentile of the fixed image); the difference panels show
            CT - CBCT over +-half of it (to 10 HU).
        transform: the registration (fixed -> moving); with it the slices pass through the CBCT centre (before: as
            it lies; after: as registered), the panels are zoomed to the CBCT's field of view, which is outlined, and
            the difference panels are grey outside it.
        names: display names of the fixed and moving inputs (e.g. file names), shown under the title.

    Drawn with Pillow (panels, colour bars, the orientation letters and the titles): with matplotlib (its imports,
    24 axes to build and draw) the figure's share of a ``register`` command on 2 cores was 1.10 s, with Pillow
    0.14-0.22 s (the difference of ``benchmarks/speed/bench_speed.py``'s command rows with and without ``--no-qc``).
    """
    from PIL import Image, ImageDraw

    p = check_output_path(path, overwrite)
    q = qc_panels(fixed, moving, registered, window, transform)
    letters = edge_letters(fixed)
    # display sizes: physical proportions, one scale per row (the longest side of its panels _PANEL pixels)
    sizes = []
    for r in range(3):
        mm = [(v.shape[1] * q["pixel_mm"][r][0], v.shape[0] * q["pixel_mm"][r][1]) for v, _ in q["panels"][r]]
        scale = _PANEL / max(max(w, h) for w, h in mm)
        sizes.append([(max(1, round(w * scale)), max(1, round(h * scale))) for w, h in mm])
    views = ["axial", "coronal", "sagittal"]
    font, small, big = _font(12), _font(9), _font(14)
    bar_space = _BAR + 34  # the colour bar and its tick labels right of a difference panel
    col_w = [_PANEL + (bar_space if c in (3, 4) else 0) for c in range(6)]
    left, top = 26, 34 + (20 if title else 0) + (18 if names else 0)
    width = left + sum(col_w) + _GAP * 6
    # each row as tall as its tallest panel (at least _MIN_ROW pixels, for its label and colour bars)
    row_h = [max(max(h for _, h in sizes[r]), _MIN_ROW) for r in range(3)]
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
    for c, (name, note) in enumerate(zip(q["titles"], q["subtitles"])):
        mid = xs[c] + col_w[c] / 2
        draw.text((mid, top - 16), name, fill="black", font=_fitted(draw, name, col_w[c] + _GAP, 12), anchor="md")
        if note:
            draw.text((mid, top - 4), note, fill="black", font=small, anchor="md")
    for r in range(3):
        label = Image.new("RGB", (row_h[r], 16), "white")
        ImageDraw.Draw(label).text((row_h[r] / 2, 8), views[r], fill="black", font=font, anchor="mm")
        canvas.paste(label.rotate(90, expand=True), (4, row_y[r]))
        for c, (img, kind) in enumerate(q["panels"][r]):
            w, h = sizes[r][c]
            x0, y0 = xs[c] + (_PANEL - w) // 2, row_y[r] + (row_h[r] - h) // 2
            tile = np.asarray(Image.fromarray(_to_rgb(img, kind)).resize((w, h), Image.Resampling.NEAREST)).copy()
            group = "before" if c in (0, 3) else "after"
            if q["fov"][group] is not None and c != 2:
                r0, r1, c0, c1 = q["boxes"][group][r]
                mask = q["fov"][group][r][r0:r1, c0:c1]
                if mask.any() and not mask.all():
                    shown = Image.fromarray(mask.astype(np.uint8) * 255).resize((w, h), Image.Resampling.NEAREST)
                    tile[_outline(np.asarray(shown) > 0)] = _YELLOW
            canvas.paste(Image.fromarray(tile), (x0, y0))
            if kind == "diff":
                draw.rectangle((x0 - 1, y0 - 1, x0 + w, y0 + h), outline="black")
                _colour_bar(draw, xs[c] + (_PANEL + w) // 2 + 6, row_y[r], row_h[r], small, q["diff_window_hu"])
            _letter_edges(draw, letters[r], (x0, y0, w, h), small)
    canvas.save(p, format="PNG", compress_level=1)
    return p


def _fitted(draw, text: str, width: float, size: int):  # noqa: ANN001, ANN202 - PIL objects
    """The largest font of at most ``size`` points (down to 8) in which ``text`` fits ``width`` pixels."""
    for points in range(size, 7, -1):
        font = _font(points)
        if draw.textlength(text, font=font) <= width:
            return font
    return _font(8)


def _colour_bar(draw, x: int, y: int, height: int, font, window_hu: float) -> None:  # noqa: ANN001 - PIL objects
    """A vertical colour bar of the difference map from -``window_hu`` (bottom) to +``window_hu`` HU (top), with ticks
    at -1, -0.5, 0, 0.5 and 1 times it, labelled in HU."""
    for k in range(height):
        value = 1.0 - 2.0 * k / max(height - 1, 1)
        rgb = _to_rgb(np.array([[value]]), "diff")[0, 0]
        draw.line((x, y + k, x + _BAR - 1, y + k), fill=tuple(int(v) for v in rgb))
    draw.rectangle((x, y, x + _BAR - 1, y + height - 1), outline="black")
    for value in (-1.0, -0.5, 0.0, 0.5, 1.0):
        ty = y + round((1.0 - value) / 2.0 * (height - 1))
        draw.line((x + _BAR, ty, x + _BAR + 2, ty), fill="black")
        draw.text((x + _BAR + 4, ty), f"{value * window_hu:g}", fill="black", font=font, anchor="lm")


def _letter_edges(draw, letters: dict[str, str], box: tuple[int, int, int, int], font) -> None:  # noqa: ANN001
    """Orientation letters at the middle of each edge of a panel ``box`` = ``(x0, y0, width, height)`` pixels,
    yellow with a black outline."""
    x0, y0, w, h = box
    style = {"fill": _YELLOW, "font": font, "stroke_width": 1, "stroke_fill": "black"}
    draw.text((x0 + 2, y0 + h / 2), letters["left"], anchor="lm", **style)
    draw.text((x0 + w - 2, y0 + h / 2), letters["right"], anchor="rm", **style)
    draw.text((x0 + w / 2, y0 + 1), letters["top"], anchor="ma", **style)
    draw.text((x0 + w / 2, y0 + h - 1), letters["bottom"], anchor="md", **style)
