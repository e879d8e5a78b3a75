"""Which CBCT degradation moves the image-based stages? A CT's paper-protocol cases simulated again with one
degradation at a time (noise only, scatter only, beam hardening only, all of them: the settings of the CT's
``bench_real_ct`` data) and registered by the learned network alone and by the default path; printed, per variant,
the mean signed error (estimate less truth, ``truth^-1 estimate`` as six parameters) of each.

The same moved object, geometry, projector and reconstruction as ``bench_real_ct``'s pairs (the CBCTs of the ``all``
row are those pairs' CBCTs, made again in this run); only the degradation of the line integrals changes.

    python -m benchmarks.accuracy.bench_physics_bias --ct abdomen_pelvis_tcia_tcga_ov_ct --num-cases 12 \\
        --results FILE
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.accuracy.bench_real_ct import data_name
from benchmarks.bench_common import end_run, pose_error, script_parser, start_registrar_run


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--ct", required=True, help="a CT whose bench_real_ct data is in --real-ct-dir")
    ap.add_argument("--real-ct-dir", type=Path, default=Path("bench_out/real_ct"),
                    help="bench_real_ct's --output-dir (default bench_out/real_ct)")
    ap.add_argument("--num-cases", type=int, default=12)
    ap.add_argument("--threads", type=int, default=2)
    args, out, monitor, t0, registrar = start_registrar_run(ap, __spec__.name if __spec__ else "bench_physics_bias")
    import SimpleITK as sitk
    import torch

    import monai_rigidreg
    from monai_rigidreg.evaluation.evaluate import iter_cases, load_datalist
    from monai_rigidreg.simulation.config import SimulationConfig
    from monai_rigidreg.simulation.physics import CBCTPhysics
    from monai_rigidreg.simulation.volumes import (
        _detector_radius,
        _object_volume,
        save_fov_mask,
        save_volume_hu,
        simulate_cbct,
        stream_seed,
    )

    d = args.real_ct_dir / data_name(Path(args.ct))
    cfg = SimulationConfig(**json.loads((d / "simulation.json").read_text())["config"])
    items = json.loads((d / "dataset.json").read_text())["training"][: args.num_cases]
    grid = cfg.object_grid()
    mu = _object_volume(cfg, 0, grid, torch.device("cpu"))
    radius = _detector_radius(cfg, grid, mu)
    first = next(iter_cases(load_datalist(d / "dataset.json")[0]))
    fixed = first.fixed
    points = first.points  # the TRE's body points (bench_real_ct's)
    p = cfg.cbct_physics
    variants = {
        "noise only": CBCTPhysics(photons=p.photons, electronic_noise=p.electronic_noise, scatter_to_primary=0.0,
                                  beam_hardening=0.0),
        "scatter only": CBCTPhysics(photons=None, electronic_noise=0.0, scatter_to_primary=p.scatter_to_primary,
                                    scatter_sigma_mm=p.scatter_sigma_mm, beam_hardening=0.0),
        "beam hardening only": CBCTPhysics(photons=None, electronic_noise=0.0, scatter_to_primary=0.0,
                                           beam_hardening=p.beam_hardening),
        "all": p,
    }
    out(f"{d.name}: {len(items)} paper-protocol cases; the data's physics {json.dumps(p.to_dict())}")
    out()
    out("| CBCT physics | method | n | mean TRE (mm) | mean signed error tx ty tz (mm), rx ry rz (deg) | sd |")
    out("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name, physics in variants.items():
            residuals: dict[bool, list] = {False: [], True: []}
            tres: dict[bool, list] = {False: [], True: []}
            for it in items:
                seed = stream_seed(cfg.seed, 1, int(it["case_id"][4:]))
                rec, fov, _ = simulate_cbct(mu, grid, cfg.cbct_grid, it["params"], (0.0, 0.0, 0.0), cfg.cbct_views,
                                            cfg.sod, cfg.sdd, physics, cfg.cbct_filter, seed=seed,
                                            detector_radius_mm=radius, padding_mode="border", device="cpu")
                save_volume_hu(rec, cfg.cbct_grid, Path(tmp) / "cbct.nii.gz", cfg.volume_dtype)
                save_fov_mask(fov, cfg.cbct_grid, Path(tmp) / "fov.nii.gz")
                moving = sitk.ReadImage(str(Path(tmp) / "cbct.nii.gz"), sitk.sitkFloat32)
                moving_fov = sitk.ReadImage(str(Path(tmp) / "fov.nii.gz"))
                for fine in (False, True):
                    res = monai_rigidreg.register(fixed, moving, model=registrar, moving_fov=moving_fov,
                                                  resample_moving=False, fine_stage=fine)
                    residual, tre = pose_error(it["params"], it["center"], res.params, res.center, points)
                    residuals[fine].append(residual)
                    tres[fine].append(tre)
            for fine in (False, True):
                r = np.asarray(residuals[fine])
                out(f"| {name} | {'default' if fine else 'alone'} | {len(r)} | {np.mean(tres[fine]):.2f} | "
                    + " ".join(f"{v:+.2f}" for v in r.mean(0)) + " | " + " ".join(f"{v:.2f}" for v in r.std(0))
                    + " |")
    out()
    end_run(out, monitor, t0, args.results, [])


if __name__ == "__main__":
    main()
