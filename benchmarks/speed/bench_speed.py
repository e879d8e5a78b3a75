"""Speed of the default registration path (issue 18), next to elastix (and, ``--methods``, SimpleITK and the peer tools
ANTs and greedy) in the same run, on clinical-size pairs.

The pairs: the real thorax planning CT of ``../shared/data`` (256 x 256 x 141 voxels, int16 ``.nii.gz``, held out of
training) as the fixed image, and CBCTs of 128^3 voxels at 1.5 mm (int16 ``.nii.gz``) simulated in the projection
domain from it in clinical geometry (:mod:`monai_rigidreg.simulation.clinical`, group ``small``: up to 40 mm /
30 degrees, isocentre 0-100 mm from the CT centre; made once into ``--output-dir`` and reused).

Printed, each with the command or call it times:

1. **start-up**: wall time of fresh Python processes that import torch, MONAI, the registration stack, and of
   ``monai-rigidreg register --help`` (the floor under any command-line registration);
2. **command line**: ``monai-rigidreg register`` on one pair, default outputs (``.tfm``, resampled CBCT, QC figure,
   ``result.json``, DICOM-free), with ``--no-qc``, and with ``MONAI_RIGIDREG_FULL_EXIT=1`` (the interpreter's
   normal teardown instead of the console script's prompt exit); next to an equivalent elastix command (a Python process
   that imports itk-elastix, reads the pair, registers with elastix's default rigid map and writes the resampled
   CBCT);
3. **in-process**: the registrar loaded once, volumes in memory, the default path with its confidence check
   (``monai_rigidreg.register``), median seconds per case and per stage, TRE and success (< 2 mm) next to
   ``register_elastix`` with the CBCT's field of view as its moving mask on the same cases (and each baseline of
   ``--methods``: ``elastix-nomask``, elastix's default rigid map without a mask; ``sitk`` with the mask; the peer
   tools ``ants`` and ``greedy`` with the mask ``--peer-mask`` gives them; a peer tool counts only after its
   convention check passes), with elastix's time over each method's;
4. **under load**: the in-process median beside one single-threaded busy loop, and beside a second process doing
   the same registrations, as ratios to the quiet median;
5. **batch**: ``monai-rigidreg register --datalist`` over all pairs in one process (model loaded once): wall time
   and cases per second.

Time on a quiet machine: the script prints the load average before and after each section.

Usage::

    python -m benchmarks.speed.bench_speed --output-dir bench_out/speed --cases 6 \
        --results benchmarks/results/bench_speed_<date>.txt
    python -m benchmarks.speed.bench_speed ... --wait-policy ACTIVE   # libgomp's default spinning, for comparison
    python -m benchmarks.speed.bench_speed ... --spin-count 10000     # GOMP_SPINCOUNT: spin this long before sleeping
    python -m benchmarks.speed.bench_speed ... --thorough   # also the thorough path (search and twin every time)
    python -m benchmarks.speed.bench_speed ... --final-norm-mm 12   # also the last level's final pass (a candidate)
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if "--wait-policy" in sys.argv:  # before anything loads libgomp
    os.environ["OMP_WAIT_POLICY"] = sys.argv[sys.argv.index("--wait-policy") + 1]
if "--spin-count" in sys.argv:
    os.environ["GOMP_SPINCOUNT"] = sys.argv[sys.argv.index("--spin-count") + 1]


import numpy as np
import SimpleITK as sitk

import monai_rigidreg  # first: its thread policy applies before torch loads
from benchmarks.bench_common import (
    Tee,
    add_peer_mask_option,
    checked_peers,
    find_cts,
    peer_mask,
    peer_mask_line,
    script_parser,
)

CT_NAME = "thorax_4dct_phase00_itkelastix"
ELASTIX_COMMAND = """
import sys, SimpleITK as sitk
from monai_rigidreg.registration.classical import register_elastix
from monai_rigidreg.core.geometry import params_to_sitk
ct, cb, out = sys.argv[1:4]
fixed = sitk.ReadImage(ct, sitk.sitkFloat32); moving = sitk.ReadImage(cb, sitk.sitkFloat32)
res = register_elastix(fixed, moving)
tfm = params_to_sitk(res.params, res.center)
sitk.WriteTransform(tfm, out + '/elastix.tfm')
sitk.WriteImage(sitk.Resample(moving, fixed, tfm, sitk.sitkLinear, -1000.0), out + '/registered.nii.gz', True)
"""


def make_pairs(ct_path: Path, folder: Path, n: int, seed: int) -> list[Path]:
    """``n`` clinical pairs (CBCT 128^3 at 1.5 mm) in ``folder/case_k`` with their TRE points
    (``tre_points.npy``; made once, reused)."""
    from monai_rigidreg.simulation.clinical import (
        CLINICAL_GROUPS,
        ClinicalCBCTSpec,
        load_clinical_case,
        load_planning_ct,
        make_clinical_case,
        save_clinical_case,
        tre_points,
    )

    spec = ClinicalCBCTSpec(size=(128, 128, 128), spacing=1.5)
    ct = None
    out = []
    for k in range(n):
        case_dir = folder / f"case_{k}"
        case = load_clinical_case(case_dir)
        if case is None:
            ct = load_planning_ct(ct_path) if ct is None else ct
            case = make_clinical_case(ct, CLINICAL_GROUPS["small"], seed + k, f"case_{k}", spec)
            save_clinical_case(case, case_dir, fixed=ct_path)
        if not (case_dir / "tre_points.npy").is_file():
            ct = load_planning_ct(ct_path) if ct is None else ct
            np.save(case_dir / "tre_points.npy", tre_points(ct, case.matrix, case.fov))
        out.append(case_dir)
    return out


def wall(cmd: list[str], repeats: int, before=None, env: dict[str, str] | None = None) -> float:
    """Median wall seconds of a command (``before()`` runs untimed ahead of each repeat; ``env``: extra
    environment variables)."""
    times = []
    environ = None if env is None else {**os.environ, **env}
    for _ in range(repeats):
        if before is not None:
            before()
        t = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=environ)
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def load_text() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def load_case(case_dir: Path) -> tuple[dict, sitk.Image, np.ndarray]:
    """A pair's ground-truth record, its CBCT (float32) and the CT body points its TRE is measured on."""
    record = json.loads((case_dir / "case.json").read_text())
    cbct = sitk.ReadImage(str(case_dir / "cbct.nii.gz"), sitk.sitkFloat32)
    return record, cbct, np.load(case_dir / "tre_points.npy")


