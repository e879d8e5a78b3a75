"""Quality-control figure of a registration, after the reference paper's Fig. 4/5.

Columns: (a) moving CBCT on the fixed grid before registration, (b) registered CBCT, (c) fixed CT, (d) difference
before, (e) difference after, (f) overlay (fixed in red, registered in green); rows: axial, coronal, sagittal
slices through the fixed image centre.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.io import check_output_path, resample

__all__ = ["qc_figure", "orthogonal_slices"]


def orthogonal_slices(image: sitk.Image, center_index: tuple[int, int, int] | None = None) -> list[np.ndarray]:
    """Axial, coronal and sagittal 2D slices (display orientation: anterior/superior up) of a 3D image."""
    arr = sitk.GetArrayFromImage(image)  # [z, y, x]
    z, y, x = (s // 2 for s in arr.shape) if center_index is None else center_index[::-1]
    axial = arr[z]  # rows y (posterior grows downwards), columns x
    coronal = np.flipud(arr[:, y, :])  # rows z, superior up
    sagittal = np.flipud(arr[:, :, x])  # rows z, columns y
    return [axial, coronal, sagittal]


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
    """
    # imported on use: the Agg backend must be chosen before pyplot is first imported, and --no-qc runs do not pay
    # for matplotlib (about 0.3-0.5 s: python -c "import matplotlib.pyplot")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = check_output_path(path, overwrite)
    before = resample(moving, fixed, None)
    vols = [before, registered, fixed]
    arr_f = sitk.GetArrayViewFromImage(fixed)
    lo, hi = window if window is not None else (float(np.percentile(arr_f, 1)), float(np.percentile(arr_f, 99)))
    slices = [orthogonal_slices(v) for v in vols]
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
                ax.imshow(img, cmap="seismic", vmin=-1, vmax=1, aspect=aspects[r], interpolation="nearest")
            elif col == 5:
                ax.imshow(img, aspect=aspects[r], interpolation="nearest")
            else:
                ax.imshow(img, cmap="gray", vmin=0, vmax=1, aspect=aspects[r], interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(titles[col], fontsize=10)
            if col == 0:
                ax.set_ylabel(views[r])
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    fig.savefig(p, dpi=80)
    plt.close(fig)
    return p
