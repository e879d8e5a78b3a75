"""Does the last level settle? Its passes run again and again from the truth and from a start a little off.

The default path's last level (:func:`monai_rigidreg.registration.last_level.refine_native`) runs pass after pass,
each from the previous one's result, until a pass moves the estimate by at most
:data:`~monai_rigidreg.registration.last_level.NATIVE_CONVERGED_MM`. Where the images fix the pose, a pass from the
truth moves it by hundredths of a millimetre and later passes stay put; where they do not, passes keep moving it and
the registration's end depends on small perturbations (float rounding of sampling points moved the serve tests'
phantom pair's end from 0.17 to 0.57 mm). This script measures it: for each pair, ``--passes`` passes of the last level
with the shipped bundle's settings (the whole CBCT field of view, no match region) from the truth and from the truth
composed with a small motion (``--offset``), and the default path's registration of the pair; each for the pair as
simulated (cone-beam CBCT) and for a clean twin whose CBCT is the CT itself resampled through the truth onto the
CBCT's grid (no CBCT physics: what is left is the object and the interpolation).

Pairs: the serve tests' phantom pair (the asymmetric Shepp-Logan phantom, a 96^3 Sim-CT at 2 mm, a 64^3 CBCT at 2 mm
from 60 views, ``tests/serve/test_serve.py``'s motion) and the same simulation of each real CT given (``--cts``;
default: the 0.4.x held-out pair). TRE: the mean distance over the CT's body points (voxels above -400 HU) between
the estimate's and the truth's images of them; a pass's move likewise between its start and its result.

Usage::

    python -m benchmarks.accuracy.bench_last_level_settling \\
        --results benchmarks/results/0.6.3.dev/bench_last_level_settling_2026-12-07.txt
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_common import end_run, find_cts, script_parser, start_cpu_run

MOTION = (5.0, -3.0, 4.0, 3.0, -2.0, 4.0)
"""The serve tests' motion (mm, degrees; CT points -> CBCT points about the CT centre)."""
PAIR_SETTINGS = {"simct_size": 96, "simct_spacing": 2.0, "cbct_size": 64, "cbct_spacing": 2.0, "simct_views": 60,
                 "cbct_views": 60}
"""The serve tests' simulation settings (``tests/serve/test_serve.py``'s ``pair``), for every object here."""
DEFAULT_CTS = ("head_tigre_ct", "thorax_4dct_phase00_itkelastix")


def clean_twin(fixed: Any, moving: Any, truth: np.ndarray) -> Any:
    """The CT resampled through ``truth`` (fixed -> moving, 4x4, LPS mm) onto ``moving``'s grid (linear, -1000 HU
    outside): a CBCT with the CT's own appearance."""
    import SimpleITK as sitk

    from monai_rigidreg.core.geometry import invert_matrix, matrix_to_sitk

    # resampling maps each CBCT voxel's point to the CT point it shows: the inverse of the truth
    return sitk.Resample(sitk.Cast(fixed, sitk.sitkFloat32), moving, matrix_to_sitk(invert_matrix(truth)),
                         sitk.sitkLinear, -1000.0, sitk.sitkFloat32)