def tre_mm(params: np.ndarray, center: np.ndarray, record: dict, points: np.ndarray) -> float:
    """Mean distance (mm) at ``points`` between the estimate (about ``center``) and the ground truth."""
    from monai_rigidreg.core.geometry import params_to_matrix
    from monai_rigidreg.registration.search import matrix_distance_mm

    return matrix_distance_mm(params_to_matrix(params, center), np.asarray(record["matrix"]), points)


def in_process(registrar, ct: sitk.Image, cases: list[Path], thorough: bool | None = None) -> list[dict]:
    """The default path (``thorough=True``: the thorough path) on every case (after one warm-up call): seconds,
    stage seconds, TRE, the flag and whether the network-led path's fallback ran."""
    rows = []
    # warm-up: allocator, FFT plans, caches
    monai_rigidreg.register(ct, load_case(cases[0])[1], model=registrar, thorough=thorough)
    for case_dir in cases:
        record, cbct, points = load_case(case_dir)
        t = time.perf_counter()
        r = monai_rigidreg.register(ct, cbct, model=registrar, thorough=thorough)
        dt = time.perf_counter() - t
        rows.append({"case": case_dir.name, "time_s": dt, "stages": dict(r.timings),
                     "tre": tre_mm(r.params, r.center, record, points), "flagged": bool(r.flagged),
                     "fallback": bool((r.details.get("fallback") or {}).get("run"))})
    return rows


def stage_medians(rows: list[dict]) -> str:
    """The median seconds of every stage over ``rows`` (0 where a stage did not run), in the order they ran."""
    stages = list(dict.fromkeys(k for r in rows for k in r["stages"]))
    return ", ".join(f"{k} {np.median([r['stages'].get(k, 0.0) for r in rows]):.2f}" for k in stages)


BASELINES = {"elastix": "elastix (default rigid map, CBCT FOV mask)",
             "elastix-nomask": "elastix (default rigid map, no mask)",
             "sitk": "SimpleITK (Mattes MI, CBCT FOV mask)",
             "ants": "ANTs (antspyx, Rigid preset)",
             "greedy": "greedy (picsl-greedy, -a -dof 6, NMI)"}
"""The in-process baselines; the peer tools' (``ants``, ``greedy``) mask is ``--peer-mask``'s
(:func:`baseline_label`)."""


