"""Registration on real CTs held out from training: the learned regression alone, the shipped network, elastix, and
(``--methods ... ants greedy``) the peer tools ANTs and greedy.

The shipped network was trained on phantoms and one pelvis CT (``scripts/make_training_data.sh``). This benchmark
simulates paired data from CTs it has never seen, by default the two held-out CTs of ``../shared/data``:

* ``thorax_4dct_phase00_itkelastix.nii.gz``: a radiotherapy planning CT of the thorax (lungs, mediastinum);
* ``head_tigre_ct.nii.gz``: a CT-derived head with real skull geometry but a flat soft-tissue plateau (no
  soft-tissue texture; see its ``.txt`` sidecar).

For each CT, ``monai-rigidreg simulate --protocol paper`` writes ``--num-cases`` pairs into
``<output-dir>/<name>`` (resumed where it exists) on the network's grids: a fan-beam Sim-CT of 128^3 at 2 mm and a
cone-beam CBCT of 64^3 at 2 mm (the paper's 128 mm interior field of view), with noise, scatter and beam
hardening. The paper protocol holds single-axis translations (5-15 mm) and rotations (10-30 degrees) and
multi-axis motions up to 30 degrees. ``monai_rigidreg.evaluation.evaluate_datalist`` then registers every case with
every method in the same run (evaluation outputs, with overlays of the failed cases, in
``<output-dir>/eval/<name>``). A peer tool (``ants``: ANTs' rigid preset, ``antspyx``; ``greedy``: ``greedy -a -dof
6``, ``picsl-greedy``; the ``bench`` extra) counts only after its convention check passes: it recovers the known
motion of a small pair through its own output (``monai_rigidreg.registration.peers.check_convention``, printed first).

Printed, per CT and over all of them: per method n, mean and median TRE (mm, over the body points the evaluation
uses), success rate (TRE < 2 mm), the share of cases under 12 mm, the per-axis mean absolute errors, the median time
per case (volumes in memory; the network methods include the confidence check, as ``evaluate`` runs them) and its
ratio to elastix's; for ``network`` and ``network-thorough`` (the thorough path, ``register(..., thorough=True)``) the
path taken, how often the network-led path's fallback ran and why, how close the cases came to its check's limits,
and the stage medians; the identity (no registration) on the same cases for reference; and every failed case
(TRE >= 2 mm) per method with its motion and the other methods' TRE on it. ``--results FILE`` writes the same text
with the command line, the date and the machine load at the top (timings are only indicative when other jobs share
the CPU).

Usage::

    python -m benchmarks.accuracy.bench_real_ct --num-cases 21 \
        --results benchmarks/results/<version>/bench_real_ct_<date>.txt
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_common import (
    Tee,
    add_peer_mask_option,
    add_registrar_options,
    apply_registrar_options,
    checked_peers,
    ct_name,
    end_run,
    find_cts,
    fine_stage_choice_summary,
    is_training_ct,
    peer_mask,
    peer_mask_line,
    registrar_options_line,
    script_parser,
    set_threads,
    signed,
    start_run,
    training_mark,
)

REPO = Path(__file__).resolve().parents[2]

DEFAULT_CTS = ("thorax_4dct_phase00_itkelastix.nii.gz", "head_tigre_ct.nii.gz")
DEFAULT_METHODS = ("network-regression", "network", "elastix")
SUCCESS_MM = 2.0
NEAR_MM = 12.0
# the network's grids (bundle network_size 64, spacing 2 mm) and the interior CBCT of the paper, as in
# scripts/make_training_data.sh (GRID, INTERIOR, NOISY)
SIM_SETTINGS = (
    "simct_size=128", "simct_spacing=2.0", "simct_views=360", "cbct_views=180",
    "cbct_size=64", "cbct_spacing=2.0", "projection_spacing=2.0",
    "photons=3e4", "scatter_to_primary=0.5", "beam_hardening=0.02",
    # the pairs centred on the origin, as every result of 0.4.x was measured on (and bench_out's pairs resume)
    "ct_frame=False",
)
CBCT_GRIDS = {  # --cbct: the CBCT's grid (the rest of SIM_SETTINGS is kept)
    "64x2": ("cbct_size=64", "cbct_spacing=2.0", "projection_spacing=2.0"),
    "128x1.6": ("cbct_size=128", "cbct_spacing=1.6", "projection_spacing=1.6"),
}


def sim_settings(cbct: str = "64x2") -> tuple[str, ...]:
    """:data:`SIM_SETTINGS` with the CBCT grid of ``cbct`` (a key of :data:`CBCT_GRIDS`)."""
    grid = CBCT_GRIDS[cbct]
    keys = {g.split("=")[0] for g in grid}
    return tuple(s for s in SIM_SETTINGS if s.split("=")[0] not in keys) + grid


def data_name(ct: Path, protocol: str = "paper", cbct: str = "64x2") -> str:
    """The CT's data folder name: its name, with the protocol and CBCT grid where they are not the defaults (so the
    default protocol's data stays where earlier runs put it)."""
    suffix = ("" if protocol == "paper" else f"_{protocol}") + ("" if cbct == "64x2" else f"_cbct{cbct}")
    return ct_name(ct) + suffix


