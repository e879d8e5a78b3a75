"""Where each start of the default path leads on one clinical-geometry pair (issue 15: choosing between starts).

For a pair made by ``benchmarks/accuracy/bench_clinical_geometry.py`` (``<pairs-dir>/<ct>/<group>_<nnn>/``), prints:

1. the global search's candidates (rotation, coarse score) in their rank order, with each candidate's own landmark
   error (deformed pairs) or TRE at the landmarks' true rigid positions;
2. the network run from the identity and from each of the ``--starts`` best candidates, twice: over the whole field
   of view (the body weight only; how 0.4.4 finds the pose) and with the pair's 70 mm ROI box in the match weight (how
   0.4.3 found it on deformed pairs); for each run the field-of-view image match the registrar chooses with
   (``RigidRegistrar._image_match``: NCC over the CBCT's field of view, and inside the ROI; as in the registrar, the
   ROI column falls back to the whole field of view for all runs of a variant where the ROI leaves no voxel for one
   of them) and the landmark error of the estimate (before the last level).

It explains which start the registrar picks and why; it does not run the last level or the confidence check (the
benchmark's per-case lines give the final errors).

Usage::

    python -m benchmarks.accuracy.bench_starts bench_out/clinical_seed2500/head_tigre_ct/deformed_003 [--starts 4]
"""

from __future__ import annotations

import argparse
import sys

import monai_rigidreg  # first: its thread policy applies before torch loads

# isort: split
from pathlib import Path

import numpy as np
import SimpleITK as sitk
import torch


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pair", type=Path, help="a pair folder of bench_clinical_geometry.py (with case.json)")
    ap.add_argument("--starts", type=int, default=4, help="search candidates to start the network from (default 4)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from monai_rigidreg.core.geometry import params_to_matrix, transform_points
    from monai_rigidreg.registration.match_region import match_weight
    from monai_rigidreg.registration.search import global_search
    from monai_rigidreg.simulation.clinical import load_clinical_case

    case = load_clinical_case(args.pair)
    if case is None:
        print(f"no finished pair in {args.pair}")
        return 2
    rec = case.record
    ct = sitk.Cast(sitk.ReadImage(rec["fixed"]), sitk.sitkFloat32)
    reg = monai_rigidreg.RigidRegistrar.from_bundle(device="cpu")
    lm = np.asarray(rec["landmarks"], dtype=np.float64).reshape(-1, 3)
    lm_true = np.asarray(rec["landmarks_moving"], dtype=np.float64).reshape(-1, 3)

    def lm_err(matrix: np.ndarray) -> float:
        return float(np.linalg.norm(transform_points(matrix, lm) - lm_true, axis=1).mean())

    roi = rec.get("roi")
    box_w = None
    if roi is not None:
        c, size = np.asarray(roi["center"]), np.asarray(roi["size_mm"])
        box_w = match_weight(ct, tuple(c - size / 2) + tuple(c + size / 2), "soft")
    truth = params_to_matrix(rec["params"], rec["center"])
    print(f"pair {args.pair} ({rec['group']}): isocentre {rec['isocenter_distance_mm']:.0f} mm from the CT centre, "
          f"motion about it {np.round(rec['params_isocenter'], 1).tolist()}; landmarks {len(lm)}, rigid floor "
          f"{rec.get('rigid_floor_mm', float('nan')):.2f} mm; the true rigid motion's landmark error "
          f"{lm_err(truth):.2f} mm")
    body = reg._bodies(ct)
    cands = global_search(ct, case.cbct, case.fov, hu_range=reg.hu_range, fixed_body=body, **reg.search_settings)
    print("\nsearch candidates, best score first (landmark error of the candidate itself):")
    for i, cand in enumerate(cands):
        print(f"  {i:2d} rotation {cand.rotation_deg} score {cand.score:.3f} landmark error {lm_err(cand.matrix):6.1f}")
    timings: dict[str, float] = {}
    starts = [("identity", np.eye(4))] + [(f"candidate {i}", c.matrix) for i, c in enumerate(cands[: args.starts])]
    variants = [("whole view", [body])] + ([("ROI-weighted", [box_w, body])] if box_w is not None else [])
    print("\nnetwork runs (before the last level): field-of-view NCC, NCC inside the ROI, landmark error (mm)")
    for label, weights in variants:
        runs = [reg._run_from(ct, case.cbct, m, None, weights, timings, body) for _, m in starts]
        totals = [r.total for r in runs]
        fov_ncc = reg._image_match(ct, case.cbct, case.fov, totals, None)
        roi_ncc = [np.nan] * len(runs)
        if box_w is not None:
            roi_ncc = reg._image_match(ct, case.cbct, case.fov, totals, box_w)
        for (name, _), r, a, b in zip(starts, runs, fov_ncc, roi_ncc):
            print(f"  {label:12s} from {name:12s}: NCC {a:.4f}, ROI NCC {b:.4f}, landmark error {lm_err(r.total):6.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
