"""The package's CBCTs against RTK's: the same cases of a real CT reconstructed by the package's simulator and by RTK
(``itk-rtk``: Joseph's forward projector and FDK, CPU), compared as images and registered by the same methods.

For each CT, the paper-protocol pairs of ``bench_real_ct.py`` (simulated first where ``<real-ct-dir>/<ct>`` holds
none, with its settings: Sim-CT 128^3 at 2 mm, CBCT 64^3 at 2 mm, 180 views, SOD 800 mm, SDD 1200 mm) give the
object, the motion, the geometry and the Sim-CT. ``benchmarks/simulation/rtk_cbct.py`` makes the RTK CBCT of each
case: the same moved object and detector, RTK's projector and reconstruction, and (default) the package's noise,
scatter and beam hardening on RTK's line integrals; with ``--ideal`` both CBCTs are made without them (the package's
then in this run), which separates what the projector and the reconstruction do from what the physics does.
RTK's CBCTs are written to ``<real-ct-dir>/<ct>_rtk`` (``_rtk_ideal``), resumed where present.

Printed per CT: the agreement of the two CBCTs in the field of view (NCC; the mean HU difference; the shift of RTK's
against the package's, the least-squares fit of their difference to the package's gradient, mm), then for each
CBCT source and method: mean TRE, success (< 2 mm), the per-axis mean absolute error and the per-axis mean signed
error (estimate less truth: a bias that the absolute error hides).

    python -m benchmarks.accuracy.bench_rtk_crosscheck --ct thorax_4dct_phase00_itkelastix head_tigre_ct \\
        --num-cases 12 --methods network-regression network elastix --results FILE
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from pathlib import Path

import numpy as np

from benchmarks.accuracy.bench_real_ct import DEFAULT_CTS, data_name, simulate_command
from benchmarks.bench_common import end_run, find_cts, script_parser, set_threads, start_run


def _config(data_dir: Path):
    from monai_rigidreg.simulation.config import SimulationConfig

    return SimulationConfig(**json.loads((data_dir / "simulation.json").read_text())["config"])


def make_rtk_set(data_dir: Path, num_cases: int, ideal: bool) -> tuple[Path, Path, list[str]]:
    """RTK's CBCTs of the first ``num_cases`` cases of ``data_dir`` (and, with ``ideal``, the package's without
    physics), each with a datalist. Returns ``(package datalist, RTK datalist, notes)``."""
    import torch

    from benchmarks.simulation.rtk_cbct import rtk_cbct
    from monai_rigidreg.simulation.physics import CBCTPhysics
    from monai_rigidreg.simulation.volumes import (
        _detector_radius,
        _object_volume,
        fitted_cone_geometry,
        frame_offset,
        save_fov_mask,
        save_volume_hu,
        simulate_cbct,
        stream_seed,
    )

    cfg = _config(data_dir)
    if np.any(frame_offset(cfg)):
        raise SystemExit(f"{data_dir}: the pairs must be centred on the origin (ct_frame=False), as bench_real_ct's")
    items = json.loads((data_dir / "dataset.json").read_text())["training"][:num_cases]
    suffix = "_ideal" if ideal else ""
    sets = {"rtk": data_dir.with_name(data_dir.name + "_rtk" + suffix)}
    if ideal:
        sets["package"] = data_dir.with_name(data_dir.name + "_ideal")
    physics = cfg.cbct_physics
    made = {name: 0 for name in sets}
    seconds = {name: 0.0 for name in sets}
    obj = None
    for it in items:
        for name, d in sets.items():
            target = d / it["moving"]
            if target.is_file():
                continue
            if obj is None:  # the object and its detector, once (only where a CBCT is missing)
                grid = cfg.object_grid()
                mu = _object_volume(cfg, 0, grid, torch.device("cpu"))
                radius = _detector_radius(cfg, grid, mu)
                obj = (grid, mu, radius,
                       fitted_cone_geometry(grid, cfg.cbct_grid, radius, cfg.cbct_views, cfg.sod, cfg.sdd))
            grid, mu, radius, geom = obj
            seed = stream_seed(cfg.seed, 1, int(it["case_id"][4:]))
            t = time.perf_counter()
            if name == "rtk":
                rec, fov = rtk_cbct(mu, grid, cfg.cbct_grid, it["params"], geom, physics, degrade=not ideal, seed=seed)
            else:
                rec_t, fov_t, _ = simulate_cbct(mu, grid, cfg.cbct_grid, it["params"], (0.0, 0.0, 0.0), cfg.cbct_views,
                                                cfg.sod, cfg.sdd, CBCTPhysics.ideal(), cfg.cbct_filter, seed=seed,
                                                detector_radius_mm=radius, padding_mode="border", device="cpu")
                rec, fov = rec_t.numpy(), fov_t.numpy()
            seconds[name] += time.perf_counter() - t
            made[name] += 1
            save_fov_mask(torch.from_numpy(fov), cfg.cbct_grid, d / it["moving_fov"])
            save_volume_hu(torch.from_numpy(rec), cfg.cbct_grid, target, cfg.volume_dtype)
    notes = [f"{name}: {made[name]} CBCT(s) made in {seconds[name]:.0f} s, {len(items) - made[name]} reused "
             f"({sets[name]})" for name in sets]
    lists = {}
    for name, d in {"package": data_dir, **sets}.items():
        entries = [{**it, "fixed": str((data_dir / it["fixed"]).resolve()), "moving": str((d / it["moving"]).resolve()),
                    "moving_fov": str((d / it["moving_fov"]).resolve())} for it in items]
        path = d / f"crosscheck_{len(items)}.json" if d != data_dir else d / f"crosscheck_package_{len(items)}.json"
        path.write_text(json.dumps({"training": entries}, indent=1))
        lists[name] = path
    return lists["package"], lists["rtk"], notes


def image_agreement(package: Path, rtk: Path, num_cases: int) -> tuple[float, float, float, np.ndarray]:
    """Mean over the cases of the NCC (as they are, and both smoothed by a Gaussian of 4 mm, which leaves the
    anatomy and removes most of the two independent noise realisations) and the mean difference (RTK less package,
    HU) in both fields of view, and
    the mean shift (mm, x y z) of RTK's CBCT against the package's (``rtk(p) ~ package(p - shift)``, the
    least-squares fit of the difference to the package's gradient)."""
    import SimpleITK as sitk

    a_items = json.loads(package.read_text())["training"][:num_cases]
    b_items = json.loads(rtk.read_text())["training"][:num_cases]
    nccs, smooth_nccs, diffs, shifts = [], [], [], []
    for ia, ib in zip(a_items, b_items):
        img_a = sitk.ReadImage(ia["moving"], sitk.sitkFloat32)
        a = sitk.GetArrayFromImage(img_a)
        b = sitk.GetArrayFromImage(sitk.ReadImage(ib["moving"], sitk.sitkFloat32))
        m = (sitk.GetArrayFromImage(sitk.ReadImage(ia["moving_fov"])) > 0) & (
            sitk.GetArrayFromImage(sitk.ReadImage(ib["moving_fov"])) > 0)
        nccs.append(float(np.corrcoef(a[m], b[m])[0, 1]))
        smooth = [sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(sitk.GetImageFromArray(v), 2.0))
                  for v in (a, b)]  # 2 voxels of 2 mm
        smooth_nccs.append(float(np.corrcoef(smooth[0][m], smooth[1][m])[0, 1]))
        diffs.append(float((b[m] - a[m]).mean()))
        grads = np.gradient(a, *img_a.GetSpacing()[::-1])  # d/dz, d/dy, d/dx (array order)
        design = np.stack([g[m] for g in grads[::-1]], 1)  # x y z
        r = (b - a)[m]
        coef = np.linalg.lstsq(np.c_[design, np.ones(len(r))], r, rcond=None)[0]
        shifts.append(-coef[:3])
    return float(np.mean(nccs)), float(np.mean(smooth_nccs)), float(np.mean(diffs)), np.mean(shifts, 0)


