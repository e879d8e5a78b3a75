"""Where does the context network's coarse level get its gradient from in the full training loss?

In the full run the coarse level's match loss rose after its pretraining (``training/context_run_v3``: 5.7 nats at
the first epoch, 6.4-6.8 by the twentieth). Its parameters receive gradients from three groups of terms of the
bundle's criterion (:class:`~monai_rigidreg.engine.RegistrationCriterion` with ``train_context.json``'s weights):

* ``match``: its own match loss (:func:`~monai_rigidreg.losses.match_loss` of the coarse level);
* ``level``: the supervised point distance of its own estimate (``w_levels`` times ``level0``);
* ``downstream``: the terms of the later levels' estimates (the final estimate's supervised term and
  ``w_levels`` times ``level1``), which reach the coarse level because each level composes its correction onto the
  coarse estimate (``total @ correction``) while it warps with a detached copy: their gradient moves the coarse
  estimate as if the local levels would not correct a change of it.

For batches of the training sampler (all its motions, from the training CTs and data), the gradient of each group
on the coarse parameters (:func:`~monai_rigidreg.engine.coarse_pretrain.coarse_parameters`) is printed: its norm,
and the cosine between the groups (per batch and the mean). A ``downstream`` gradient much larger than the others
and unaligned with the ``match`` one says that the full loss drives the coarse level away from its match.

    python -m benchmarks.ablation.bench_coarse_gradients --init CKPT --batches 8 --threads 1

A diagnosis of training (training CTs), not an accuracy figure.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks.ablation.context_setup import add_common_options
from benchmarks.bench_common import Tee, end_run, script_parser, start_run


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--init", type=Path, required=True, help="weights (a model.pt or a training checkpoint)")
    ap.add_argument("--batches", type=int, default=8)
    ap.add_argument("--batch", type=int, default=4)
    add_common_options(ap, seed=0)
    args = ap.parse_args()
    out = Tee()
    monitor, t0 = start_run(out, __spec__.name if __spec__ else "bench_coarse_gradients", args.threads, "cpu",
                            str(args.init))
    import torch

    from benchmarks.ablation.context_setup import sampler_sources, train_config
    from monai_rigidreg.core.geometry import params_to_matrix_torch
    from monai_rigidreg.engine import RigidPairSampler
    from monai_rigidreg.engine.coarse_pretrain import coarse_parameters
    from monai_rigidreg.engine.handlers import load_matching_weights
    from monai_rigidreg.losses import match_loss

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    parser = train_config()
    model = parser.get_parsed_content("network_def")
    load_matching_weights(model, torch.load(args.init, map_location="cpu", weights_only=True))
    criterion = parser.get_parsed_content("loss")
    w_levels = float(criterion.w_levels)
    net = model.regression
    net.train()
    params = coarse_parameters(net)
    sources, size, spacing, factor = sampler_sources(parser, args.data, args.shared)
    it = iter(RigidPairSampler(sources, size, spacing, context_factor=factor, seed=args.seed))
    autocast = getattr(net, "train_autocast", getattr(net, "_autocast", None))
    out(f"weights: {args.init}; {args.batches} batches of {args.batch} from the training sampler; w_levels "
        f"{w_levels:g}; coarse parameters: {sum(p.numel() for p in params)}; encoders' autocast: {autocast}")

    def grad_of(loss: torch.Tensor) -> torch.Tensor:
        gs = torch.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
        return torch.cat([(torch.zeros_like(p) if g is None else g).flatten().double() for p, g in zip(params, gs)])

    def cos(a: torch.Tensor, b: torch.Tensor) -> float:
        return float(a @ b / (a.norm() * b.norm()).clamp_min(1e-30))

    out("\n| batch | match0 (nats) | level0 (mm) | final (mm) | norm match | norm level | norm downstream | "
        "cos(match, level) | cos(match, downstream) | cos(match + level, downstream) |")
    out("|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for k in range(args.batches):
        batch = [next(it) for _ in range(args.batch)]
        moving = torch.stack([b["moving"] for b in batch]).float()
        fixed = torch.stack([b["fixed"] for b in batch]).float()
        context = torch.stack([b["context"] for b in batch]).float()
        truth_params = torch.stack([b["rigid_params"]["params"] for b in batch]).float()
        truth = params_to_matrix_torch(truth_params.double())
        levels, records = net.forward_levels(moving, fixed, context, matches=True)
        grid = criterion.grid
        sup = [criterion.loss.sup_term(lv, truth_params, grid) for lv in levels]
        m0 = match_loss(records[0], truth)
        g_match = grad_of(m0)
        g_level = grad_of(w_levels * sup[0])
        down = sup[-1] + w_levels * sum(sup[1:-1]) if len(sup) > 2 else sup[-1]
        g_down = grad_of(down)
        row = [float(m0.detach()), float(sup[0].detach()), float(sup[-1].detach()), float(g_match.norm()),
               float(g_level.norm()), float(g_down.norm()), cos(g_match, g_level), cos(g_match, g_down),
               cos(g_match + g_level, g_down)]
        rows.append(row)
        out(f"| {k + 1} | " + " | ".join(f"{v:.3g}" for v in row) + " |")
    mean = np.mean(np.asarray(rows), axis=0)
    out("| mean | " + " | ".join(f"{v:.3g}" for v in mean) + " |")
    end_run(out, monitor, t0, args.results, [])


if __name__ == "__main__":
    main()
