"""Quality-control figure of a registration, after the reference paper's Fig. 4/5.

Columns: (a) moving CBCT on the fixed grid before registration, (b) registered CBCT, (c) fixed CT, (d) difference
before, (e) difference after (both with a colour bar), (f) overlay (fixed in red, registered in green); rows:
axial, coronal, sagittal slices through the CBCT's centre (its isocentre) as placed by the registration, or the
fixed image centre without a transform. Every panel carries the patient-orientation letters of its edges (from the
fixed image's direction cosines, LPS: L/R, P/A, S/I), and the CBCT's field of view as registered is outlined
(yellow) on the panels that show it: dark outside it is truncation, not misalignment.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.geometry import Grid
from monai_rigidreg.io import check_output_path, resample

__all__ = ["qc_figure", "orthogonal_slices", "resampled_slices", "edge_letters"]

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
    """
    # imported on use: the Agg backend must be chosen before pyplot is first imported, and --no-qc runs do not pay
    # for matplotlib (about 0.3-0.5 s: python -c "import matplotlib.pyplot")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = check_output_path(path, overwrite)
    arr_f = sitk.GetArrayViewFromImage(fixed)
    # the window from every 8th voxel (2 per axis): the percentiles of a 256^3 CT to within a few HU, in 1/8 the time
    lo, hi = window if window is not None else (float(v) for v in np.percentile(arr_f[::2, ::2, ::2], [1, 99]))
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
    spacing = fixed.GetSpacing()
    aspects = [spacing[1] / spacing[0], spacing[2] / spacing[0], spacing[2] / spacing[1]]
    titles = ["(a) moving (before)", "(b) registered", "(c) fixed", "(d) diff before", "(e) diff after",
              "(f) overlay R=fixed G=reg."]
    views = ["axial", "coronal", "sagittal"]
    fig, axes = plt.subplots(3, 6, figsize=(18, 9.5))
    for r in range(3):
        b, g, f = (_window(s[r], lo, hi) for s in slices)
        panels = [b, g, f, b - f, g - f, np.stack([f, g, np.zeros_like(f)], -1)]
        for col, img in enumerate(panels):
            ax = axes[r, col]
            if col in (3, 4):
                im = ax.imshow(img, cmap="seismic", vmin=-1, vmax=1, aspect=aspects[r], interpolation="nearest")
                bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
                bar.ax.tick_params(labelsize=7)
                if r == 0:
                    bar.set_label("difference / display window", fontsize=7)
            elif col == 5:
                ax.imshow(img, aspect=aspects[r], interpolation="nearest")
            else:
                ax.imshow(img, cmap="gray", vmin=0, vmax=1, aspect=aspects[r], interpolation="nearest")
            if fov is not None and col in (1, 4, 5) and fov[r].min() == 0 and fov[r].max() > 0:
                ax.contour(fov[r], levels=[0.5], colors="yellow", linewidths=0.8)
            _letter_edges(ax, letters[r])
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(titles[col], fontsize=10)
            if col == 0:
                ax.set_ylabel(views[r])
    subtitle = f"fixed: {names[0]}   moving: {names[1]}" if names else ""
    if title or subtitle:
        fig.suptitle("\n".join(t for t in (title, subtitle) if t), fontsize=11)
    # fixed margins instead of tight_layout(), which draws the whole figure an extra time to measure its text (the
    # figure's share of a command is the difference of benchmarks/bench_speed.py's CLI rows with and without --no-qc)
    fig.subplots_adjust(left=0.025, right=0.99, bottom=0.01, top=0.9 if subtitle else 0.93, wspace=0.32,
                        hspace=0.06)
    fig.savefig(p, dpi=80)
    plt.close(fig)
    return p


def _letter_edges(ax: object, letters: dict[str, str]) -> None:
    """Orientation letters at the middle of each edge of a panel (axes coordinates)."""
    from matplotlib import patheffects  # on use, as in qc_figure (no matplotlib import without a figure)

    style = {"color": "yellow", "fontsize": 7, "fontweight": "bold",
             "path_effects": [patheffects.withStroke(linewidth=1.5, foreground="black")]}
    ax.text(0.01, 0.5, letters["left"], transform=ax.transAxes, ha="left", va="center", **style)
    ax.text(0.99, 0.5, letters["right"], transform=ax.transAxes, ha="right", va="center", **style)
    ax.text(0.5, 0.99, letters["top"], transform=ax.transAxes, ha="center", va="top", **style)
    ax.text(0.5, 0.01, letters["bottom"], transform=ax.transAxes, ha="center", va="bottom", **style)