def main() -> int:
    ap = script_parser(__doc__)
    ap.add_argument("--ct", nargs="+", default=None, help=f"CTs (default {' '.join(DEFAULT_CTS)})")
    ap.add_argument("--real-ct-dir", type=Path, default=Path("bench_out/real_ct"),
                    help="bench_real_ct's --output-dir (default bench_out/real_ct)")
    ap.add_argument("--num-cases", type=int, default=12, help="paper-protocol cases per CT (default 12)")
    ap.add_argument("--seed", type=int, default=6000, help="simulation seed of missing pairs (default 6000)")
    ap.add_argument("--ideal", action="store_true", help="both CBCTs without noise, scatter and beam hardening")
    ap.add_argument("--methods", nargs="+", default=["network-regression", "network", "elastix"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--results", type=Path, default=None, help="also write the printed text to FILE")
    args = ap.parse_args()
    set_threads(args.threads)
    from benchmarks.bench_common import Tee
    from benchmarks.simulation.rtk_cbct import rtk_available, rtk_version

    out = Tee()
    if not rtk_available():
        out("itk-rtk is not installed (pip install 'monai-rigidreg[bench]'): nothing to compare")
        return 2
    from monai_rigidreg.evaluation import evaluate_datalist
    from monai_rigidreg.registration.registrar import RigidRegistrar

    monitor, t0 = start_run(out, __spec__.name if __spec__ else "bench_rtk_crosscheck", args.threads, "cpu",
                            "the shipped bundle")
    out(f"itk-rtk {rtk_version()}; {args.num_cases} paper-protocol cases per CT; CBCT physics: "
        + ("none in either (--ideal)" if args.ideal else "the package's, on each projector's line integrals"))
    out()
    registrar = RigidRegistrar.from_bundle(device="cpu")
    notes: list[str] = []
    for ct in find_cts(args.ct, out, DEFAULT_CTS):
        data_dir = args.real_ct_dir / data_name(ct)
        if not (data_dir / "dataset.json").is_file():
            subprocess.run(simulate_command(ct, data_dir, max(args.num_cases, 12), args.seed), check=True,
                           env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"})
        package, rtk, made = make_rtk_set(data_dir, args.num_cases, args.ideal)
        notes += [f"{data_name(ct)}: {m}" for m in made]
        ncc, smooth_ncc, diff, shift = image_agreement(package, rtk, args.num_cases)
        out(f"## {data_name(ct)}")
        out()
        out(f"the two CBCTs in the field of view: NCC {ncc:.3f} ({smooth_ncc:.3f} both smoothed by 4 mm), mean "
            f"difference (RTK less package) {diff:+.1f} HU, "
            f"shift of RTK's against the package's x {shift[0]:+.3f} y {shift[1]:+.3f} z {shift[2]:+.3f} mm")
        out()
        out("| CBCT | method | n | mean TRE (mm) | success (<2 mm) | mean abs error tx ty tz (mm), rx ry rz (deg) "
            "| mean signed error tx ty tz, rx ry rz |")
        out("|---|---|---|---|---|---|---|")
        for source, dl in (("package" + (" (ideal)" if args.ideal else ""), package),
                           ("RTK" + (" (ideal)" if args.ideal else ""), rtk)):
            result = evaluate_datalist(dl, args.methods, registrar=registrar, progress=False, html=False)
            for method in args.methods:
                rows = [c for c in result["cases"] if c.method == method]
                tre = np.array([c.tre_mm for c in rows])
                signed_err = np.array([np.subtract(c.params_pred, c.params_true) for c in rows])
                abs_err = np.array([c.abs_errors for c in rows])
                out(f"| {source} | {method} | {len(rows)} | {tre.mean():.2f} | {np.mean(tre < 2.0):.0%} | "
                    + " ".join(f"{v:.2f}" for v in abs_err.mean(0)) + " | "
                    + " ".join(f"{v:+.2f}" for v in signed_err.mean(0)) + " |")
        out()
    end_run(out, monitor, t0, args.results, notes)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
