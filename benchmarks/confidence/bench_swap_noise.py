"""The ``noise`` test of swapped inputs, measured: each image's soft-tissue noise and which swap reasons fire.

For every case of the confidence calibration's sets that can be regenerated from the simulated pairs on this machine
(:mod:`benchmarks.confidence.calibration_sets`: paper protocol, partial overlap, damaged, swapped, negative and
clinical-geometry pairs), prints the noise of the fixed and the moving image
(:func:`~monai_rigidreg.registration.inputs.image_noise_hu`, as at 2 mm voxels), their ratio on the pairs in the
usual order and on the swapped ones, and the reasons :func:`~monai_rigidreg.registration.inputs.swapped_reasons`
gives per set: ``SWAPPED_NOISE_RATIO`` (1.5) must sit between the usual pairs' ratios and the swapped ones', and the
``noise`` reason fire on swapped pairs only. Nothing is registered.

    python -m benchmarks.confidence.bench_swap_noise --real-ct-dir bench_out/real_ct --pairs-dirs bench_out/clinical
"""

from __future__ import annotations

import collections
from pathlib import Path

from benchmarks.bench_common import Tee, end_run, script_parser, start_run


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--real-ct-dir", type=Path, default=Path("bench_out/real_ct"))
    ap.add_argument("--paper-cts", nargs="+", default=["thorax_4dct_phase00_itkelastix", "head_tigre_ct"])
    ap.add_argument("--pairs-dirs", type=Path, nargs="+", default=[Path("bench_out/clinical")])
    ap.add_argument("--results", type=Path, default=None)
    args = ap.parse_args()
    out = Tee()
    monitor, t0 = start_run(out, __spec__.name if __spec__ else "bench_swap_noise", 1, "cpu", "none (no network)")
    import SimpleITK as sitk

    from benchmarks.confidence import calibration_sets as sets
    from monai_rigidreg.registration.inputs import SWAPPED_NOISE_RATIO, image_noise_hu, swapped_reasons

    generators = [sets.paper_cases(args.real_ct_dir, args.paper_cts), sets.clinical_cases(args.pairs_dirs, None),
                  sets.negative_cases(args.real_ct_dir, args.pairs_dirs[0])]
    reasons: collections.Counter = collections.Counter()
    ratios: dict[str, list[float]] = {"usual": [], "swapped": []}
    out("| case | set | fixed noise (HU) | moving noise (HU) | fixed / moving | swap reasons |")
    out("|---|---|---|---|---|---|")
    for gen in generators:
        for case in gen:
            fixed, moving = sitk.Cast(case.fixed, sitk.sitkFloat32), sitk.Cast(case.moving, sitk.sitkFloat32)
            why = swapped_reasons(fixed, moving)
            reasons[(case.set, tuple(why))] += 1
            if case.set in ("paper", "clinical", "swapped"):
                nf, nm = image_noise_hu(fixed), image_noise_hu(moving)
                ratios["swapped" if case.set == "swapped" else "usual"].append(nf / nm)
                out(f"| {case.key} | {case.set} | {nf:.1f} | {nm:.1f} | {nf / nm:.2f} | {', '.join(why) or '-'} |")
    out("\n| set | swap reasons | cases |\n|---|---|---|")
    for (name, why), n in sorted(reasons.items()):
        out(f"| {name} | {', '.join(why) or '-'} | {n} |")
    for kind, values in ratios.items():
        if values:
            out(f"\nfixed / moving noise, {kind} order: {min(values):.2f}-{max(values):.2f} over {len(values)} pairs "
                f"(SWAPPED_NOISE_RATIO {SWAPPED_NOISE_RATIO:g})")
    end_run(out, monitor, t0, args.results, [])


if __name__ == "__main__":
    main()
