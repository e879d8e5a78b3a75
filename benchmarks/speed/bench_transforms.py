"""Throughput of the training augmentation pipeline on the CPU (cases per second).

Volumes are loaded once and kept in memory (as a ``CacheDataset`` would); each case runs::

    CopyItemsd("fixed" -> "moving") -> RandRigid6DoFd -> RandCBCTDegradationd -> ResampleToNetworkGridd

for two network grids (64^3 at 4 mm, 96^3 at 2.5 mm), plus a cheaper ordering that degrades on the network grid.
Run: ``python -m benchmarks.speed.bench_transforms [--image CT.nii.gz] [--cases 10] [--threads 2]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Sequence

import torch
from monai.transforms import Compose, CopyItemsd, EnsureTyped, LoadImaged

from monai_rigidreg.transforms import RandCBCTDegradationd, RandRigid6DoFd, ResampleToNetworkGridd

DEFAULT_IMAGE = "/work/shared/data/abdomen_pelvis_totalsegmentator_example_ct.nii.gz"


def pipelines(size: int, spacing: float) -> dict[str, list]:
    rigid = RandRigid6DoFd(keys="moving", center_key="fixed")
    cbct = RandCBCTDegradationd(keys="moving")
    grid = ResampleToNetworkGridd(keys=("moving", "fixed"), size=size, spacing=spacing, ref_key="fixed")
    return {
        "full-res CBCT": [CopyItemsd(keys="fixed", names="moving"), rigid, cbct, grid],
        "CBCT on grid": [CopyItemsd(keys="fixed", names="moving"), rigid, grid, cbct],
    }


def time_pipeline(steps: list, item: dict, cases: int, seed: int = 0) -> tuple[float, list[float]]:
    """Cases per second of ``steps`` and the mean time (ms) of each step."""
    for s in steps:
        if hasattr(s, "set_random_state"):
            s.set_random_state(seed)
    Compose(steps)(dict(item))  # warm-up
    per_step = [0.0] * len(steps)
    t0 = time.perf_counter()
    for _ in range(cases):
        d = dict(item)
        for i, s in enumerate(steps):
            ts = time.perf_counter()
            d = s(d)
            per_step[i] += time.perf_counter() - ts
    total = time.perf_counter() - t0
    return cases / total, [1000.0 * t / cases for t in per_step]


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--image", default=DEFAULT_IMAGE)
    parser.add_argument("--cases", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    item = Compose(
        [LoadImaged(keys="fixed", ensure_channel_first=True), EnsureTyped(keys="fixed", dtype=torch.float32)]
    )({"fixed": args.image})
    shape = tuple(item["fixed"].shape[1:])
    print(
        f"input {os.path.basename(args.image)} {shape}, torch {torch.__version__}, {args.threads} threads, "
        f"{os.cpu_count()} cores visible, {platform.processor() or platform.machine()}"
    )
    print("| network grid | ordering | cases/s | rigid ms | CBCT ms | grid ms |")
    print("|---|---|---|---|---|---|")
    for size, spacing in ((64, 4.0), (96, 2.5)):
        for name, steps in pipelines(size, spacing).items():
            rate, ms = time_pipeline(steps, item, args.cases)
            names = [type(s).__name__ for s in steps]
            t = {n: m for n, m in zip(names, ms)}
            print(
                f"| {size}^3 @ {spacing} mm | {name} | {rate:.2f} | {t['RandRigid6DoFd']:.0f} | "
                f"{t['RandCBCTDegradationd']:.0f} | {t['ResampleToNetworkGridd']:.0f} |"
            )


if __name__ == "__main__":
    main()