def baseline_label(method: str, use_mask: bool | None = None) -> str:
    """:data:`BASELINES`' label of ``method``, a peer tool's with the mask it got (``use_mask`` as
    :func:`~monai_rigidreg.registration.peers.register_peer`'s)."""
    from monai_rigidreg.registration.peers import PEER_METHODS, peer_uses_mask

    if method not in PEER_METHODS:
        return BASELINES[method]
    return BASELINES[method][:-1] + (", CBCT FOV mask)" if peer_uses_mask(method, use_mask) else ", no mask)")


def baseline_rows(ct: sitk.Image, cases: list[Path], method: str = "elastix",
                  use_mask: bool | None = None) -> list[dict]:
    """A baseline of :data:`BASELINES` on every case: seconds and TRE (``use_mask``: the peer tools', as
    :func:`~monai_rigidreg.registration.peers.register_peer`'s)."""
    from monai_rigidreg.registration.classical import register_elastix, register_sitk
    from monai_rigidreg.registration.peers import register_peer

    rows = []
    for case_dir in cases:
        record, cbct, points = load_case(case_dir)
        fov = sitk.ReadImage(str(case_dir / "cbct_fov.nii.gz"))
        t = time.perf_counter()
        if method == "elastix":
            res = register_elastix(ct, cbct, moving_mask=fov)
        elif method == "elastix-nomask":
            res = register_elastix(ct, cbct)
        elif method == "sitk":
            res = register_sitk(ct, cbct, moving_mask=fov)
        else:
            res = register_peer(method, ct, cbct, moving_mask=fov, use_mask=use_mask)
        dt = time.perf_counter() - t
        rows.append({"case": case_dir.name, "time_s": dt, "tre": tre_mm(res.params, res.center, record, points)})
    return rows


def worker(cases_file: Path) -> None:
    """A second registration process: registers the cases in a loop until killed."""
    registrar = monai_rigidreg.RigidRegistrar.from_bundle()
    cases = [Path(p) for p in json.loads(cases_file.read_text())]
    ct = sitk.ReadImage(json.loads((cases[0] / "case.json").read_text())["fixed"], sitk.sitkFloat32)
    while True:
        for case_dir in cases:
            monai_rigidreg.register(ct, load_case(case_dir)[1], model=registrar)


