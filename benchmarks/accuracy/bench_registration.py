"""Accuracy and speed of network, network+refine, SimpleITK and elastix on a held-out paper-protocol set.

The set is simulated here (never used in training): the reference study's protocol (translations of 5-15 mm and
rotations up to 30 degrees, single and multi-axis) applied to

* the stock Shepp-Logan phantom at the paper's grids (Sim-CT 256^3 at 1 mm, CBCT 128^3 at 1 mm = an interior
  128 mm field of view), and
* the thorax planning CT of ``../shared/data`` (held out from training; skipped if absent).

Every method runs on the same cases in one process, on ``--threads`` CPU threads (default 2). Printed: the paper's
Tables 1 and 2 per method, TRE, success rate (TRE < 2 mm) and median seconds per case (volumes in memory), and
the network's time per case including reading both volumes from disk.

Usage::

    python -m benchmarks.accuracy.bench_registration --cases 14 --max-cases 6 --output-dir bench_out
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_common import script_parser


def simulate_sets(out: Path, cases: int, thorax: Path | None, seed: int) -> list[Path]:
    from monai_rigidreg.simulation import simulate_dataset

    lists = [simulate_dataset(out / "shepp_logan_paper", phantom="shepp-logan", protocol="paper", num_cases=cases,
                              preset="paper", seed=seed, progress=False)]
    if thorax is not None and thorax.is_file():
        lists.append(simulate_dataset(out / "thorax_paper", phantom=str(thorax), protocol="paper", num_cases=cases,
                                      preset="paper", seed=seed + 1, progress=False,
                                      simct_size=(256, 256, 160), simct_spacing=(1.5, 1.5, 2.0),
                                      ct_frame=False))  # centred on the origin, as the results were measured
    return lists


def subset_datalist(datalist: Path, n: int, out_dir: Path) -> Path:
    """A datalist of ``n`` items of ``datalist`` (absolute paths): the first two (the paper's showcase cases) and an
    even spread of the rest, so that multi-axis cases are included."""
    from monai_rigidreg.evaluation.evaluate import load_datalist

    items, _ = load_datalist(datalist)
    rest = np.linspace(2, len(items) - 1, max(n - 2, 0)).round().astype(int).tolist() if len(items) > 2 else []
    picked = [items[i] for i in sorted({*range(min(2, len(items))), *rest})][:n]
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "subset.json"
    path.write_text(json.dumps({"training": picked}, indent=1))
    return path


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--cases", type=int, default=21, help="paper-protocol cases per object (max 63)")
    ap.add_argument("--output-dir", type=Path, default=Path("bench_registration_out"))
    ap.add_argument("--methods", nargs="+", default=["network", "network+refine", "sitk", "elastix"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--bundle", type=Path, default=None)
    ap.add_argument("--seed", type=int, default=5000)
    ap.add_argument("--no-thorax", action="store_true")
    ap.add_argument("--max-cases", type=int, default=None,
                    help="evaluate N of the simulated cases per object: the two showcase cases and an even spread")
    args = ap.parse_args()

    import torch

    torch.set_num_threads(args.threads)
    import SimpleITK as sitk

    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(args.threads)
    from monai_rigidreg.evaluation import evaluate_datalist
    from monai_rigidreg.evaluation.report import format_report, summarize
    from monai_rigidreg.io.shared_data import find_data_file
    from monai_rigidreg.registration.classical import elastix_available
    from monai_rigidreg.registration.registrar import RigidRegistrar

    methods = [m for m in args.methods if m != "elastix" or elastix_available()]
    thorax = None if args.no_thorax else find_data_file("thorax_4dct_phase00_itkelastix.nii.gz")
    t0 = time.perf_counter()
    lists = simulate_sets(args.output_dir / "data", args.cases, thorax, args.seed)
    t_sim = time.perf_counter() - t0
    registrar = RigidRegistrar.from_bundle(args.bundle, device="cpu")
    all_cases = []
    lists_used: list[Path] = []
    for dl in lists:
        if args.max_cases is not None:  # <output-dir>/<set>/subset.json: the other benchmarks' default datalists
            dl = subset_datalist(dl, args.max_cases, args.output_dir / dl.parent.name)
        # the report in a folder of its own (evaluate_datalist replaces a folder holding its own files only)
        res = evaluate_datalist(dl, methods, args.output_dir / dl.parent.name / "report", registrar=registrar,
                                progress=False, overwrite=True)
        all_cases += res["cases"]
        print(f"\n## {dl.parent.name} ({len(res['cases']) // len(methods)} cases)\n")
        lists_used.append(dl)
        print(res["report"])
    print(f"\n## all objects ({len(all_cases) // len(methods)} cases)\n")
    summary = summarize(all_cases)
    print(format_report(summary))

    # network time per case including reading the two volumes (the user-facing path)
    from monai_rigidreg.evaluation.evaluate import load_datalist

    items, _ = load_datalist(lists_used[0])
    times = []
    for it in items[: min(10, len(items))]:
        t = time.perf_counter()
        registrar(it["fixed"], it["moving"], resample_moving=False, assess=False)
        times.append(time.perf_counter() - t)
    net_times = [c.extra["timings"]["network"] for c in all_cases if c.method == "network"]
    print(f"network forward (cascade) only: median {np.median(net_times):.3f} s per case")
    print(f"network path including reading both volumes (paper grids, no QC/confidence): median "
          f"{np.median(times):.3f} s per case")
    print(f"simulation of the benchmark set: {t_sim:.0f} s; threads: {args.threads}")
    (args.output_dir / "summary.json").write_text(json.dumps(
        {"summary": summary, "network_s_with_io": float(np.median(times)), "threads": args.threads}, indent=1))


if __name__ == "__main__":
    main()
