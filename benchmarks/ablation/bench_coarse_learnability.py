"""Can the context network's coarse level learn its match at all? The coarse level trained alone, briefly.

The full training run supervises the coarse level among five other terms over the whole range of motion. Here only
the coarse level runs (:meth:`~monai_rigidreg.networks.ContextCorrelationNet._coarse`: the CBCT's 16 mm cells
against the CT context's), trained on its match loss alone (:func:`~monai_rigidreg.losses.match_loss`) with Adam on
samples of one band of motion from the training sampler, and the loss and the share of cells whose best match is
within one cell (16 mm) of the truth are printed as it goes. A loss that stays near 8.3 nats (a uniform guess over
4 096 cells) on small motions says the design cannot learn it; a falling one, that the full run's mix is the
obstacle.

    python -m benchmarks.ablation.bench_coarse_learnability --steps 300 --band 10 10 --threads 1
    python -m benchmarks.ablation.bench_coarse_learnability --set coarse_units=2 --set coarse_norm=INSTANCE

Samples come from the training CTs (a diagnosis of training, not an accuracy figure); the network's other levels
are not used.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from benchmarks.ablation.context_setup import add_common_options
from benchmarks.bench_common import Tee, end_run, script_parser, start_run


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a ContextCorrelationNet argument (JSON value or string)")
    ap.add_argument("--init", type=Path, default=None, help="start from these weights (default: fresh, seed 0)")
    ap.add_argument("--band", type=float, nargs=2, default=[10.0, 10.0], metavar=("MM", "DEG"),
                    help="the motion band: largest translation (mm) and angle per axis (degrees)")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--every", type=int, default=25, help="print every N steps")
    add_common_options(ap, seed=0)
    args = ap.parse_args()
    out = Tee()
    monitor, t0 = start_run(out, __spec__.name if __spec__ else "bench_coarse_learnability", args.threads, "cpu",
                            str(args.init or "freshly initialised"))
    import torch

    from benchmarks.ablation.context_setup import sampler_sources, train_config
    from monai_rigidreg.engine import RigidPairSampler
    from monai_rigidreg.engine.coarse_pretrain import coarse_parameters, coarse_step
    from monai_rigidreg.engine.handlers import load_matching_weights
    from monai_rigidreg.engine.sampler import MotionRange

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    parser = train_config(args.set)
    model = parser.get_parsed_content("network_def")
    if args.init is not None:
        load_matching_weights(model, torch.load(args.init, map_location="cpu", weights_only=True))
    net = model.regression
    net.train()
    params = coarse_parameters(net)
    opt = torch.optim.Adam(params, lr=args.lr)
    sources, size, spacing, factor = sampler_sources(parser, args.data, args.shared)
    band = MotionRange(float(args.band[0]), float(args.band[1]))
    it = iter(RigidPairSampler(sources, size, spacing, context_factor=factor, motions=(band,), case_motions=(band,),
                               seed=args.seed))
    out(f"variant: {' '.join(args.set) or 'the train config'}; band {args.band[0]:g} mm / {args.band[1]:g} deg; "
        f"{args.steps} steps of {args.batch}; lr {args.lr:g}; trained: {sum(p.numel() for p in params)} parameters")
    out("\n| step | samples | match loss (nats, mean of the last steps) | cells within 16 mm | s |")
    out("|---|---|---|---|---|")
    losses: list[float] = []
    hits: list[float] = []
    t = time.perf_counter()
    for step in range(1, args.steps + 1):
        loss, share = coarse_step(net, [next(it) for _ in range(args.batch)])
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        hits.append(share)
        if step % args.every == 0 or step == args.steps:
            k = args.every
            out(f"| {step} | {step * args.batch} | {np.mean(losses[-k:]):.3f} | {np.nanmean(hits[-k:]):.3f} | "
                f"{time.perf_counter() - t:.0f} |")
    end_run(out, monitor, t0, args.results, [])


if __name__ == "__main__":
    main()
