"""What the last level's expected TRE (``registration.precision``) costs a registration: the default path in process on
``bench_speed``'s pairs, alternately with the signal and with ``pose_covariance`` replaced by a stub that returns at
once (its result then reads "unconstrained", so those registrations come out flagged: only their time counts).

Prints the median seconds per registration and of the last-level stage (``runtime_s.native_level``) for both, and
the signals of the real runs. Time it on a quiet machine.

    python -m benchmarks.speed.bench_precision_cost --pairs bench_out/speed --repeats 3
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

from benchmarks.bench_common import end_run, script_parser, start_registrar_run


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--pairs", type=Path, default=Path("bench_out/speed"), help="bench_speed's --output-dir")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args, out, monitor, t0, registrar = start_registrar_run(ap, __spec__.name if __spec__ else "bench_precision_cost")
    import numpy as np
    import SimpleITK as sitk

    import monai_rigidreg
    from benchmarks.speed.bench_speed import load_case
    from monai_rigidreg.registration import last_level

    cases = sorted(p for p in args.pairs.iterdir() if (p / "case.json").is_file())
    if not cases:
        raise SystemExit(f"no pairs in {args.pairs}: make them with python -m benchmarks.speed.bench_speed")
    ct = sitk.ReadImage(str(load_case(cases[0])[0]["fixed"]), sitk.sitkFloat32)
    cbcts = [load_case(c)[1] for c in cases]
    real = last_level.pose_covariance

    def stub(*_args: object, **_kwargs: object) -> tuple[np.ndarray, float, float]:
        return np.full((6, 6), np.inf), float("nan"), 0.0

    monai_rigidreg.register(ct, cbcts[0], model=registrar)  # warm-up
    times: dict[str, list[float]] = {"with": [], "without": []}
    native: dict[str, list[float]] = {"with": [], "without": []}
    rows = []
    try:
        for _ in range(args.repeats):
            for mode in ("with", "without"):
                last_level.pose_covariance = real if mode == "with" else stub
                for case, cbct in zip(cases, cbcts):
                    t = time.perf_counter()
                    res = monai_rigidreg.register(ct, cbct, model=registrar)
                    times[mode].append(time.perf_counter() - t)
                    native[mode].append(res.timings.get("native_level", float("nan")))
                    if mode == "with" and len(rows) < len(cases):
                        s = res.details["signals"]
                        rows.append(f"| {case.name} | {s.get('expected_tre_mm', float('nan')):.4f} | "
                                    f"{res.confidence:.3f} | {res.flagged} |")
    finally:
        last_level.pose_covariance = real
    out("| pair | expected_tre_mm | confidence | flagged |\n|---|---|---|---|")
    for row in rows:
        out(row)
    out("\n| | median s / registration | median s, last level | n |\n|---|---|---|---|")
    for mode in ("with", "without"):
        out(f"| {mode} the expected TRE | {statistics.median(times[mode]):.3f} | "
            f"{statistics.median(native[mode]):.3f} | {len(times[mode])} |")
    end_run(out, monitor, t0, args.results, [])


if __name__ == "__main__":
    main()
