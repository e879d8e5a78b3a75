"""Simulate clinical-geometry training pairs from real CTs: cone-beam CBCTs at random isocentres and setup errors.

For each CT, ``--cases`` pairs are drawn as the clinical-geometry benchmark draws them
(:func:`monai_rigidreg.simulation.clinical.make_clinical_case`: an isocentre in the body 0-100 mm from the CT
centre, a setup error of the ``small`` or ``large`` band, a CBCT simulated from projections with randomized physics:
photons, scatter, beam hardening, source distances, field-of-view diameter, views). Each pair is a folder with
``cbct.nii.gz``, ``cbct_fov.nii.gz`` and ``case.json``; ``dataset.json`` lists them as a MONAI datalist
(``training``) with the CT's path, ready for :func:`monai_rigidreg.engine.sampler.sources_from_datalist`.

Deterministic in ``--seed`` (case seeds from the CT's name and the case number); a case already written is kept
(an interrupted run resumes). Progress: one line per case.

    python scripts/make_clinical_training_data.py --output-dir data/clinical --cases 12 \
        ../shared/data/head_tcia_cptac_lscc_ct.nii.gz ../shared/data/thorax_tcia_cptac_pda_ct.nii.gz
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from monai_rigidreg.simulation.clinical import (
    CLINICAL_GROUPS,
    CLINICAL_PHYSICS,
    ClinicalCBCTSpec,
    case_seed,
    load_clinical_case,
    load_planning_ct,
    make_clinical_case,
    save_clinical_case,
)


def case_spec(rng: np.random.Generator) -> ClinicalCBCTSpec:
    """A randomized acquisition: physics, distances and field of view (2.5 mm voxels, 260 x 260 x 160 mm grid), the
    exposure raised for a thick patient as in the benchmark's pairs (``CLINICAL_PHYSICS.exposure_reference``; pairs
    written before 2026-12-06 were simulated without it and are kept: delete a CT's folders to simulate them again)."""
    physics = replace(
        CLINICAL_PHYSICS,
        photons=float(10 ** rng.uniform(4.0, 5.5)),
        scatter_to_primary=float(rng.uniform(0.1, 0.8)),
        beam_hardening=float(rng.uniform(0.0, 0.04)),
        electronic_noise=float(rng.uniform(2.0, 15.0)),
        fov_diameter_mm=float(rng.uniform(200.0, 260.0)),
    )
    sod = float(rng.choice([800.0, 1000.0]))
    return ClinicalCBCTSpec(size=(104, 104, 64), spacing=2.5, views=int(rng.choice([90, 120, 180])), sod=sod,
                            sdd=1.5 * sod, physics=physics)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cts", nargs="+", help="CT files (HU)")
    parser.add_argument("--output-dir", required=True)
    parser.add_argument("--cases", type=int, default=12, help="pairs per CT")
    parser.add_argument("--large-share", type=float, default=0.4, help="share of pairs from the large band")
    parser.add_argument("--seed", type=int, default=7000)
    parser.add_argument("--threads", type=int, default=max(1, (os.cpu_count() or 2) // 2))
    parser.add_argument("--shard", default="0/1", help="I/N: simulate every N-th case starting at I (parallel runs)")
    parser.add_argument("--device", default="cpu", help="device of the projector and reconstruction (cpu, cuda)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    shard, shards = (int(v) for v in args.shard.split("/"))
    out = Path(args.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(ct, i) for ct in args.cts for i in range(args.cases)]
    cts: dict[str, object] = {}
    for n, (ct_path, i) in enumerate(jobs):
        name = Path(ct_path).name.split(".nii")[0]
        folder = out / f"{name}_{i:03d}"
        if n % shards != shard or load_clinical_case(folder) is not None:
            continue
        if name not in cts:
            cts[name] = load_planning_ct(ct_path)
        seed = case_seed(args.seed, name, i)
        rng = np.random.default_rng(seed)
        group = CLINICAL_GROUPS["large" if rng.random() < args.large_share else "small"]
        t0 = time.perf_counter()
        case = make_clinical_case(cts[name], group, seed, case_id=folder.name, spec=case_spec(rng), num_landmarks=20,
                                  device=args.device)
        save_clinical_case(case, folder, fixed=ct_path)
        print(f"{folder.name}: {group.name}, isocentre {case.record['isocenter_distance_mm']:.0f} mm, "
              f"{time.perf_counter() - t0:.1f} s", flush=True)
    if shard == 0:
        write_datalist(out)
    return 0


def write_datalist(out: Path) -> Path:
    """``dataset.json`` of every complete case under ``out`` (paths relative to ``out``; the CT's absolute)."""
    items = []
    for folder in sorted(p for p in out.iterdir() if p.is_dir()):
        case = load_clinical_case(folder)
        if case is None:
            continue
        rec = dict(case.record)
        rec["moving"] = f"{folder.name}/{rec['moving']}"
        rec["moving_fov"] = f"{folder.name}/{rec['moving_fov']}"
        for k in ("landmarks", "landmarks_moving"):
            rec.pop(k, None)
        items.append(rec)
    path = out / "dataset.json"
    path.write_text(json.dumps({"training": items}, indent=1))
    print(f"{len(items)} pairs -> {path}", flush=True)
    return path


if __name__ == "__main__":
    sys.exit(main())
