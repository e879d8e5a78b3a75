"""Are the estimates of ordinary pairs unchanged by issue 35's overlap handling? This checkout against another one.

Reads the estimates this checkout made (``bench_confidence_calibration.py --collect``'s ``--cases`` file) for the
ordinary sets (``paper``: the paper protocol; ``clinical``: clinical geometry with deformed pairs; full overlap,
inputs in the right order), registers the same pairs with the package of ``--tree`` (another checkout, e.g. the
commit before issue 35, in a child process that imports it) and prints, per case and over all, the largest parameter
difference and the mean distance between the two estimates over the TRE points, the error of each against the truth
and whether the match was kept inside the CT (``details.overlap.matched_within_ct``: where it was, a change is
expected; everywhere else the code path is the old one).

Usage::

    git archive f2467dc | tar -x -C /tmp/base   # the commit before issue 35
    python -m benchmarks.confidence.bench_estimates_unchanged --tree /tmp/base \\
        --cases bench_out/calibration/cases.jsonl --sets paper clinical \\
        --results benchmarks/results/0.4.9/bench_estimates_unchanged_<date>.txt
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_common import REPO, Tee, end_run, script_parser, start_run

SETS_FILE = Path(__file__).with_name("calibration_sets.py")


def _sets_module() -> Any:
    """:mod:`benchmarks.confidence.calibration_sets` of this checkout, loaded by path (the other tree's
    ``benchmarks`` package may not have it)."""
    spec = importlib.util.spec_from_file_location("calibration_sets_here", SETS_FILE)
    module = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def child(args: Any) -> None:
    """In the other tree's process: register the cases named in ``--keys`` and write their parameters."""
    import SimpleITK as sitk
    import torch

    import monai_rigidreg

    torch.set_num_threads(1)
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
    keys = set(json.loads(Path(args.keys).read_text()))
    sets = _sets_module()
    registrar = monai_rigidreg.RigidRegistrar.from_bundle(device="cpu")
    registrar.adapt_threads = False
    gens = [sets.paper_cases(Path(args.real_ct_dir), args.paper_cts),
            sets.clinical_cases([Path(p) for p in args.pairs_dirs], None)]
    with open(args.out, "w") as f:
        for gen in gens:
            for case in gen:
                if case.key not in keys:
                    continue
                res = monai_rigidreg.register(case.fixed, case.moving, model=registrar, moving_fov=case.fov,
                                              resample_moving=False, **case.options)
                err, ok = case.score(res.params, res.center)
                f.write(json.dumps({"key": case.key, "params": [float(v) for v in res.params],
                                    "center": [float(v) for v in res.center], "error_mm": err, "success": ok,
                                    "confidence": float(res.confidence), "flagged": bool(res.flagged)}) + "\n")
                f.flush()
                print(f"{case.key}: {err:.3f} mm", flush=True)


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--tree", type=Path, required=False, help="the other checkout's root")
    ap.add_argument("--cases", type=Path, default=Path("bench_out/calibration/cases.jsonl"))
    ap.add_argument("--sets", nargs="+", default=["paper", "clinical"])
    ap.add_argument("--cts", nargs="*", default=None, help="only these CTs (default: all in --cases)")
    ap.add_argument("--real-ct-dir", default="bench_out/real_ct")
    ap.add_argument("--paper-cts", nargs="+", default=["thorax_4dct_phase00_itkelastix", "head_tigre_ct"])
    ap.add_argument("--pairs-dirs", nargs="+", default=["bench_out/clinical", "bench_out/clinical_seed2500"])
    ap.add_argument("--results", type=Path, default=None)
    ap.add_argument("--child", action="store_true", help=argparse_suppress())
    ap.add_argument("--keys", default=None, help=argparse_suppress())
    ap.add_argument("--out", default=None, help=argparse_suppress())
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    out = Tee()
    monitor, t0 = start_run(out, __spec__.name if __spec__ else "bench_estimates_unchanged", 1, "cpu",
                            "the shipped bundle (each tree's own)")
    rows = [json.loads(line) for line in args.cases.read_text().splitlines() if line.strip()]
    rows = [r for r in rows if r["set"] in args.sets and r["refused"] is None and (not args.cts or r["ct"] in args.cts)]
    work = Path("bench_out/estimates_unchanged")
    work.mkdir(parents=True, exist_ok=True)
    keys_file, other_file = work / "keys.json", work / f"{args.tree.name}.jsonl"
    done = {}
    if other_file.is_file():
        done = {json.loads(line)["key"]: json.loads(line) for line in other_file.read_text().splitlines() if line}
    todo = [r["key"] for r in rows if r["key"] not in done]
    if todo:
        keys_file.write_text(json.dumps(todo))
        part = work / f"{args.tree.name}.part.jsonl"
        env = {**os.environ, "PYTHONPATH": str(args.tree.resolve()), "OMP_NUM_THREADS": "1"}
        subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", "--keys", str(keys_file), "--out",
                        str(part), "--real-ct-dir", args.real_ct_dir, "--paper-cts", *args.paper_cts,
                        "--pairs-dirs", *args.pairs_dirs], env=env, cwd=REPO, check=True)
        for line in part.read_text().splitlines():
            r = json.loads(line)
            done[r["key"]] = r
        other_file.write_text("".join(json.dumps(r) + "\n" for r in done.values()))
    out(f"other tree: {args.tree}; sets {', '.join(args.sets)}; {len(rows)} cases")
    out("\n| case | matched within the CT | max |Δ param| (mm or deg) | error here (mm) | error there (mm) "
        "| flagged here | flagged there |")
    out("|---|---|---|---|---|---|---|")
    same, changed = [], []
    for r in rows:
        o = done.get(r["key"])
        if o is None:
            continue
        diff = float(np.max(np.abs(np.asarray(r["params"]) - np.asarray(o["params"]))))
        within = (r.get("overlap") or {}).get("matched_within_ct")
        (changed if within else same).append((r, o, diff))
        out(f"| {r['key']} | {within or '-'} | {diff:.2e} | {r['error_mm']:.3f} | {o['error_mm']:.3f} | "
            f"{'yes' if r['flagged'] else 'no'} | {'yes' if o.get('flagged') else 'no'} |")
    for name, group in (("matched as before (no part of the CBCT's tissue outside the CT)", same),
                        ("matched within the CT", changed)):
        if not group:
            out(f"\n{name}: none")
            continue
        d = np.array([g[2] for g in group])
        e_here = np.array([g[0]["error_mm"] for g in group])
        e_there = np.array([g[1]["error_mm"] for g in group])
        ok_here, ok_there = sum(g[0]["success"] for g in group), sum(g[1]["success"] for g in group)
        out(f"\n{name}: {len(group)} cases; largest parameter difference {d.max():.2e}; mean error here "
            f"{e_here.mean():.3f} mm, there {e_there.mean():.3f} mm; successes here {ok_here}, there {ok_there}; "
            f"largest error change {np.max(np.abs(e_here - e_there)):.3f} mm")
        fails_here = [g for g in group if not g[0]["success"]]
        fails_there = [g for g in group if not g[1]["success"]]
        out(f"  failures here {len(fails_here)}, flagged {sum(g[0]['flagged'] for g in fails_here)}; failures there "
            f"{len(fails_there)}, flagged {sum(bool(g[1].get('flagged')) for g in fails_there)}")
    end_run(out, monitor, t0, args.results, [])


def argparse_suppress() -> str:
    import argparse

    return argparse.SUPPRESS


if __name__ == "__main__":
    main()