def summarize(out: Tee, name: str, rows: list[dict], ref: float | None = None) -> float:
    t = float(np.median([r["time_s"] for r in rows]))
    tre = np.asarray([r["tre"] for r in rows])
    ratio = f", elastix / this {ref / t:.2f}x" if ref is not None else ""
    out(f"| {name} | {len(rows)} | {t:.2f} | {tre.mean():.2f} | {np.median(tre):.2f} | {np.mean(tre < 2) * 100:.0f}% "
        f"| {ratio.lstrip(', ')} |")
    return t


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--output-dir", type=Path, default=Path("bench_out/speed"))
    ap.add_argument("--cases", type=int, default=6)
    ap.add_argument("--seed", type=int, default=18000)
    ap.add_argument("--cli-repeats", type=int, default=3)
    ap.add_argument("--wait-policy", default=None, help="OMP_WAIT_POLICY for this run (default: the package's)")
    ap.add_argument("--spin-count", default=None, help="GOMP_SPINCOUNT for this run (default: the package's)")
    ap.add_argument("--thorough", action="store_true",
                    help="also time the thorough path (register(..., thorough=True)) on the same cases in section 3")
    ap.add_argument("--final-norm-mm", type=float, default=None,
                    help="also time the default path with the last level's final pass on the normalised local "
                         "contrast at this sigma (RigidRegistrar native_final_norm_mm, off by default) in section 3")
    ap.add_argument("--skip", nargs="*", default=[], choices=["startup", "cli", "load", "batch"])
    ap.add_argument("--methods", nargs="+", default=["elastix"], choices=list(BASELINES),
                    help="baselines of the in-process section beside the default path (default elastix; also sitk; "
                         "elastix-nomask, elastix without the CBCT's field of view as its mask; the peer tools ants "
                         "and greedy, the 'bench' extra); elastix is always run, the ratios' reference")
    add_peer_mask_option(ap)
    ap.add_argument("--results", type=Path, default=None)
    ap.add_argument("--worker", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker is not None:
        worker(args.worker)
        return

    out = Tee()
    t_run = time.perf_counter()
    import torch

    out(f"command: python {' '.join(sys.argv)}")
    out(f"date: {time.strftime('%Y-%m-%dT%H:%M:%S%z')}; machine: {os.cpu_count()} CPU cores; torch "
        f"{torch.__version__} ({torch.get_num_threads()} threads), SimpleITK {sitk.Version_VersionString()}, "
        f"monai-rigidreg {monai_rigidreg.__version__}; OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}, "
        f"GOMP_SPINCOUNT={os.environ.get('GOMP_SPINCOUNT')}")
    out(f"load average at start (1/5/15 min): {load_text()}")
    cts = find_cts([CT_NAME], out, (CT_NAME,))
    if not cts:
        out("no CT: nothing to measure")
        return
    ct_path = cts[0]
    args.output_dir.mkdir(parents=True, exist_ok=True)
    cases = make_pairs(ct_path, args.output_dir, args.cases, args.seed)
    ct = sitk.ReadImage(str(ct_path), sitk.sitkFloat32)
    first = sitk.ReadImage(str(cases[0] / "cbct.nii.gz"))
    stored = sitk.ImageFileReader()
    stored.SetFileName(str(ct_path))
    stored.ReadImageInformation()
    out(f"pairs: {len(cases)} ({args.output_dir}); CT {ct.GetSize()} voxels "
        f"{sitk.GetPixelIDValueAsString(stored.GetPixelID())}, CBCT {first.GetSize()} at {first.GetSpacing()[0]} mm "
        f"{first.GetPixelIDTypeAsString()}")
    exe = shutil.which("monai-rigidreg") or "monai-rigidreg"

    if "startup" not in args.skip:
        out("\n## 1. Start-up (fresh processes, median of 3; wall seconds)\n")
        out("| command | s |\n|---|---|")
        for label, cmd in [("python -c pass", [sys.executable, "-c", "pass"]),
                           ("python -c 'import torch'", [sys.executable, "-c", "import torch"]),
                           ("python -c 'import monai'", [sys.executable, "-c", "import monai"]),
                           ("python -c 'import monai_rigidreg.registration.registrar'",
                            [sys.executable, "-c", "import monai_rigidreg.registration.registrar"]),
                           ("python -c 'import itk' (elastix)",
                            [sys.executable, "-c", "import itk; itk.ElastixRegistrationMethod"]),
                           ("monai-rigidreg --version", [exe, "--version"]),
                           ("monai-rigidreg register --help", [exe, "register", "--help"])]:
            out(f"| `{label}` | {wall(cmd, 3):.2f} |")
        out(f"\nload average (1/5/15 min): {load_text()}")

    if "cli" not in args.skip:
        out("\n## 2. One registration from the command line (median of "
            f"{args.cli_repeats}; wall seconds, outputs written)\n")
        tmp = Path(tempfile.mkdtemp(prefix="bench_speed_"))
        cbct = str(cases[0] / "cbct.nii.gz")

        def fresh() -> None:
            shutil.rmtree(tmp / "o", ignore_errors=True)
            (tmp / "o").mkdir()

        base = [exe, "register", "--fixed", str(ct_path), "--moving", cbct, "--output-dir", str(tmp / "o"),
                "--overwrite"]
        rows = [("`monai-rigidreg register` (default outputs, QC figure)", base, None),
                ("`monai-rigidreg register --no-qc`", base + ["--no-qc"], None),
                ("the same as the first row, `MONAI_RIGIDREG_FULL_EXIT=1` (the interpreter's normal teardown)", base,
                 {"MONAI_RIGIDREG_FULL_EXIT": "1"}),
                ("elastix equivalent (python: import, read, elastix rigid, write .tfm + resampled)",
                 [sys.executable, "-c", ELASTIX_COMMAND, str(ct_path), cbct, str(tmp / "o")], None)]
        out("| command | s |\n|---|---|")
        for label, cmd, env in rows:
            out(f"| {label} | {wall(cmd, args.cli_repeats, before=fresh, env=env):.2f} |")
        fresh()
        subprocess.run(base, check=True, capture_output=True)
        runtime = json.loads((tmp / "o" / "result.json").read_text())["runtime_s"]
        out("\nstages of the registration in that command (result.json runtime_s): "
            + ", ".join(f"{k} {v:.2f}" for k, v in runtime.items()))
        shutil.rmtree(tmp, ignore_errors=True)
        out(f"load average (1/5/15 min): {load_text()}")

    out("\n## 3. In-process (registrar loaded once, volumes in memory; the network path with its confidence check)\n")
    baselines = checked_peers(list(dict.fromkeys(["elastix", *args.methods])), out)
    registrar = monai_rigidreg.RigidRegistrar.from_bundle()
    ours = in_process(registrar, ct, cases)
    thorough = in_process(registrar, ct, cases, thorough=True) if args.thorough else None
    final_norm = None
    if args.final_norm_mm is not None:
        shipped, registrar.native_final_norm_mm = registrar.native_final_norm_mm, float(args.final_norm_mm)
        final_norm = in_process(registrar, ct, cases)
        registrar.native_final_norm_mm = shipped
    peer_mask_line(args, baselines, out)
    rows_of = {m: baseline_rows(ct, cases, m, peer_mask(args)) for m in baselines}
    t_elx = float(np.median([r["time_s"] for r in rows_of["elastix"]]))
    out("| method | n | median s / case | mean TRE (mm) | median TRE (mm) | success (<2 mm) | speed-up |")
    out("|---|---|---|---|---|---|---|")
    t_ours = summarize(out, "monai-rigidreg (default path)", ours, t_elx)
    if thorough is not None:
        summarize(out, "monai-rigidreg (--thorough)", thorough, t_elx)
    if final_norm is not None:
        summarize(out, f"monai-rigidreg (final pass at {args.final_norm_mm:g} mm)", final_norm, t_elx)
    t_of = {m: summarize(out, baseline_label(m, peer_mask(args)), rows_of[m], None if m == "elastix" else t_elx)
            for m in baselines}
    if "elastix-nomask" in t_of:
        out(f"\nthe default path against elastix's default rigid map without a mask: "
            f"{t_of['elastix-nomask'] / t_ours:.2f}x")
    out("\nmedian seconds per stage (0 where a stage did not run): " + stage_medians(ours))
    out(f"flagged: {sum(r['flagged'] for r in ours)} of {len(ours)}; network-led path's fallback ran on "
        f"{sum(r['fallback'] for r in ours)} of {len(ours)}")
    if thorough is not None:
        out("--thorough, median seconds per stage: " + stage_medians(thorough))
        out(f"--thorough flagged: {sum(r['flagged'] for r in thorough)} of {len(thorough)}")
    if final_norm is not None:
        out("--final-norm-mm, median seconds per stage: " + stage_medians(final_norm))
    out(f"load average (1/5/15 min): {load_text()}")

    if "load" not in args.skip:
        out("\n## 4. Under load (the same in-process cases)\n")
        out("| beside | median s / case | slowdown |\n|---|---|---|\n| nothing (section 3) | "
            f"{t_ours:.2f} | 1.00x |")
        cases_file = args.output_dir / "cases.json"
        cases_file.write_text(json.dumps([str(c) for c in cases]))
        for label, cmd in [("one single-threaded busy loop", [sys.executable, "-c", "while True: pass"]),
                           ("a second registration process (same cases, in a loop)",
                            [sys.executable, os.path.abspath(__file__), "--worker", str(cases_file)]
                            + (["--wait-policy", args.wait_policy] if args.wait_policy else [])
                            + (["--spin-count", args.spin_count] if args.spin_count else []))]:
            proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            try:
                time.sleep(3.0 if "busy" in label else 15.0)  # the second registrar loads its model first
                t = float(np.median([r["time_s"] for r in in_process(registrar, ct, cases)]))
            finally:
                proc.kill()
                proc.wait()
            out(f"| {label} | {t:.2f} | {t / t_ours:.2f}x |")
            time.sleep(2.0)
        out(f"\nload average (1/5/15 min): {load_text()}")

    if "batch" not in args.skip:
        out("\n## 5. Batch: `monai-rigidreg register --datalist` (one process, model loaded once)\n")
        tmp = Path(tempfile.mkdtemp(prefix="bench_speed_batch_"))
        datalist = tmp / "pairs.json"
        datalist.write_text(json.dumps([{"fixed": str(ct_path), "moving": str((c / "cbct.nii.gz").resolve()),
                                         "case_id": c.name} for c in cases]))
        out("| command | pairs | wall s | cases / s |\n|---|---|---|---|")
        for label, extra in [("default outputs", []), ("--no-qc", ["--no-qc"])]:
            shutil.rmtree(tmp / "o", ignore_errors=True)
            t = time.perf_counter()
            subprocess.run([exe, "register", "--datalist", str(datalist), "--output-dir", str(tmp / "o"), "-q"]
                           + extra, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            dt = time.perf_counter() - t
            out(f"| {label} | {len(cases)} | {dt:.1f} | {len(cases) / dt:.3f} |")
        shutil.rmtree(tmp, ignore_errors=True)
        out(f"\nload average (1/5/15 min): {load_text()}")

    out(f"\ntotal wall time {time.perf_counter() - t_run:.0f} s")
    out.write(args.results)


if __name__ == "__main__":
    main()
