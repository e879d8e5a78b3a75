"""Does the image-based polish move the estimate off the truth on a CT? The residual (estimate against the truth) per
parameter on a CT's paper-protocol pairs, for the default path, the learned network alone and two variants of the
last level: its mean over the pairs is a bias, its standard deviation the scatter.

Rows: ``default``; ``alone`` (``fine_stage=False``); ``no-last-level`` (the network and its Gauss-Newton stage only,
``native_level=False``); ``bias-2`` (the last level estimating an intensity bias of degree 2 with the pose);
``gain-norm`` (both Gauss-Newton stages aligning the local contrast normalised by its strength over 12 mm,
``contrast_norm_sigma_mm``) and ``gain-norm, no intensity`` (the same without the intensity channel). ``--variants``
picks rows.

    python -m benchmarks.accuracy.bench_polish_bias --real-ct-dir bench_out/real_ct --ct abdomen_pelvis_tcia_tcga_ov_ct
"""

from __future__ import annotations

from pathlib import Path

from benchmarks.bench_common import end_run, pose_error, script_parser, start_registrar_run

VARIANTS = {"default": {}, "alone": {}, "no-last-level": {"native_level": False}, "bias-2": {"native_bias_degree": 2},
            "gain-norm": {"stage.contrast_norm_sigma_mm": 12.0},
            "gain-norm, no intensity": {"stage.contrast_norm_sigma_mm": 12.0, "stage.intensity_weight": 0.0}}
STAGE_KEYS = ("contrast_norm_sigma_mm", "intensity_weight")


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--real-ct-dir", type=Path, default=Path("bench_out/real_ct"),
                    help="bench_real_ct's --output-dir (<dir>/<ct>/dataset.json)")
    ap.add_argument("--ct", nargs="+", required=True)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS), metavar="ROW",
                    help=f"rows (default all: {', '.join(VARIANTS)})")
    args, out, monitor, t0, registrar = start_registrar_run(ap, __spec__.name if __spec__ else "bench_polish_bias")
    import numpy as np

    import monai_rigidreg
    from monai_rigidreg.evaluation.evaluate import iter_cases, load_datalist

    stage = registrar.network.fine_stage
    base = {k: getattr(registrar, k) for k in ("native_level", "native_bias_degree")}
    base.update({f"stage.{k}": getattr(stage, k) for k in STAGE_KEYS})

    def apply(settings: dict) -> None:
        for k, v in settings.items():
            if k.startswith("stage."):
                setattr(stage, k.removeprefix("stage."), v)
            else:
                setattr(registrar, k, v)

    out("| CT | variant | n | mean TRE (mm) | mean residual tx ty tz (mm), rx ry rz (deg) | sd of the residual |")
    out("|---|---|---|---|---|---|")
    for ct in args.ct:
        cases = list(iter_cases(load_datalist(args.real_ct_dir / ct / "dataset.json")[0]))
        for name in args.variants:
            apply({**base, **VARIANTS[name]})
            residuals, tres = [], []
            for case in cases:
                res = monai_rigidreg.register(case.fixed, case.moving, model=registrar, moving_fov=case.fov,
                                              resample_moving=False, fine_stage=name != "alone")
                residual, tre = pose_error(case.truth, case.center, res.params, res.center, case.points)
                residuals.append(residual)
                tres.append(tre)
            r = np.asarray(residuals)
            out(f"| {ct} | {name} | {len(r)} | {np.mean(tres):.2f} | {' '.join(f'{v:+.2f}' for v in r.mean(0))} | "
                f"{' '.join(f'{v:.2f}' for v in r.std(0))} |")
        apply(base)
    end_run(out, monitor, t0, args.results, [])


if __name__ == "__main__":
    main()
