"""Does the failure flag catch failed registrations, and how often does it flag good ones?

For every case of the given datalists the shipped network registers the pair; then the estimate is deliberately
spoiled by known offsets (a translation along a random direction, or a rotation about a random axis, of each
size in ``--translations`` / ``--rotations``; seeded) and each spoiled estimate is scored by the same confidence
check as ``register`` (:meth:`RigidRegistrar.assess`: edge-alignment gain and swapped-input agreement). A result is
a failure when its mean TRE over the fixed image's body points is at least 2 mm (the report's success rule).

Printed: per offset, how many results fail and how many of those are flagged; over everything, failures caught
(recall) and successes flagged (false alarms), with the network's own (unspoiled) results counted as they come.

Usage::

    python -m benchmarks.confidence.bench_confidence --datalist data/val_paper/dataset.json \\
        bench_out/shepp_logan_paper/subset.json bench_out/thorax_paper/subset.json
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk
import torch

from benchmarks.bench_common import script_parser
from monai_rigidreg.core.geometry import recenter_params, target_registration_error
from monai_rigidreg.evaluation.evaluate import iter_cases, load_datalist
from monai_rigidreg.evaluation.report import SUCCESS_TRE_MM
from monai_rigidreg.registration.confidence import CONFIDENCE_THRESHOLD, cylindrical_fov_mask
from monai_rigidreg.registration.registrar import RigidRegistrar


def _offsets(translations: list[float], rotations: list[float], rng: np.random.Generator
             ) -> list[tuple[str, np.ndarray]]:
    out = []
    for t in translations:
        v = rng.normal(size=3)
        out.append((f"translation {t:g} mm", np.concatenate([t * v / np.linalg.norm(v), np.zeros(3)])))
    for r in rotations:
        d = np.zeros(6)
        d[3 + int(rng.integers(3))] = r * (1 if rng.random() < 0.5 else -1)
        out.append((f"rotation {r:g} deg", d))
    return out


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--datalist", type=Path, nargs="+", default=[Path("data/val_paper/dataset.json")])
    ap.add_argument("--translations", type=float, nargs="+", default=[2.0, 5.0, 10.0, 20.0])
    ap.add_argument("--rotations", type=float, nargs="+", default=[2.0, 5.0, 10.0, 15.0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--bundle", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(args.threads)
    rng = np.random.default_rng(args.seed)
    reg = RigidRegistrar.from_bundle(args.bundle, device="cpu")

    rows: list[tuple[str, bool, bool, float]] = []  # (kind, failed, flagged, confidence)
    for dl in args.datalist:
        items, _ = load_datalist(dl)
        for case in iter_cases(items):
            fixed, moving, center = case.fixed, case.moving, case.center
            fov_img = cylindrical_fov_mask(moving) if case.fov is None else case.fov
            grid = reg.network_grid(fixed, moving)
            f_t, m_t = reg.preprocess(fixed, grid), reg.preprocess(moving, grid)
            fov_t = reg._on_grid(fov_img, grid, "nearest", 0.0)[0]
            est = reg.estimate(m_t, f_t, grid)
            for kind, offset in [("network estimate", np.zeros(6)), *_offsets(args.translations, args.rotations, rng)]:
                p = est + offset
                conf = reg.assess(m_t, f_t, grid, p, fov_t)["confidence"]
                tre = float(target_registration_error(recenter_params(p, grid.center(), center), case.truth,
                                                      case.points, center=center))
                rows.append((kind, tre >= SUCCESS_TRE_MM, conf < CONFIDENCE_THRESHOLD, conf))
        print(f"{dl}: {len(items)} cases", flush=True)

    print(f"\nFailure flag (confidence < {CONFIDENCE_THRESHOLD}); failure: mean TRE >= {SUCCESS_TRE_MM:g} mm\n")
    print("| estimate | results | failures | flagged failures | successes | flagged successes |")
    print("|---|---|---|---|---|---|")
    for kind in dict.fromkeys(r[0] for r in rows):
        sel = [r for r in rows if r[0] == kind]
        fails = [r for r in sel if r[1]]
        oks = [r for r in sel if not r[1]]
        print(f"| {kind} | {len(sel)} | {len(fails)} | {sum(r[2] for r in fails)} | {len(oks)} | "
              f"{sum(r[2] for r in oks)} |")
    fails = [r for r in rows if r[1]]
    oks = [r for r in rows if not r[1]]
    print(f"\nall: failures caught {sum(r[2] for r in fails)} / {len(fails)}, "
          f"successes flagged {sum(r[2] for r in oks)} / {len(oks)}")


if __name__ == "__main__":
    main()
