"""The failure flag's signals on the clinical-geometry pairs, case by case (issue 15's false alarms).

For every pair made by ``benchmarks/accuracy/bench_clinical_geometry.py`` (``<pairs-dir>/<ct>/<group>_<nnn>/``),
registers it with the default path (the deformed pairs with their 70 mm ``--roi`` box, as the benchmark does) and prints
the error (TRE over the CT body points in the field of view; landmark error on deformed pairs), success (< 2 mm;
deformed: < rigid floor + 2 mm), the confidence and its three signals (``details.signals``: ``local_gain``, the edge
alignment gained by a small perturbation, limit ``LOCAL_GAIN_LIMIT``; ``swap_tre_mm``, the disagreement with the
swapped-input estimate, 3 mm gives 0.5; ``tissue_on_air``, the share of the CT's tissue in view that the estimate
puts on CBCT air), and which start won. A success with confidence < 0.5 is a false alarm; the signal past its limit in
each row says which test raised it.

``--spoil``: also the ``tissue_on_air`` signal at the true pose and at the true pose spoiled by each offset of
``--translations`` (mm, along a random direction) and ``--rotations`` (degrees, about one of the three coordinate
axes through the isocentre, drawn at random), seeded; computed on the network grid as the registrar does (the CT
without its couch, the CBCT resampled through the pose), one interpolation instead of the registrar's two. Its table
gives the signal's distribution for right poses (truth, and the deformed pairs) and for wrong ones.

Usage::

    python -m benchmarks.accuracy.bench_clinical_geometry --cts thorax_4dct_phase00_itkelastix head_tigre_ct \\
        --cases-per-group 5 --simulate-only --output-dir bench_out/clinical   # the pairs
    python -m benchmarks.confidence.bench_confidence_clinical --pairs-dir bench_out/clinical [--groups large deformed]
"""

from __future__ import annotations

import sys

import monai_rigidreg  # first: its thread policy applies before torch loads

# isort: split
from typing import Any

import numpy as np
import torch

from benchmarks.accuracy.bench_clinical_geometry import cached_pairs, case_errors, is_success, pairs_parser, run_method
from benchmarks.bench_common import Tee


def _spoiled_poses(case: Any, translations: list[float], rotations: list[float], rng: np.random.Generator
                   ) -> list[tuple[str, np.ndarray]]:
    """The true fixed -> moving matrix and its spoiled twins: each offset applied about the isocentre (CT frame)."""
    from monai_rigidreg.core.geometry import params_to_matrix

    iso = np.asarray(case.record["isocenter"], dtype=np.float64)
    out = [("truth", case.matrix)]
    for t in translations:
        v = rng.normal(size=3)
        out.append((f"translation {t:g} mm", case.matrix @ params_to_matrix(
            np.concatenate([t * v / np.linalg.norm(v), np.zeros(3)]), iso)))
    for r in rotations:
        d = np.zeros(6)
        d[3 + int(rng.integers(3))] = r * (1 if rng.random() < 0.5 else -1)
        out.append((f"rotation {r:g} deg", case.matrix @ params_to_matrix(d, iso)))
    return out


def _tissue_on_air_at(registrar: Any, ct: Any, cbct: Any, fov: Any, matrix: np.ndarray) -> float:
    """:func:`~monai_rigidreg.registration.confidence.tissue_on_air` of a pose on the grid and tensors the registrar
    would use from that pose as a start (``RigidRegistrar._start_tensors``: the CT without its couch, the CBCT through
    the pose), the field of view eroded as ``assess_estimate`` erodes it."""
    from monai_rigidreg.core.image_ops import erode
    from monai_rigidreg.registration.confidence import tissue_on_air

    grid, fixed_t, moved = registrar._start_tensors(ct, cbct, matrix, registrar._bodies(ct))
    fov_t = registrar._on_grid(fov, grid, "nearest", 0.0, matrix)
    fov_e = erode(fov_t[None], (2, 2, 2))[0, 0]
    return tissue_on_air(fixed_t[0], moved[0], fov_e, registrar.hu_range)


