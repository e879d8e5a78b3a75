"""Training-style augmentation of a planning CT into (Sim-CT, CBCT-like) pairs, saved as a PNG figure.

Pipeline (MONAI ``Compose``)::

    LoadImaged(ensure_channel_first)   "fixed": the CT, HU, RAS affine
    CopyItemsd                         "moving" = copy of "fixed"
    RandRigid6DoFd                     moves "moving" by a random 6-DoF motion M, records T = M (fixed -> moving)
    RandCBCTDegradationd               makes "moving" look like a CBCT (image domain)
    ResampleToNetworkGridd             both onto one axis-aligned grid centred on the fixed image

Usage::

    python examples/augmentation_pipeline.py \
        --image /work/shared/data/abdomen_pelvis_totalsegmentator_example_ct.nii.gz --output augmented.png --cases 3
    python examples/augmentation_pipeline.py --synthetic --output augmented.png

Panels per case: fixed (axial), moving (axial, coronal, sagittal), on the network grid (identity LPS direction:
axial shown radiologically, patient left on the right, anterior at the top; coronal/sagittal superior at the top).
"""

from __future__ import annotations

import argparse
import os
import tempfile
from collections.abc import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import SimpleITK as sitk  # noqa: E402
import torch  # noqa: E402
from monai.transforms import Compose, CopyItemsd, EnsureTyped, LoadImaged  # noqa: E402

from monai_rigidreg.core.geometry import Grid  # noqa: E402
from monai_rigidreg.transforms import RandCBCTDegradationd, RandRigid6DoFd, ResampleToNetworkGridd  # noqa: E402

DEFAULT_IMAGE = "/work/shared/data/abdomen_pelvis_totalsegmentator_example_ct.nii.gz"


def synthetic_ct(path: str, size: int = 96, spacing: float = 3.0) -> str:
    """Write a simple pelvis-like phantom (HU) as NIfTI: body ellipse, fat rim, spine, hips, bowel gas."""
    n = size
    c = (np.arange(n) - (n - 1) / 2) * spacing  # mm
    z, y, x = np.meshgrid(c, c, c, indexing="ij")  # SimpleITK array order
    vol = np.full((n, n, n), -1000.0, dtype=np.float32)
    body = (x / 150) ** 2 + (y / 100) ** 2 < 1
    vol[body] = -100.0  # fat
    vol[(x / 140) ** 2 + (y / 90) ** 2 < 1] = 40.0  # soft tissue
    vol[((x / 18) ** 2 + ((y - 55) / 18) ** 2 < 1)] = 700.0  # spine
    for sx in (-95.0, 95.0):
        vol[((x - sx) / 25) ** 2 + ((y - 10) / 30) ** 2 + (z / 60) ** 2 < 1] = 900.0  # hips
    vol[((x + 30) / 20) ** 2 + ((y + 30) / 15) ** 2 + ((z - 40) / 25) ** 2 < 1] = -900.0  # bowel gas
    img = sitk.GetImageFromArray(vol)
    img.SetSpacing((spacing,) * 3)
    img.SetOrigin((-(n - 1) / 2 * spacing,) * 3)
    sitk.WriteImage(img, path)
    return path


def build_pipeline(size: Sequence[int] | int = 128, spacing: Sequence[float] | float = 2.5, seed: int = 0) -> Compose:
    """The augmentation pipeline for a datalist item ``{"fixed": path}``."""
    pipeline = Compose(
        [
            LoadImaged(keys="fixed", ensure_channel_first=True, image_only=True),
            EnsureTyped(keys="fixed", dtype=torch.float32),
            CopyItemsd(keys="fixed", names="moving"),
            RandRigid6DoFd(keys="moving", center_key="fixed", translate_range=15.0, rotate_range=10.0, axis_prob=0.7),
            RandCBCTDegradationd(keys="moving"),
            ResampleToNetworkGridd(keys=("moving", "fixed"), size=size, spacing=spacing, ref_key="fixed"),
        ]
    )
    pipeline.set_random_state(seed)
    return pipeline


def views(vol: np.ndarray) -> list[np.ndarray]:
    """Axial, coronal, sagittal central slices of an LPS-aligned ``[x, y, z]`` volume, ready for ``imshow``."""
    i, j, k = (s // 2 for s in vol.shape)
    return [vol[:, :, k].T, vol[:, j, :].T[::-1], vol[i, :, :].T[::-1]]


def save_figure(items: list[dict], output: str, window: tuple[float, float] = (-600.0, 800.0)) -> None:
    cols = ["fixed axial", "moving axial", "moving coronal", "moving sagittal"]
    fig, axes = plt.subplots(len(items), 4, figsize=(13, 3.4 * len(items)), squeeze=False)
    for row, item in zip(axes, items):
        fixed = item["fixed"][0].numpy()
        moving = item["moving"][0].numpy()
        panels = [views(fixed)[0]] + views(moving)
        for ax, panel, title in zip(row, panels, cols):
            ax.imshow(panel, cmap="gray", vmin=window[0], vmax=window[1])
            ax.set_title(title, fontsize=9)
            ax.axis("off")
        p = item["rigid_params"]["params"].numpy()
        rec = item["cbct_degradation"]
        on = [
            k for k in ("noise", "scatter", "cupping", "streaks", "rings", "fov", "hu", "blur", "downsample") if rec[k]
        ]
        row[0].text(
            0.0,
            -0.12,
            "T: t=({:.1f}, {:.1f}, {:.1f}) mm  r=({:.1f}, {:.1f}, {:.1f}) deg\nCBCT: {}".format(*p, ", ".join(on)),
            transform=row[0].transAxes,
            fontsize=8,
            va="top",
        )
    fig.tight_layout()
    fig.savefig(output, dpi=90)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--image", default=DEFAULT_IMAGE, help="planning CT (NIfTI/any ITK format, HU)")
    parser.add_argument("--synthetic", action="store_true", help="use a synthetic phantom instead of --image")
    parser.add_argument("--output", default="augmentation_pipeline.png", help="PNG figure to write")
    parser.add_argument("--cases", type=int, default=3, help="number of augmented cases")
    parser.add_argument("--size", type=int, default=128, help="network grid size (voxels per axis)")
    parser.add_argument("--spacing", type=float, default=2.5, help="network grid spacing (mm)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    torch.set_num_threads(min(2, os.cpu_count() or 1))

    with tempfile.TemporaryDirectory() as tmp:
        image = args.image
        if args.synthetic or not os.path.exists(image):
            image = synthetic_ct(os.path.join(tmp, "synthetic_ct.nii.gz"))
        pipeline = build_pipeline(args.size, args.spacing, args.seed)
        items = [pipeline({"fixed": image}) for _ in range(args.cases)]
    for n, item in enumerate(items):
        g = Grid.from_metatensor(item["moving"])
        p = item["rigid_params"]["params"].numpy().round(2)
        print(f"case {n}: params (tx, ty, tz, rx, ry, rz) = {p.tolist()}, network grid {g.size} @ {g.spacing} mm")
    save_figure(items, args.output)
    print(f"saved {args.output}")


if __name__ == "__main__":
    main()
