"""With or without the fine stage: which end pose is right, and do the image-match signals tell?

The weight-free fine stage's coarse levels correct a learned estimate that is a few millimetres off (``bench_speed``'s
``case_2``) and, on a large patient's noisy, scatter-shaded CBCTs, carry a right one tens of millimetres away
(``docs/results.md``, "A large patient's clinical CBCTs"). For each given pair this script runs the default path
with the fallback off (``RigidRegistrar.lead_fallback = False``: the network, the fine stage, the last level, the
check) twice, with the bundle's fine stage and with its steps set to zero (the network's estimate straight to the last
level), and prints each end pose's TRE and the signals a chooser between the two could read: ``edge_ncc`` and
``ncc_after`` (the confidence's image match), the last level's ``residual_var`` and ``local_gain``; then which pose
each signal would pick and whether that is the better one.

Pairs: folders with ``case.json`` (``fixed``, ``matrix``, ``landmarks`` or a ``tre_points.npy``), ``cbct.nii.gz`` and
``cbct_fov.nii.gz``, as ``bench_clinical_geometry`` and ``bench_speed`` write them.

Usage::

    python -m benchmarks.accuracy.bench_fine_stage_choice \\
        bench_out/clinical_aec/abdomen_pelvis_tcia_tcga_ov_ct/{small_000,small_001,large_000,large_003} \\
        bench_out/speed/case_2 --results benchmarks/results/0.6.2.dev/bench_fine_stage_choice_2026-12-06.txt
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from benchmarks.bench_common import end_run, script_parser, start_cpu_run

SIGNALS = {"edge_ncc": +1, "ncc_after": +1, "residual_var": -1, "local_gain": -1}
"""Each signal and its sense (+1: higher is the better fit)."""
TIE_MM = 0.1
"""A pick counts as right where its TRE is within this of the better pose's (both right to a tenth of a mm)."""


def _registrars(bundle: str | None):
    import torch

    from monai_rigidreg.networks import GaussNewtonStage
    from monai_rigidreg.registration import RigidRegistrar

    out = {}
    for name, zero in (("fine stage", False), ("no fine stage", True)):
        reg = RigidRegistrar.from_bundle(bundle, device="cpu")
        reg.lead_fallback = False
        if zero:
            for module in vars(reg).values():
                if isinstance(module, torch.nn.Module):
                    for sub in module.modules():
                        if isinstance(sub, GaussNewtonStage):
                            sub.iterations = tuple(0 for _ in sub.iterations)
        out[name] = reg
    return out


def main(argv: list[str] | None = None) -> int:
    ap = script_parser(__doc__)
    ap.add_argument("pairs", nargs="+", type=Path, help="pair folders (case.json, cbct.nii.gz, cbct_fov.nii.gz)")
    ap.add_argument("--bundle", default=None, help="bundle directory (default: the shipped one)")
    args, out, monitor, t0 = start_cpu_run(ap, argv, __spec__.name if __spec__ else "bench_fine_stage_choice",
                                           lambda a: a.bundle or "the shipped bundle")
    import SimpleITK as sitk

    import monai_rigidreg
    from monai_rigidreg.core.geometry import transform_points

    registrars = _registrars(args.bundle)
    out()
    out("| pair | end pose | TRE (mm) | " + " | ".join(SIGNALS) + " |")
    out("|---|---|---|" + "---|" * len(SIGNALS))
    right = {k: 0 for k in SIGNALS}
    n = 0
    for folder in args.pairs:
        case = json.loads((folder / "case.json").read_text())
        ct = sitk.ReadImage(case["fixed"], sitk.sitkFloat32)
        cbct = sitk.ReadImage(str(folder / "cbct.nii.gz"), sitk.sitkFloat32)
        fov = sitk.ReadImage(str(folder / "cbct_fov.nii.gz"))
        truth = np.asarray(case["matrix"], dtype=np.float64)
        points = (np.asarray(case["landmarks"]) if "landmarks" in case
                  else np.load(folder / "tre_points.npy"))
        rows = {}
        for name, reg in registrars.items():
            res = monai_rigidreg.register(ct, cbct, model=reg, moving_fov=fov, resample_moving=False)
            tre = float(np.linalg.norm(transform_points(np.asarray(res.matrix), points)
                                       - transform_points(truth, points), axis=1).mean())
            signals = {**res.details.get("signals", {}), **res.details.get("native_level", {})}
            rows[name] = (tre, {k: float(signals.get(k, float("nan"))) for k in SIGNALS})
            out(f"| {folder.parent.name}/{folder.name} | {name} | {tre:.2f} | "
                + " | ".join(f"{rows[name][1][k]:.4g}" for k in SIGNALS) + " |")
        best = min(tre for tre, _ in rows.values())
        n += 1
        for key, sense in SIGNALS.items():
            pick = max(rows, key=lambda k: sense * rows[k][1][key])
            right[key] += rows[pick][0] <= best + TIE_MM
    out()
    out(f"Which end pose each signal picks (the higher edge_ncc / ncc_after, the lower residual_var / local_gain), "
        f"right on how many of {n} pairs (right: a TRE within {TIE_MM} mm of the better pose's): "
        + ", ".join(f"{k} {v} of {n}" for k, v in right.items()))
    out()
    end_run(out, monitor, t0, args.results, ["the default path with the fallback off (lead_fallback False), one "
                                             "registrar with the bundle's fine stage and one with its steps at zero"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