def main() -> None:
    ap = pairs_parser(__doc__, ["small", "large", "deformed"])
    ap.add_argument("--spoil", action="store_true", help="also tissue_on_air at the truth and spoiled poses")
    ap.add_argument("--translations", type=float, nargs="+", default=[5.0, 10.0, 20.0, 40.0])
    ap.add_argument("--rotations", type=float, nargs="+", default=[5.0, 10.0, 20.0, 45.0])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from monai_rigidreg.core.geometry import transform_points
    from monai_rigidreg.registration.confidence import CONFIDENCE_THRESHOLD, LOCAL_GAIN_LIMIT
    from monai_rigidreg.simulation.clinical import tre_points

    out = Tee()
    out(f"command: python {' '.join(sys.argv)}")
    out(f"monai-rigidreg {monai_rigidreg.__version__}; flag: confidence < {CONFIDENCE_THRESHOLD}; edge-gain limit "
        f"{LOCAL_GAIN_LIMIT}; swap disagreement 3 mm -> 0.5")
    registrar = monai_rigidreg.RigidRegistrar.from_bundle(device="cpu")
    out("\n| CT | pair | error (mm) | success | confidence | local_gain | swap_tre_mm | tissue_on_air | "
        "region_shift_mm (blocks) | start | verdict |")
    out("|---|---|---|---|---|---|---|---|---|---|---|")
    rng = np.random.default_rng(args.seed)
    spoiled: list[tuple[str, str, str, float, float]] = []
    counts = {"false alarm": 0, "flagged failure": 0, "missed failure": 0, "ok": 0}
    for ct_name, pair_name, ct, case in cached_pairs(args.pairs_dir, args.groups, out):
        # registered and scored as bench_clinical_geometry.py does (the deformed pairs with their ROI box)
        rec = case.record
        res = run_method("network", ct, case, registrar, roi_supported=True)
        points = tre_points(ct, case.matrix, case.fov)
        res.update(case_errors(res["params"], rec, points))
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
            f"{s['local_gain']:.4f} | {s['swap_tre_mm']:.2f} | {s.get('tissue_on_air', float('nan')):.3f} | "
            f"{s.get('region_shift_mm', float('nan')):.2f} ({s.get('region_blocks', '-')}) | "
            f"{res['details']['start']} | {verdict} |")
        if args.spoil:
            for label, matrix in _spoiled_poses(case, args.translations, args.rotations, rng):
                tre = float(np.linalg.norm(transform_points(matrix, points) - transform_points(case.matrix, points),
                                           axis=1).mean()) if len(points) else float("nan")
                spoiled.append((ct_name, pair_name, label, tre,
                                _tissue_on_air_at(registrar, ct.image, case.cbct, case.fov, matrix)))
    out("\n" + ", ".join(f"{k}: {v}" for k, v in counts.items()))
    if spoiled:
        out("\n## tissue_on_air at the true and spoiled poses (TRE of the pose over the CT body points in view)\n")
        out("| pose | n | TRE min-max (mm) | tissue_on_air min | median | max |")
        out("|---|---|---|---|---|---|")
        for label in dict.fromkeys(r[2] for r in spoiled):
            for deformed in (False, True):
                rows = [r for r in spoiled if r[2] == label and r[1].startswith("deformed") == deformed]
                if not rows:
                    continue
                v = np.array([r[4] for r in rows])
                tre = np.array([r[3] for r in rows])
                out(f"| {label}{' (deformed pairs)' if deformed else ''} | {len(rows)} | {tre.min():.1f}-"
                    f"{tre.max():.1f} | {np.nanmin(v):.3f} | {np.nanmedian(v):.3f} | {np.nanmax(v):.3f} |")
        out("\nper pose and pair (CT, pair, pose, TRE mm, tissue_on_air):")
        for r in spoiled:
            out(f"  {r[0]} {r[1]} {r[2]}: {r[3]:.1f} {r[4]:.3f}")
    out.write(args.results)


if __name__ == "__main__":
    main()
