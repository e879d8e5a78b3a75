"""The failure flag's signals on the clinical-geometry pairs, case by case (issue 15's false alarms).

For every pair made by ``benchmarks/bench_clinical_geometry.py`` (``<pairs-dir>/<ct>/<group>_<nnn>/``), registers it
with the default path (the deformed pairs with their 70 mm ``--roi`` box, as the benchmark does) and prints the
error (TRE over the CT body points in the field of view; landmark error on deformed pairs), success (< 2 mm;
deformed: < rigid floor + 2 mm), the confidence and its two signals (``details.signals``: ``local_gain``, the edge
alignment gained by a small perturbation, limit ``LOCAL_GAIN_LIMIT``; ``swap_tre_mm``, the disagreement with the
swapped-input estimate, 3 mm gives 0.5), and which start won. A success with confidence < 0.5 is a false alarm; the
signal below its limit in each row says which test raised it.

Usage::

    python benchmarks/bench_clinical_geometry.py --cts thorax_4dct_phase00_itkelastix head_tigre_ct \\
        --cases-per-group 5 --simulate-only --output-dir bench_out/clinical   # the pairs
    python benchmarks/bench_confidence_clinical.py --pairs-dir bench_out/clinical [--groups large deformed]
"""

from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import monai_rigidreg  # noqa: E402  (first: its thread policy applies before torch loads)

# isort: split
import numpy as np  # noqa: E402
import torch  # noqa: E402
from bench_clinical_geometry import cached_pairs, case_errors, is_success, pairs_parser, run_method  # noqa: E402
from bench_common import Tee  # noqa: E402


def main() -> None:
    ap = pairs_parser(__doc__, ["small", "large", "deformed"])
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from monai_rigidreg.confidence import CONFIDENCE_THRESHOLD, LOCAL_GAIN_LIMIT
    from monai_rigidreg.simulation.clinical import tre_points

    out = Tee()
    out(f"command: python {' '.join(sys.argv)}")
    out(f"monai-rigidreg {monai_rigidreg.__version__}; flag: confidence < {CONFIDENCE_THRESHOLD}; edge-gain limit "
        f"{LOCAL_GAIN_LIMIT}; swap disagreement 3 mm -> 0.5")
    registrar = monai_rigidreg.RigidRegistrar.from_bundle(device="cpu")
    out("\n| CT | pair | error (mm) | success | confidence | local_gain | swap_tre_mm | start | verdict |")
    out("|---|---|---|---|---|---|---|---|---|")
    counts = {"false alarm": 0, "flagged failure": 0, "missed failure": 0, "ok": 0}
    for ct_name, pair_name, ct, case in cached_pairs(args.pairs_dir, args.groups, out):
        # registered and scored as bench_clinical_geometry.py does (the deformed pairs with their ROI box)
        rec = case.record
        res = run_method("network", ct, case, registrar, roi_supported=True)
        res.update(case_errors(res["params"], rec, tre_points(ct, case.matrix, case.fov)))
        lm = np.asarray(rec["landmarks"]).reshape(-1, 3)
        row = {"deformed": rec["deformation"] is not None, "results": {"network": res},
               "floor": float(rec["rigid_floor_mm"]) if len(lm) >= 3 else float("nan")}
        ok = is_success(row, "network")
        err = res["landmark"] if row["deformed"] else res["tre"]
        verdict = ("false alarm" if res["flagged"] else "ok") if ok else (
            "flagged failure" if res["flagged"] else "missed failure")
        counts[verdict] += 1
        s = res["details"]["signals"]
        out(f"| {ct_name} | {pair_name} | {err:.2f} | {'yes' if ok else 'no'} | {res['confidence']:.2f} | "
            f"{s['local_gain']:.4f} | {s['swap_tre_mm']:.2f} | {res['details']['start']} | {verdict} |")
    out("\n" + ", ".join(f"{k}: {v}" for k, v in counts.items()))
    if args.results is not None:
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text("\n".join(out.lines) + "\n")


if __name__ == "__main__":
    main()
