"""Two bundles, one run: which is faster on the same pairs, and do their estimates differ?

Loads a registrar from each of two bundles (``--bundle-a``, default the shipped one; ``--bundle-b``, e.g. a copy
with one inference setting changed) into one process and registers ``bench_speed``'s clinical-size pairs (made by
``bench_speed --output-dir``) with the default path, A and B interleaved case by case and their order alternated
from round to round, so that a change of the machine's load falls on both alike. Printed: the median seconds per
registration and per stage of each, B's median over A's, the mean distance between the two estimates over the
pair's TRE points (0: identical), each one's TRE, flags and fallbacks, the fine-stage choice of each (how far
the fine stage moved the regression's estimate, which end pose was kept), and the load average before and after.

Time on a quiet machine (pause other jobs); the figures are seconds on this machine's cores as the run found them.

Usage::

    python -m benchmarks.speed.bench_bundle_ab --bundle-b scratch/bundle_tol03 --rounds 5 \\
        --results benchmarks/results/<version>/bench_bundle_ab_<what>_<date>.txt
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk

import monai_rigidreg  # first: its thread policy applies before torch loads
from benchmarks.bench_common import Tee, script_parser
from benchmarks.speed.bench_speed import load_case, load_text, stage_medians, tre_mm
from monai_rigidreg.core.geometry import params_to_matrix, target_registration_error


def _choice(result: monai_rigidreg.RegistrationResult) -> str:
    """The fine-stage choice of a result in a few words (``details.fine_stage_choice``): how far the fine stage
    moved the regression's estimate and, where the choice ran, which end pose was kept."""
    choice = result.details.get("fine_stage_choice")
    if not choice:
        return "-"
    return f"{choice['move_mm']:.2f} mm" + (f", kept {choice['kept']}" if "kept" in choice else "")


def _estimate_distance_mm(a: monai_rigidreg.RegistrationResult, b: monai_rigidreg.RegistrationResult,
                          points: np.ndarray) -> float:
    """Mean distance (mm) between where two results map the TRE points (both fixed -> moving)."""
    ma = params_to_matrix(np.asarray(a.params), np.asarray(a.center))
    mb = params_to_matrix(np.asarray(b.params), np.asarray(b.center))
    return float(target_registration_error(ma, mb, points))


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--bundle-a", type=Path, default=None, help="default: the shipped bundle")
    ap.add_argument("--bundle-b", type=Path, required=True)
    ap.add_argument("--output-dir", type=Path, default=Path("bench_out/speed"), help="bench_speed's pairs")
    ap.add_argument("--rounds", type=int, default=5, help="registrations of each case with each bundle")
    ap.add_argument("--results", type=Path, default=None)
    args = ap.parse_args()
    if args.rounds < 1:
        ap.error("--rounds must be at least 1")
    out = Tee()
    cases = sorted(p for p in args.output_dir.glob("case_*") if (p / "case.json").is_file())
    if not cases:
        raise SystemExit(f"no pairs in {args.output_dir}: make them with python -m benchmarks.speed.bench_speed "
                         f"--output-dir {args.output_dir}")
    names = {"A": str(args.bundle_a or "the shipped bundle"), "B": str(args.bundle_b)}
    registrars = {"A": monai_rigidreg.RigidRegistrar.from_bundle(args.bundle_a),
                  "B": monai_rigidreg.RigidRegistrar.from_bundle(args.bundle_b)}
    ct = sitk.ReadImage(json.loads((cases[0] / "case.json").read_text())["fixed"], sitk.sitkFloat32)
    loaded = [load_case(c) for c in cases]
    out(f"command: python -m benchmarks.speed.bench_bundle_ab {' '.join(sys.argv[1:])}")
    out(f"date: {time.strftime('%Y-%m-%dT%H:%M:%S%z')}; {os.cpu_count()} CPU cores; monai-rigidreg "
        f"{monai_rigidreg.__version__}")
    out(f"A: {names['A']}\nB: {names['B']}")
    out(f"pairs: {len(cases)} ({args.output_dir}); rounds: {args.rounds}")
    out(f"load average at start (1/5/15 min): {load_text()}")
    for key in "AB":  # warm-up: allocator, FFT plans, caches
        monai_rigidreg.register(ct, loaded[0][1], model=registrars[key])
    rows: dict[str, list[dict]] = {"A": [], "B": []}
    last: dict[tuple[str, int], monai_rigidreg.RegistrationResult] = {}
    for k in range(args.rounds):
        for i, (record, cbct, points) in enumerate(loaded):
            for key in ("AB" if (k + i) % 2 == 0 else "BA"):
                t = time.perf_counter()
                r = monai_rigidreg.register(ct, cbct, model=registrars[key])
                dt = time.perf_counter() - t
                last[(key, i)] = r
                rows[key].append({"case": cases[i].name, "time_s": dt, "stages": dict(r.timings),
                                  "tre": tre_mm(r.params, r.center, record, points), "flagged": bool(r.flagged),
                                  "fallback": bool((r.details.get("fallback") or {}).get("run"))})
    out(f"load average at the end (1/5/15 min): {load_text()}")
    out("")
    out("| bundle | registrations | median s | mean TRE (mm) | flagged | fallback ran |")
    out("|---|---|---|---|---|---|")
    med = {}
    for key in "AB":
        rs = rows[key]
        med[key] = float(np.median([r["time_s"] for r in rs]))
        out(f"| {key} | {len(rs)} | {med[key]:.3f} | {np.mean([r['tre'] for r in rs]):.3f} | "
            f"{sum(r['flagged'] for r in rs)} | {sum(r['fallback'] for r in rs)} |")
    out("")
    for key in "AB":
        out(f"stages of {key} (median s): {stage_medians(rows[key])}")
    out(f"B / A (median seconds): {med['B'] / med['A']:.3f}; A - B: {med['A'] - med['B']:+.3f} s")
    out("")
    out("| pair (last round) | TRE A (mm) | TRE B (mm) | A to B (mm, mean over the TRE points) | fine-stage choice "
        "A / B |")
    out("|---|---|---|---|---|")
    for i, (record, _, points) in enumerate(loaded):  # the last round's results
        a, b = last[("A", i)], last[("B", i)]
        out(f"| {cases[i].name} | {tre_mm(a.params, a.center, record, points):.3f} | "
            f"{tre_mm(b.params, b.center, record, points):.3f} | {_estimate_distance_mm(a, b, points):.4f} | "
            f"{_choice(a)} / {_choice(b)} |")
    out.write(args.results)


if __name__ == "__main__":
    main()
