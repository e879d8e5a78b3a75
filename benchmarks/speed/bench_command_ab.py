"""The ``monai-rigidreg register`` command of two checkouts, alternated on one pair: wall seconds per run and the
medians, for a change whose effect is smaller than the run-to-run spread of separate benchmark runs.

Each run is a fresh process, ``python -c "from monai_rigidreg.cli import console; console()" register ...`` with
``PYTHONPATH`` set to the checkout (its package is imported ahead of the installed one), default outputs written
into a fresh folder. The two checkouts alternate (A, B, A, B, ...) so that a drift of the machine hits both alike.

Usage::

    git worktree add /tmp/base <commit>      # the checkout to compare with
    python -m benchmarks.speed.bench_command_ab --tree-a /tmp/base [--tree-b .] [--rounds 10] \
        [--fixed CT --moving CBCT] [--results benchmarks/results/bench_command_ab_<what>_<date>.txt]

Default pair: the ``bench_speed.py`` pair ``bench_out/speed/case_0`` and its thorax CT. Run it on a quiet machine.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_common import script_parser

REPO = Path(__file__).resolve().parents[2]


def one_run(tree: Path, fixed: Path, moving: Path, out: Path) -> float:
    shutil.rmtree(out, ignore_errors=True)
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, "-c", "import sys; from monai_rigidreg.cli import console; console(sys.argv[1:])",
           "register", "--fixed", str(fixed), "--moving", str(moving), "--output-dir", str(out), "-q"]
    t = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    dt = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: exit {proc.returncode}: {proc.stderr.strip().splitlines()[-1:]}")
    return dt


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--tree-a", type=Path, required=True)
    ap.add_argument("--tree-b", type=Path, default=REPO)
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--fixed", type=Path, default=None)
    ap.add_argument("--moving", type=Path, default=None)
    ap.add_argument("--results", type=Path, default=None)
    args = ap.parse_args()
    case = REPO / "bench_out" / "speed" / "case_0"
    moving = args.moving or case / "cbct.nii.gz"
    fixed = args.fixed or (Path(json.loads((case / "case.json").read_text())["fixed"]) if args.moving is None else None)
    if fixed is None or not Path(moving).exists():
        raise SystemExit("no pair: give --fixed and --moving, or run benchmarks/speed/bench_speed.py first")
    lines = [f"command: python {' '.join(sys.argv)}",
             f"date: {time.strftime('%Y-%m-%dT%H:%M:%S%z')}; load average at start "
             f"{' '.join(f'{v:.2f}' for v in os.getloadavg())}; pair: {fixed} / {moving}"]
    tmp = Path(tempfile.mkdtemp(prefix="bench_command_ab_"))
    times: dict[str, list[float]] = {"A": [], "B": []}
    trees = {"A": args.tree_a.resolve(), "B": args.tree_b.resolve()}
    for _ in range(args.rounds):
        for name, tree in trees.items():
            times[name].append(one_run(tree, fixed, moving, tmp / name))
    shutil.rmtree(tmp, ignore_errors=True)
    lines.append("\n| checkout | runs (wall s, in order) | median s |\n|---|---|---|")
    for name, tree in trees.items():
        lines.append(f"| {name}: {tree} | {' '.join(f'{t:.2f}' for t in times[name])} | "
                     f"{float(np.median(times[name])):.2f} |")
    lines.append(f"\nmedian B - A: {float(np.median(times['B']) - np.median(times['A'])):+.2f} s; load average at end "
                 f"{' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print("\n".join(lines))
    if args.results is not None:
        args.results.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
