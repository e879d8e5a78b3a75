"""The last level's intensity-bias model, or its local-contrast scale, on the clinical-geometry pairs (issue 15's
precision target).

``--highpass-sigmas``: instead of the bias degrees, the Gaussian (mm) of the last level's local-contrast feature
(``RigidRegistrar(native_highpass_sigma_mm=...)``; 16 is the fine stage's own, the bundle's setting before 0.4.5),
the bias degrees as the bundle ships them.

The last level (:func:`monai_rigidreg.registration.last_level.refine_native`) estimates the pose jointly with an
intensity bias, a polynomial per feature channel (``RigidRegistrar(native_bias_degree=...,
native_bias_degree_roi=...)``; the bundle's ``native_bias_degree`` without and ``native_bias_degree_roi`` with a match
region). Each degree here is given to both, so the whole-FOV pairs and the ``--roi`` deformed pairs see the same model.
This benchmark registers the rigid clinical-geometry pairs made by ``benchmarks/accuracy/bench_clinical_geometry.py``
with the default path once per degree and prints the error per case (TRE over the CT body points in the field of view;
on deformed pairs, ``--groups deformed``, the landmark error in the ROI, registered with the ROI box as
``bench_clinical_geometry.py`` does) and over the cases every degree registers (TRE < 2 mm; deformed: landmark error
< rigid floor + 2 mm), so the degrees are compared on the same successes.

Usage::

    python -m benchmarks.accuracy.bench_clinical_geometry --cts thorax_4dct_phase00_itkelastix head_tigre_ct \\
        --cases-per-group 5 --simulate-only --output-dir bench_out/clinical   # the pairs
    python -m benchmarks.ablation.bench_native_bias --pairs-dir bench_out/clinical --degrees 2 0 -1 \\
        --results benchmarks/results/0.4.2/bench_native_bias_2026-12-02.txt
    python -m benchmarks.ablation.bench_native_bias --pairs-dir bench_out/clinical --groups small large \\
        --highpass-sigmas 16 4 --threads 2 --results benchmarks/results/0.4.5/bench_native_highpass_2026-12-02.txt
"""

from __future__ import annotations

import sys

import monai_rigidreg  # first: its thread policy applies before torch loads

# isort: split
import numpy as np
import torch

from benchmarks.accuracy.bench_clinical_geometry import (
    SUCCESS_MM,
    cached_pairs,
    case_errors,
    is_success,
    pairs_parser,
    run_method,
)
from benchmarks.bench_common import Tee


def main() -> None:
    ap = pairs_parser(__doc__, ["small", "large"])
    ap.add_argument("--degrees", nargs="+", type=int, default=[2, 0, -1])
    ap.add_argument("--highpass-sigmas", nargs="+", type=float, default=None,
                    help="vary native_highpass_sigma_mm instead of the bias degrees")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from monai_rigidreg.simulation.clinical import tre_points

    out = Tee()
    out(f"command: python {' '.join(sys.argv)}")
    if args.highpass_sigmas:
        out(f"monai-rigidreg {monai_rigidreg.__version__}; the default path, native_highpass_sigma_mm varied")
        label = "sigma"
        registrars = {v: monai_rigidreg.RigidRegistrar.from_bundle(device="cpu", native_highpass_sigma_mm=v)
                      for v in args.highpass_sigmas}
    else:
        out(f"monai-rigidreg {monai_rigidreg.__version__}; the default path, native_bias_degree and "
            "native_bias_degree_roi varied together")
        label = "degree"
        registrars = {d: monai_rigidreg.RigidRegistrar.from_bundle(device="cpu", native_bias_degree=d,
                                                                   native_bias_degree_roi=d)
                      for d in args.degrees}
    values = list(registrars)
    rows: list[tuple[str, dict[float, float]]] = []
    success: list[dict[float, bool]] = []
    for ct_name, pair_name, ct, case in cached_pairs(args.pairs_dir, args.groups, out):
        points = tre_points(ct, case.matrix, case.fov)
        deformed = case.record["deformation"] is not None
        floor = float(case.record.get("rigid_floor_mm") or 0.0) if deformed else 0.0
        tre, ok = {}, {}
        for d, registrar in registrars.items():
            res = run_method("network", ct, case, registrar, roi_supported=True)
            res.update(case_errors(res["params"], case.record, points))
            tre[d] = res["landmark"] if deformed else res["tre"]
            ok[d] = is_success({"deformed": deformed, "floor": floor, "results": {"network": res}}, "network")
        rows.append((f"{ct_name} {pair_name}", tre))
        success.append(ok)
        print(rows[-1][0], {d: round(v, 3) for d, v in tre.items()}, flush=True)
    out("\n| case | " + " | ".join(f"{label} {d:g}" for d in values) + " |")
    out("|---|" + "---|" * len(values))
    for name, tre in rows:
        out(f"| {name} | " + " | ".join(f"{tre[d]:.3f}" for d in values) + " |")
    common = [tre for (_, tre), ok in zip(rows, success) if all(ok.values())]
    out(f"\nover the {len(common)} cases every {label} registers (TRE < {SUCCESS_MM} mm; deformed: landmark error "
        f"< floor + {SUCCESS_MM} mm); error = TRE, on deformed pairs the landmark error:")
    out(f"| {label} | successes (all cases) | mean error (mm) | median error (mm) | better than {label} "
        f"{values[0]:g} on |")
    out("|---|---|---|---|---|")
    for d in values:
        vals = np.array([t[d] for t in common])
        ref = np.array([t[values[0]] for t in common])
        n_ok = sum(ok[d] for ok in success)
        out(f"| {d:g} | {n_ok} of {len(rows)} | {vals.mean():.3f} | {np.median(vals):.3f} | "
            f"{int((vals < ref).sum())} of {len(vals)} |")
    out.write(args.results)


if __name__ == "__main__":
    main()