def run_passes(registrar: Any, fixed: Any, moving: Any, fov: Any, start: np.ndarray, truth: np.ndarray,
               points: np.ndarray, passes: int) -> list[dict[str, float]]:
    """``passes`` passes of the last level (one pass each of the registrar's own ``_native``, no match region),
    each from the last one's result: per pass the move, the TRE after it and the pass's own ``expected_tre_mm``."""
    from monai_rigidreg.core.geometry import Grid
    from monai_rigidreg.registration.search import matrix_distance_mm

    grid = Grid.from_sitk(moving)  # only where _native measures its own move; the moves here are over ``points``
    rows, matrix = [], start
    for _ in range(passes):
        new, detail = registrar._native(fixed, moving, matrix, fov, [], grid, converge=False)
        rows.append({"move": matrix_distance_mm(new, matrix, points), "tre": matrix_distance_mm(new, truth, points),
                     "expected": float(detail.get("expected_tre_mm", float("nan")))})
        matrix = new
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = script_parser(__doc__)
    ap.add_argument("--cts", nargs="*", default=None, help=f"real CTs (paths or names; default: {DEFAULT_CTS})")
    ap.add_argument("--passes", type=int, default=8)
    ap.add_argument("--offset", nargs=6, type=float, default=[2.0, -2.0, 2.0, 1.0, -1.0, 1.0],
                    help="the second start: the truth composed with this motion (mm, degrees, about the CT centre)")
    ap.add_argument("--seed", type=int, default=3)
    args, out, monitor, t0 = start_cpu_run(ap, argv, __spec__.name if __spec__ else "bench_last_level_settling",
                                           "the shipped bundle")
    import SimpleITK as sitk

    import monai_rigidreg
    from monai_rigidreg.core.geometry import params_to_matrix
    from monai_rigidreg.evaluation.evaluate import body_points
    from monai_rigidreg.registration.search import matrix_distance_mm
    from monai_rigidreg.simulation import simulate_pair

    registrar = monai_rigidreg.RigidRegistrar.from_bundle(device="cpu")
    objects: list[tuple[str, str]] = [("shepp-logan-asym phantom", "shepp-logan-asym")]
    objects += [(p.name.split(".")[0], str(p)) for p in find_cts(args.cts, out, DEFAULT_CTS)]
    out(f"motion {MOTION}; simulation {PAIR_SETTINGS}, seed {args.seed}; {args.passes} passes per start; the second "
        f"start: the truth composed with {tuple(args.offset)}")
    summary = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, source in objects:
            pair = simulate_pair(Path(tmp) / f"pair_{len(summary)}", phantom=source, params=MOTION, seed=args.seed,
                                 device="cpu", **PAIR_SETTINGS)
            fixed = sitk.ReadImage(pair["fixed"], sitk.sitkFloat32)
            cbct = sitk.ReadImage(pair["moving"], sitk.sitkFloat32)
            fov = sitk.ReadImage(pair["moving_fov"])
            truth = np.asarray(pair["matrix"], dtype=np.float64)
            center = np.asarray(pair["center"], dtype=np.float64)
            points = body_points(fixed)
            off = truth @ params_to_matrix(args.offset, center)
            for variant, moving in (("cone-beam CBCT", cbct), ("clean twin", clean_twin(fixed, cbct, truth))):
                result = monai_rigidreg.register(fixed, moving, model=registrar, moving_fov=fov,
                                                 resample_moving=False)
                level = result.details.get("native_level", {})
                reg_tre = matrix_distance_mm(np.asarray(result.matrix), truth, points)
                out()
                out(f"## {name}, {variant}")
                out(f"default path: TRE {reg_tre:.3f} mm, last level {level.get('passes')} passes, the last moved "
                    f"{level.get('last_pass_mm')} mm, expected_tre_mm {level.get('expected_tre_mm')}")
                out("| start | " + " | ".join(f"pass {i + 1}" for i in range(args.passes)) + " |")
                out("|---|" + "---|" * args.passes)
                for start_name, start in (("truth", truth), ("offset", off)):
                    rows = run_passes(registrar, fixed, moving, fov, start, truth, points, args.passes)
                    out(f"| {start_name}: move / TRE mm | "
                        + " | ".join(f"{r['move']:.3f} / {r['tre']:.3f}" for r in rows) + " |")
                    later = rows[2:] or rows
                    summary.append((name, variant, start_name, max(r["move"] for r in later),
                                    min(r["tre"] for r in later), max(r["tre"] for r in later),
                                    rows[-1]["expected"], reg_tre))
    out()
    out("## Summary (passes 3 onwards)")
    out("| object | CBCT | start | largest move (mm) | TRE min - max (mm) | expected_tre_mm (last pass) | "
        "default path TRE (mm) |")
    out("|---|---|---|---|---|---|---|")
    for name, variant, start_name, move, lo, hi, expected, reg_tre in summary:
        out(f"| {name} | {variant} | {start_name} | {move:.3f} | {lo:.3f} - {hi:.3f} | {expected:.3f} | "
            f"{reg_tre:.3f} |")
    out()
    end_run(out, monitor, t0, args.results, [
        "the last level's passes with the shipped bundle's settings over the whole CBCT field of view (no match "
        "region, no body weight), each from the previous pass's result; the default path with its own weights"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