def simulate_command(ct: Path, out_dir: Path, num_cases: int, seed: int, display: bool = False,
                     protocol: str = "paper", cbct: str = "64x2") -> list[str]:
    """The ``monai-rigidreg simulate`` call for one CT (``display``: as a user would type it)."""
    exe = shutil.which("monai-rigidreg")
    if display:
        base = ["monai-rigidreg"]
    else:
        base = [exe] if exe else [sys.executable, "-m", "monai_rigidreg.cli"]
    cmd = [*base, "simulate", "--no-progress", "-q", "--output-dir", str(out_dir), "--phantom", str(ct),
           "--protocol", protocol, "--num-cases", str(num_cases), "--seed", str(seed), "--device", "cpu"]
    for s in sim_settings(cbct):
        cmd += ["--set", s]
    return cmd


def identity_tre(items: list[dict]) -> dict[str, float]:
    """TRE of doing nothing, per case, over the same body points as the evaluation."""
    from monai_rigidreg.core.geometry import target_registration_error
    from monai_rigidreg.evaluation.evaluate import iter_cases

    return {c.case_id: float(target_registration_error(np.zeros(6), c.truth, c.points, center=c.center))
            for c in iter_cases(items)}


def _pct(x: float) -> str:
    return f"{100 * x:.0f}%"


