"""Seconds to generate one synthetic-anatomy volume (``monai_rigidreg.simulation.synth_phantom``) per grid size.

Usage::

    python -m benchmarks.simulation.bench_synth --sizes 64 128 --spacing 2.0 --seeds 10 --threads 2
"""

from __future__ import annotations

import os
import statistics
import time

import torch

from benchmarks.bench_common import script_parser
from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.simulation.synth import synth_phantom


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    ap.add_argument("--spacing", type=float, default=2.0)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"threads {args.threads}, load {os.getloadavg()[0]:.2f}")
    print("| grid | spacing (mm) | seeds | median (s) | min (s) | max (s) |")
    print("|---|---|---|---|---|---|")
    for n in args.sizes:
        grid = Grid.centered((n,) * 3, (args.spacing,) * 3)
        synth_phantom(grid, 0)  # warm-up
        times = []
        for seed in range(1, args.seeds + 1):
            t0 = time.perf_counter()
            synth_phantom(grid, seed)
            times.append(time.perf_counter() - t0)
        print(f"| {n}^3 | {args.spacing:g} | {args.seeds} | {statistics.median(times):.3f} | {min(times):.3f} | "
              f"{max(times):.3f} |")


if __name__ == "__main__":
    main()
