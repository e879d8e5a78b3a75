"""ANTs' rigid registration on ``bench_speed``'s clinical-size pairs with and without the CBCT's field-of-view mask,
with the ``DenseRigid`` preset, and started from ANTsPy's own default (the centres of intensity mass aligned) instead
of the identity: is a failure of the peer a capture-range limit or a misuse of it?

    python -m benchmarks.accuracy.bench_ants_settings --cases case_0 case_1 case_2 case_3 --threads 2

Each row: the TRE (mm, at the pair's CT body points) of :func:`~monai_rigidreg.registration.peers.register_ants`
with one setting (preset, mask, start), and its seconds. Needs ``bench_speed``'s pairs in ``--pairs-dir`` and the
``bench`` extra (antspyx).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_common import Tee, end_run, script_parser, start_run

SETTINGS = (("Rigid", True, "identity"), ("Rigid", False, "identity"), ("DenseRigid", True, "identity"),
            ("Rigid", True, "mass"), ("Rigid", False, "mass"))
"""(preset, the CBCT's field of view as ANTs' moving mask, start: ``peers.ANTS_STARTS``)"""


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--pairs-dir", type=Path, default=Path("bench_out/speed"))
    ap.add_argument("--cases", nargs="+", default=["case_0", "case_1"])
    ap.add_argument("--ct", type=Path, default=Path("../shared/data/thorax_4dct_phase00_itkelastix.nii.gz"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--results", type=Path, default=None)
    args = ap.parse_args()
    os.environ["ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"] = str(args.threads)  # read by ANTs on its first call
    out = Tee()
    monitor, t0 = start_run(out, __spec__.name if __spec__ else "bench_ants_settings", args.threads, "cpu", "ANTs")
    import SimpleITK as sitk

    from benchmarks.speed.bench_speed import load_case, tre_mm
    from monai_rigidreg.registration.peers import register_ants

    ct = sitk.ReadImage(str(args.ct), sitk.sitkFloat32)
    out("| case | truth (tx ty tz mm, rx ry rz deg, about the isocentre) | identity TRE | preset | mask | start | "
        "TRE (mm) | s |")
    out("|---|---|---|---|---|---|---|---|")
    for case in args.cases:
        record, cbct, points = load_case(args.pairs_dir / case)
        fov = sitk.ReadImage(str(args.pairs_dir / case / "cbct_fov.nii.gz"))
        truth = " ".join(f"{v:+.1f}" for v in record.get("params_isocenter", []))
        ident = tre_mm(np.zeros(6), np.zeros(3), record, points)
        for preset, masked, start in SETTINGS:
            t = time.perf_counter()
            res = register_ants(ct, cbct, moving_mask=fov if masked else None, type_of_transform=preset, start=start)
            out(f"| {case} | {truth} | {ident:.1f} | {preset} | {'CBCT field of view' if masked else 'none'} | "
                f"{'centres of mass' if start == 'mass' else start} | "
                f"{tre_mm(res.params, res.center, record, points):.2f} | {time.perf_counter() - t:.1f} |")
    out()
    end_run(out, monitor, t0, args.results, [])


if __name__ == "__main__":
    main()