def summary_table(rows: list[dict], methods: list[str], out: Tee) -> None:
    """One markdown table: every method and the identity over the same cases."""
    from monai_rigidreg.core.geometry import parameter_errors

    header = ["method", "n", "mean TRE (mm)", "median TRE (mm)", f"success (<{SUCCESS_MM:g} mm)",
              f"<{NEAR_MM:g} mm", "|Δtx|", "|Δty|", "|Δtz|", "|Δrx|", "|Δry|", "|Δrz|", "median time (s)",
              "time / elastix"]
    out("| " + " | ".join(header) + " |")
    out("|" + "---|" * len(header))
    t_elx = np.median([r["results"]["elastix"].runtime_s for r in rows]) if "elastix" in methods else None
    for m in methods:
        res = [r["results"][m] for r in rows]
        tre = np.array([c.tre_mm for c in res])
        mae = np.mean(np.stack([c.abs_errors for c in res]), axis=0)
        t = float(np.median([c.runtime_s for c in res]))
        ratio = f"{t / t_elx:.2f}" if t_elx else "-"
        out(f"| {m} | {len(res)} | {np.mean(tre):.2f} | {np.median(tre):.2f} | {_pct(np.mean(tre < SUCCESS_MM))} | "
            f"{_pct(np.mean(tre < NEAR_MM))} | " + " | ".join(f"{v:.2f}" for v in mae) + f" | {t:.2f} | {ratio} |")
    tre0 = np.array([r["identity_tre"] for r in rows])
    mae0 = np.mean(parameter_errors(np.zeros((len(rows), 6)), np.stack([r["truth"] for r in rows])), axis=0)
    out(f"| identity (no registration) | {len(rows)} | {np.mean(tre0):.2f} | {np.median(tre0):.2f} | "
        f"{_pct(np.mean(tre0 < SUCCESS_MM))} | {_pct(np.mean(tre0 < NEAR_MM))} | "
        + " | ".join(f"{v:.2f}" for v in mae0) + " | - | - |")
    out()
    out("Per-axis columns: mean absolute error, mm (t) and degrees (r). Time: median per case, volumes in memory; "
        "the network methods include the confidence check.")
    flag_rows = []
    for m in methods:
        res = [r["results"][m] for r in rows]
        if not all("flagged" in c.extra for c in res):
            continue
        fails = [c for c in res if not c.success]
        oks = [c for c in res if c.success]
        flag_rows.append(f"{m}: {sum(bool(c.extra['flagged']) for c in fails)} of {len(fails)} failures flagged, "
                         f"{sum(bool(c.extra['flagged']) for c in oks)} of {len(oks)} successes flagged")
    if flag_rows:
        out("Failure flag (confidence < 0.5): " + "; ".join(flag_rows) + ".")
    for m in [m for m in methods if m in ("network", "network-thorough")]:
        res = [r["results"][m] for r in rows]
        fell = [c for c in res if (c.extra.get("fallback") or {}).get("run")]
        reasons: dict[str, int] = {}
        for c in fell:
            for k in c.extra["fallback"]["reasons"]:
                reasons[k] = reasons.get(k, 0) + 1
        paths = [c.extra.get("path") for c in res]
        stages = list(dict.fromkeys(k for c in res for k in c.extra.get("timings", {})))
        out(f"{m}: paths {dict((p, paths.count(p)) for p in dict.fromkeys(paths))}; fallback ran on {len(fell)} of "
            f"{len(res)} (reasons {reasons}); median seconds per stage (0 where it did not run): " + ", ".join(
                f"{k} {np.median([c.extra['timings'].get(k, 0.0) for c in res]):.2f}" for k in stages))
        out("  " + fine_stage_choice_summary([c.extra.get("fine_stage_choice") for c in res]))
        checks = [c.extra["lead_check"] for c in res if c.extra.get("lead_check")]
        if checks:  # how close the cases came to the check's limits (lead.py)
            out(f"  check: confidence min {min(k['confidence'] for k in checks):.3f}, overlap min "
                f"{min(k['overlap'] for k in checks):.3f}, polish max {max(k['polish_mm'] for k in checks):.2f} mm, "
                f"translation max {max(k['max_translation_mm'] for k in checks):.1f} mm, rotation max "
                f"{max(k['max_rotation_deg'] for k in checks):.1f} deg")
        for r, c in ((r, r["results"][m]) for r in rows if (r["results"][m].extra.get("fallback") or {}).get("run")):
            others = ", ".join(f"{k} {v.tre_mm:.2f}" for k, v in r["results"].items() if k != m)
            out(f"  - fallback on {r['ct']} {r['case_id']} [{r['label']}]: {c.extra['lead_check']}; start "
                f"{c.extra.get('start')}; TRE {c.tre_mm:.2f} mm ({others})")


def failure_list(rows: list[dict], methods: list[str], out: Tee) -> None:
    """The failed cases (TRE >= 2 mm) of each method, with their motion and the other methods' TRE."""
    out(f"Failed cases (TRE >= {SUCCESS_MM:g} mm) per method; error = estimate - truth (mm, degrees); "
        "TRE of every method on the case for comparison")
    out()
    for m in methods:
        failed = [r for r in rows if not r["results"][m].success]
        out(f"{m}: {len(failed)} of {len(rows)} failed")
        for r in failed:
            c = r["results"][m]
            err = np.asarray(c.params_pred) - np.asarray(c.params_true)
            err[3:] = (err[3:] + 180.0) % 360.0 - 180.0
            others = ", ".join(f"{k} {v.tre_mm:.2f}" for k, v in r["results"].items() if k != m)
            conf = f", confidence {c.extra['confidence']:.2f}{' flagged' if c.extra.get('flagged') else ''}" \
                if c.extra.get("confidence") is not None else ""
            out(f"  - {r['ct']} {r['case_id']} [{r['group']}: {r['label']}]: TRE {c.tre_mm:.2f} mm (identity "
                f"{r['identity_tre']:.2f}){conf}; error " + signed(err)
                + (f"; others: {others}" if others else ""))
    out()


