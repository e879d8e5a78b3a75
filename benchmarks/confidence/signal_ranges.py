"""One failure signal over collected calibration cases: its range on right results and on failures, per set and CT.

Reads the JSON lines of ``bench_confidence_calibration --collect`` (``--cases``) and prints, for ``--signal`` (a key
of ``details.signals``), where ``--where KEY MIN`` holds (another signal at or above ``MIN``; default: every case),
the minimum, median and maximum over the right results (TRE under 2 mm) and over the failures, per set and CT, then
the cases named by ``--show`` (key substrings) with their values. ``--rule BELOW``: how many right results and
failures lie below that value (what a flag ``signal < BELOW`` would flag). Used to decide whether a recorded signal
can separate a failure the other signals miss (``docs/trust.md``, "Bone on the CBCT's bone").

    python -m benchmarks.confidence.signal_ranges --cases cases.jsonl --signal bone_agreement \\
        --where bone_share 0.04 --show other_patient
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import shlex
import statistics
import sys
from pathlib import Path
from typing import Any

from benchmarks.bench_common import Tee


def _value(row: dict[str, Any], key: str) -> float:
    v = (row.get("signals") or {}).get(key)
    return float(v) if isinstance(v, (int, float)) and math.isfinite(float(v)) else math.nan


def _stats(values: list[float]) -> str:
    v = [x for x in values if math.isfinite(x)]
    if not v:
        return "- | - | - | 0"
    return f"{min(v):.3f} | {statistics.median(v):.3f} | {max(v):.3f} | {len(v)}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=Path, nargs="+", required=True)
    ap.add_argument("--signal", required=True)
    ap.add_argument("--where", nargs=2, metavar=("KEY", "MIN"), default=None)
    ap.add_argument("--show", nargs="*", default=[])
    ap.add_argument("--rule", type=float, default=None, metavar="BELOW")
    ap.add_argument("--results", type=Path, default=None)
    args = ap.parse_args(argv)
    out = Tee()
    out("command: python -m benchmarks.confidence.signal_ranges " + shlex.join(sys.argv[1:] if argv is None else argv))
    out(f"date: {datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')}")
    rows = [json.loads(line) for path in args.cases for line in path.read_text().splitlines() if line.strip()]
    rows = [r for r in rows if r.get("refused") is None and r.get("signals")]
    if args.where:
        key, low = args.where[0], float(args.where[1])
        rows = [r for r in rows if _value(r, key) >= low]
        out(f"cases with {key} >= {low:g}: {len(rows)}")
    out(f"\n{args.signal}: min | median | max | n, right results (TRE < 2 mm) and failures\n")
    out("| set | CT | right: min | median | max | n | failures: min | median | max | n |")
    out("|---|---|---|---|---|---|---|---|---|---|")
    groups = sorted({(r["set"], r["ct"]) for r in rows})
    for s, ct in groups:
        mine = [r for r in rows if r["set"] == s and r["ct"] == ct]
        ok = [_value(r, args.signal) for r in mine if r["success"]]
        bad = [_value(r, args.signal) for r in mine if not r["success"]]
        out(f"| {s} | {ct} | {_stats(ok)} | {_stats(bad)} |")
    ok_all = [_value(r, args.signal) for r in rows if r["success"]]
    bad_all = [_value(r, args.signal) for r in rows if not r["success"]]
    out(f"| all | all | {_stats(ok_all)} | {_stats(bad_all)} |")
    if args.rule is not None:
        n_ok = sum(v < args.rule for v in ok_all if math.isfinite(v))
        n_bad = sum(v < args.rule for v in bad_all if math.isfinite(v))
        out(f"\n{args.signal} < {args.rule:g}: {n_ok} of {len(ok_all)} right results, "
            f"{n_bad} of {len(bad_all)} failures")
    if args.show:
        out("\n| case | success | flagged | " + args.signal + " |")
        out("|---|---|---|---|")
        for r in rows:
            if any(s in r["key"] for s in args.show):
                out(f"| {r['key']} | {r['success']} | {r['flagged']} | {_value(r, args.signal):.3f} |")
    out.write(args.results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
