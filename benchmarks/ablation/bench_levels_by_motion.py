"""Where a context-network checkpoint stands per level and per band of motion, on the training stream's own samples.

The training log averages every level's loss over the whole motion distribution (``DEFAULT_MOTIONS``: small setup
errors, up to 40 mm / 30 degrees, 30-60 mm / 45 degrees), so a level that works on small motions and fails on large
ones reads as "not learning". This script draws ``--samples`` pairs per band from the training sampler
(:class:`~monai_rigidreg.engine.RigidPairSampler`, the bundle's train config, the same sources as
``scripts/train_context_model.sh``) with only that band's motion, runs the checkpoint's network in evaluation mode
(:meth:`~monai_rigidreg.networks.ContextCorrelationNet.forward_levels` with the match records) and prints per band:
the supervised point distance (mm, the training's ``loss_sup`` measure) after the coarse level and after each pass,
and each level's match loss (nats; a uniform coarse softmax over 4 096 cells is 8.32).

    python -m benchmarks.ablation.bench_levels_by_motion training/context_run/models/checkpoint_checkpoint_epoch=35.pt \
        --data data --samples 8 --threads 1

Samples come from the training CTs (not held out): this is a diagnosis of training, not an accuracy figure.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.ablation.context_setup import add_common_options
from benchmarks.bench_common import Tee, end_run, script_parser, start_run

BANDS = {  # name: (max translation mm, max rotation deg, min translation mm)
    "small (10 mm, 10 deg)": (10.0, 10.0, 0.0),
    "moderate (40 mm, 30 deg)": (40.0, 30.0, 0.0),
    "large (30-60 mm, 45 deg)": (60.0, 45.0, 30.0),
    "paper-like (15 mm, 5 deg)": (15.0, 5.0, 0.0),
    "between (25 mm, 15 deg)": (25.0, 15.0, 0.0),
}
TRAINING_LISTS = ("train.json", "clinical/dataset.json")


def main() -> None:
    from monai_rigidreg.networks.context_net import COARSE_STARTS

    ap = script_parser(__doc__)
    ap.add_argument("checkpoint", type=Path, help="a training checkpoint (checkpoint_*epoch=N.pt) or model.pt")
    ap.add_argument("--samples", type=int, default=8, help="pairs per band (default 8)")
    ap.add_argument("--passes", type=int, nargs=2, default=None,
                    help="passes of the 8 mm and 4 mm levels (default: the train config's; inference uses 2 1)")
    ap.add_argument("--coarse-start", choices=COARSE_STARTS, default="coarse",
                    help="where the local levels start (ContextCorrelationNet's coarse_start)")
    add_common_options(ap, seed=123, data_help='the training data folder (train.json, clinical/)')
    args = ap.parse_args()
    out = Tee()
    monitor, t0 = start_run(out, __spec__.name if __spec__ else "bench_levels_by_motion", args.threads, "cpu",
                            str(args.checkpoint))
    import torch

    from benchmarks.ablation.context_setup import sampler_sources, train_config
    from monai_rigidreg.core.geometry import params_to_matrix_torch
    from monai_rigidreg.engine import RigidPairSampler
    from monai_rigidreg.engine.criterion import canonical_grid
    from monai_rigidreg.engine.sampler import MotionRange
    from monai_rigidreg.io.shared_data import TRAINING_CTS
    from monai_rigidreg.losses import RigidRegistrationLoss, match_loss
    from monai_rigidreg.transforms import RIGID_KEY

    torch.set_num_threads(args.threads)
    parser = train_config()
    net = parser.get_parsed_content("network_def")
    state = torch.load(args.checkpoint, map_location="cpu", weights_only=True)
    net.load_state_dict(state.get("network", state))
    net.eval()
    net.regression.coarse_start = args.coarse_start
    if args.passes is not None:
        net.regression.passes = tuple(args.passes)
    sources, size, spacing, factor = sampler_sources(parser, args.data, args.shared, TRAINING_LISTS)
    n_lists = sum((args.data / name).is_file() for name in TRAINING_LISTS)
    n_cts = sum((args.shared / f"{n}.nii.gz").is_file() for n in TRAINING_CTS)
    grid = canonical_grid(size, spacing)
    sup = RigidRegistrationLoss(w_ssim=0.0, w_ncc=0.0, w_mi=0.0, w_grad=0.0, w_sup=1.0, w_reg=0.0)
    out(f"sources: {len(sources)} ({n_lists} datalists, {n_cts} CTs); {args.samples} samples per band; "
        f"passes {net.regression.passes}; local levels start from: {args.coarse_start}\n")
    out("| band | level | point distance mean (mm) | median | share < 2 mm | match loss (nats) |")
    out("|---|---|---|---|---|---|")
    record: dict[str, Any] = {}
    for name, (t_max, r_max, t_min) in BANDS.items():
        band = MotionRange(t_max, r_max, min_translation=t_min)
        sampler = RigidPairSampler(sources, size, spacing, context_factor=factor, motions=(band,),
                                   case_motions=(band,), seed=args.seed)
        it = iter(sampler)
        dists: list[list[float]] = []
        nats: list[list[float]] = []
        ident: list[float] = []
        for _ in range(args.samples):
            s = next(it)
            moving, fixed, context = (s[k][None].float() for k in ("moving", "fixed", "context"))
            gt = s[RIGID_KEY]
            truth = torch.as_tensor(np.asarray(gt["params"] if isinstance(gt, dict) else gt),
                                    dtype=torch.float32).reshape(1, 6)
            with torch.no_grad():
                levels, records = net.regression.forward_levels(moving, fixed, context, matches=True)
            dists.append([float(sup.sup_term(p.float(), truth, grid)) for p in levels])
            ident.append(float(sup.sup_term(torch.zeros_like(truth), truth, grid)))
            m = params_to_matrix_torch(truth.to(torch.float64))
            # with both starts the local levels' records hold the doubled batch: their match loss is not read
            nats.append([float(match_loss(r, m)) if i == 0 or args.coarse_start != "both" else float("nan")
                         for i, r in enumerate(records)])
        d = np.asarray(dists)
        d0 = np.asarray(ident)
        n = np.asarray(nats)
        record[name] = {"point_distance_mm": d.tolist(), "match_nats": n.tolist()}
        out(f"| {name} | identity (no estimate) | {d0.mean():.2f} | {np.median(d0):.2f} | "
            f"{(d0 < 2.0).mean():.2f} | - |")
        for j in range(d.shape[1]):
            nat = f"{n[:, j].mean():.2f}" if j < n.shape[1] else "-"
            out(f"| {name} | {'coarse' if j == 0 else f'pass {j}'} | {d[:, j].mean():.2f} | "
                f"{np.median(d[:, j]):.2f} | {(d[:, j] < 2.0).mean():.2f} | {nat} |")
    if args.results is not None:
        args.results.with_suffix(".json").write_text(json.dumps(record) + "\n")
    end_run(out, monitor, t0, args.results, [])


if __name__ == "__main__":
    main()
