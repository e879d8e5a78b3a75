"""Does a clinical-geometry CBCT show the anatomy? Per real CT and pair: the line integral through the isocentre and
the NCC between the CBCT and the planning CT under the true motion, with the physics each degradation at a time.

A CBCT simulated from the whole body in the beam can be photon-starved or scatter-dominated where the patient is
large (every registration method then fails on it, which says nothing about the methods). For each CT this script
re-simulates one rigid clinical pair (``bench_clinical_geometry``'s pairs: the same isocentre and motion; noise seed
1, not the pair's own) with the physics as configured (``ClinicalCBCTSpec``'s, the automatic exposure control
included), without the exposure control, ideal, and with one degradation alone; and reads every cached rigid pair's
CBCT as it is (deformed pairs are left out: their truth is not the rigid motion; so are pairs simulated with another
acquisition than the current one).

* ``p_centre``: the median over the views of the ideal line integral of the detector's centre pixel (the ray through
  the isocentre); the exposure control raises the photon count by ``exp(p_centre - exposure_reference)``.
* ``NCC``: the CT resampled through the inverse of the true motion onto the CBCT grid against the CBCT, over its field
  of view (1 = the CBCT shows the CT's anatomy up to a linear intensity change).

Usage::

    python -m benchmarks.simulation.bench_clinical_image_quality --pairs-dir bench_out/clinical \\
        --results benchmarks/results/0.6.2.dev/bench_clinical_image_quality_2026-12-06.txt

About 10 s per re-simulated CBCT on 2 cores (six variants per CT).
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks.accuracy.bench_clinical_geometry import current_acquisition
from benchmarks.bench_common import end_run, find_cts, script_parser, start_cpu_run


def truth_ncc(ct_image, cbct, fov, matrix: np.ndarray) -> float:
    """NCC of the CBCT and the CT under the true fixed -> moving ``matrix`` (4x4, LPS mm), over the field of view."""
    import SimpleITK as sitk

    from monai_rigidreg.core.geometry import invert_matrix, matrix_to_sitk

    tfm = matrix_to_sitk(invert_matrix(matrix))  # output (CBCT) points -> CT points
    ct_on_cbct = sitk.GetArrayFromImage(sitk.Resample(ct_image, cbct, tfm, sitk.sitkLinear, -1000.0))
    inside = sitk.GetArrayFromImage(fov) > 0
    a = ct_on_cbct[inside] - ct_on_cbct[inside].mean()
    b = sitk.GetArrayFromImage(cbct)[inside].astype(np.float64)
    b = b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def main(argv: list[str] | None = None) -> int:
    ap = script_parser(__doc__)
    ap.add_argument("--cts", nargs="*", default=None, help="real CTs (names in ../shared/data or paths; default all)")
    ap.add_argument("--pairs-dir", default="bench_out/clinical",
                    help="bench_clinical_geometry's --output-dir (its pairs are read, not written)")
    ap.add_argument("--case", default="small_000", help="the pair re-simulated per CT")
    args, out, monitor, t0 = start_cpu_run(ap, argv, __spec__.name if __spec__ else "bench_clinical_image_quality",
                                           "none (simulation only)", threads=2)
    import SimpleITK as sitk

    from monai_rigidreg.io.shared_data import HELD_OUT_CTS, TRAINING_CTS
    from monai_rigidreg.simulation.clinical import ClinicalCBCTSpec, load_planning_ct, simulate_clinical_cbct

    cts = find_cts(args.cts, out, (*TRAINING_CTS, *HELD_OUT_CTS))
    spec = ClinicalCBCTSpec()
    acquisition = current_acquisition()  # what a cached pair must have recorded to be read as it is
    physics = spec.physics
    variants = {
        "as configured": physics,
        "no exposure control": replace(physics, exposure_reference=None),
        "ideal": replace(physics, photons=None, electronic_noise=0.0, scatter_to_primary=0.0, beam_hardening=0.0),
        "photons only": replace(physics, scatter_to_primary=0.0, beam_hardening=0.0, exposure_reference=None),
        "scatter only": replace(physics, photons=None, electronic_noise=0.0, beam_hardening=0.0),
        "beam hardening only": replace(physics, photons=None, electronic_noise=0.0, scatter_to_primary=0.0),
    }
    out(f"physics as configured: {json.dumps(physics.to_dict())}")
    out()
    out(f"| CT | p_centre ({args.case}) | photons used | " + " | ".join(f"NCC {v}" for v in variants)
        + " | NCC of the cached pairs (min-max, n) |")
    out("|---|---|---|" + "---|" * len(variants) + "---|")
    for path in cts:
        ct = load_planning_ct(path)
        ct_image = sitk.Cast(ct.image, sitk.sitkFloat32)
        folder = Path(args.pairs_dir) / ct.name
        case_dir = folder / args.case
        if not (case_dir / "case.json").is_file():
            out(f"| {ct.name} | no pair {case_dir} (run bench_clinical_geometry first) |")
            continue
        case = json.loads((case_dir / "case.json").read_text())
        if case.get("deformation") is not None:
            out(f"| {ct.name} | {args.case} is a deformed pair: choose a rigid one (--case) |")
            continue
        matrix = np.asarray(case["matrix"], dtype=np.float64)
        nccs, info = [], {}
        for name, phys in variants.items():
            cbct, fov, got = simulate_clinical_cbct(ct, case["isocenter"], case["params_isocenter"], None,
                                                    replace(spec, physics=phys), 1, "cpu")
            nccs.append(truth_ncc(ct_image, cbct, fov, matrix))
            info = got if name == "as configured" else info
        cached, other = [], 0
        for pair in sorted(p for p in folder.iterdir() if (p / "case.json").is_file()):
            rec = json.loads((pair / "case.json").read_text())
            if rec.get("deformation") is not None:
                continue
            if rec.get("cbct") != acquisition:
                other += 1  # simulated with another acquisition (e.g. before the exposure control)
                continue
            cached.append(truth_ncc(ct_image, sitk.ReadImage(str(pair / "cbct.nii.gz"), sitk.sitkFloat32),
                                    sitk.ReadImage(str(pair / "cbct_fov.nii.gz")), np.asarray(rec["matrix"])))
        out(f"| {ct.name} | {info['centre_line_integral']:.2f} | {info['photons']:.3g} | "
            + " | ".join(f"{v:.3f}" for v in nccs) + " | "
            + (f"{min(cached):.3f}-{max(cached):.3f} ({len(cached)})" if cached else "none")
            + (f"; {other} of another acquisition left out" if other else "") + " |")
        print(f"{ct.name} done", file=sys.stderr, flush=True)
    out()
    end_run(out, monitor, t0, args.results, [f"pairs read from {args.pairs_dir} (seed as simulated there)"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