def main() -> int:
    ap = script_parser(__doc__)
    ap.add_argument("--num-cases", type=int, default=21, help="cases per CT (default 21; paper: max 63, multi30: 8)")
    ap.add_argument("--protocol", choices=("paper", "multi30"), default="paper",
                    help="motions: the reference's paper protocol (default) or multi30, 6-DoF motions with "
                         "|rx| = |ry| = |rz| = 30 degrees (data in DIR/<name>_multi30)")
    ap.add_argument("--cbct", choices=tuple(CBCT_GRIDS), default="64x2",
                    help="the CBCT grid: 64^3 at 2 mm (default, the paper's 128 mm interior field of view) or "
                         "128^3 at 1.6 mm (205 mm; data in DIR/<name>_cbct128x1.6)")
    ap.add_argument("--ct", nargs="+", default=None, metavar="PATH",
                    help=f"CT volumes (NIfTI or DICOM folder, HU); default {' '.join(DEFAULT_CTS)} from the data "
                         "folder ($MONAI_RIGIDREG_DATA or ../shared/data)")
    ap.add_argument("--seed", type=int, default=6000, help="simulation seed, the same for every CT (default 6000)")
    ap.add_argument("--threads", type=int, default=2, help="torch, SimpleITK and ITK/elastix threads (default 2)")
    ap.add_argument("--output-dir", type=Path, default=Path("bench_out/real_ct"),
                    help="data in DIR/<name>, evaluation outputs in DIR/eval/<name> (default bench_out/real_ct)")
    ap.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS),
                    help=f"evaluation methods (default {' '.join(DEFAULT_METHODS)}; also network-thorough, the "
                         "thorough path, sitk, network+refine, and the peer tools ants and greedy)")
    ap.add_argument("--device", default="cpu", help="device of the network (default cpu)")
    ap.add_argument("--bundle", type=Path, default=None,
                    help="bundle directory of the network methods (default: the shipped bundle)")
    ap.add_argument("--fine-passes", type=int, default=None,
                    help="fine passes of a CorrelationRigidNet at inference (default: the bundle's)")
    ap.add_argument("--subcell", choices=("softargmax", "parabola"), default=None,
                    help="how a CorrelationRigidNet's fine level reads its matches (default: the bundle's)")
    add_registrar_options(ap)
    add_peer_mask_option(ap)
    ap.add_argument("--results", type=Path, default=None, help="also write the printed text to FILE")
    args = ap.parse_args()
    if args.num_cases < 1 or args.threads < 1:
        ap.error("--num-cases and --threads must be >= 1")

    set_threads(args.threads)  # before the libraries start their pools

    from monai_rigidreg.evaluation import evaluate_datalist
    from monai_rigidreg.evaluation.evaluate import METHODS, load_datalist
    from monai_rigidreg.registration.classical import elastix_available
    from monai_rigidreg.registration.registrar import RigidRegistrar

    out = Tee()
    bad = [m for m in args.methods if m not in METHODS]
    if bad:
        ap.error(f"unknown method(s) {bad}; choose from {METHODS}")
    methods = list(dict.fromkeys(args.methods))
    if "elastix" in methods and not elastix_available():
        out("skipped method elastix: itk-elastix is not installed")
        methods.remove("elastix")
    if "elastix" in methods:
        import itk

        itk.MultiThreaderBase.SetGlobalDefaultNumberOfThreads(args.threads)

    bundle = (f"{args.bundle or 'the shipped bundle'}"
              + (f"; fine passes {args.fine_passes}" if args.fine_passes is not None else "")
              + (f"; subcell {args.subcell}" if args.subcell is not None else "")
              + (f"; final pass on the normalised contrast at {args.native_final_norm_mm:g} mm"
                 if args.native_final_norm_mm is not None else ""))
    monitor, t_start = start_run(out, __spec__.name, args.threads, args.device, bundle)
    methods = checked_peers(methods, out)  # ANTs reads ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS (set_threads) here
    peer_mask_line(args, methods, out)
    out(f"methods: {' '.join(methods)}; {args.num_cases} {args.protocol}-protocol cases per CT, seed {args.seed}; "
        f"simulation settings: {' '.join(sim_settings(args.cbct))}")
    out()

    cts = find_cts(args.ct, out, DEFAULT_CTS)
    if not cts:
        out("no CT to benchmark")
        return 2
    registrar = (RigidRegistrar.from_bundle(args.bundle, device=args.device)
                 if any(m.startswith("network") for m in methods) else None)
    if registrar is not None and args.fine_passes is not None:
        regression = getattr(registrar.network, "regression", None)
        if not hasattr(regression, "fine_passes"):
            ap.error("--fine-passes needs a bundle whose regression is a CorrelationRigidNet")
        regression.fine_passes = int(args.fine_passes)
    if registrar is not None and args.subcell is not None:
        fine = getattr(getattr(registrar.network, "regression", None), "fine", None)
        if not hasattr(fine, "subcell"):
            ap.error("--subcell needs a bundle whose regression is a CorrelationRigidNet")
        fine.subcell = args.subcell
    apply_registrar_options(registrar, args)
    if registrar is not None:
        out(registrar_options_line(registrar))
    all_rows: list[dict] = []
    per_ct: list[tuple[str, list[dict]]] = []
    timing: list[str] = []
    sim_env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    for ct in cts:
        name = data_name(ct, args.protocol, args.cbct)
        data_dir = args.output_dir / name
        cmd = simulate_command(ct, data_dir, args.num_cases, args.seed, protocol=args.protocol, cbct=args.cbct)
        reused = (data_dir / "dataset.json").is_file()
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, env=sim_env, capture_output=True, text=True)
        t_sim = time.perf_counter() - t0
        if proc.returncode != 0:
            msg = (proc.stderr.strip().splitlines() or [f"exit status {proc.returncode}"])[-1]
            out(f"skipped {name}: simulation failed (exit {proc.returncode}): {msg}")
            continue
        dl = data_dir / "dataset.json"
        items, _ = load_datalist(dl)
        info = {it["case_id"]: it for it in items}
        t0 = time.perf_counter()
        res = evaluate_datalist(dl, methods, args.output_dir / "eval" / name, registrar=registrar, device=args.device,
                                progress=False, max_overlays=0, overwrite=True,  # this script's own report folder
                                peer_mask=peer_mask(args))
        t_eval = time.perf_counter() - t0
        ident = identity_tre(items)
        rows = []
        for cid, it in info.items():
            results = {c.method: c for c in res["cases"] if c.case_id == cid}
            rows.append({"ct": name, "case_id": cid, "group": it.get("group", ""), "label": it.get("label", ""),
                         "truth": np.asarray(results[methods[0]].params_true), "identity_tre": ident[cid],
                         "results": results})
        per_ct.append((name, rows))
        all_rows += rows
        timing.append(f"{name}: simulation {t_sim:.0f} s ({'resumed/reused' if reused else 'new'}), evaluation "
                      f"{t_eval:.0f} s for {len(rows)} cases x {len(methods)} methods; load average now "
                      f"{os.getloadavg()[0]:.2f}")
        print(timing[-1], flush=True)
        print("  simulate: " + shlex.join(simulate_command(ct, data_dir, args.num_cases, args.seed, True,
                                                            args.protocol, args.cbct)), flush=True)

    if not per_ct:
        out("no CT could be evaluated")
        return 2
    for name, rows in per_ct:
        out(f"## {name}{training_mark(name)}: {len(rows)} cases")
        out()
        summary_table(rows, methods, out)
        out()
    held = [r for name, rows in per_ct if not is_training_ct(name) for r in rows]
    trained = [name for name, _ in per_ct if is_training_ct(name)]
    if len(per_ct) > 1 and held:
        out(f"## all held-out CTs ({len(held)} cases)" + (f"; not in this table, the training CTs {', '.join(trained)}"
                                                           if trained else ""))
        out()
        summary_table(held, methods, out)
        out()
    failure_list(all_rows, methods, out)

    example = simulate_command(cts[0], args.output_dir / data_name(cts[0], args.protocol, args.cbct), args.num_cases,
                               args.seed, True, args.protocol, args.cbct)
    end_run(out, monitor, t_start, args.results, [
        *timing, f"simulate command (per CT; --output-dir and --phantom change): {shlex.join(example)}",
        "evaluation outputs (cases.csv, summary.json, report.md, report.html with overlays of failed or flagged "
        f"cases): {args.output_dir / 'eval'}/<name>"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
