"""Can the context network's coarse level find a CBCT cell among the CT context's cells when the two images agree?

The coarse level matches every 16 mm cell of the CBCT (a 128 mm volume) against every cell of the CT context (256 mm,
the same centre). Here the "CBCT" is the CT context's own central 128 mm, unmoved and undegraded, so every cell's
right match is known exactly and differences come from the encoder alone: its receptive field (a cell that sees past
the 128 mm volume's border sees zeros there, and the context's anatomy in the context) and its normalisation
(instance norm's statistics over a 128 mm and a 256 mm volume differ). Printed per variant: the share of the crop's
cells with anatomy whose best match (cosine similarity of the coarse features) is their own context cell, also with
every instance-norm layer using the statistics it had on the context (to tell the two causes apart).

    python -m benchmarks.ablation.bench_coarse_consistency --checkpoint CKPT --samples 6
    python -m benchmarks.ablation.bench_coarse_consistency --samples 6 --set coarse_units=1 --set coarse_norm=NONE

Without ``--checkpoint`` the network is freshly initialised (seed 0): the consistency a design starts from.
Samples are the training stream's CT contexts (training CTs; a diagnosis, not an accuracy figure).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks.ablation.context_setup import add_common_options
from benchmarks.bench_common import Tee, end_run, script_parser, start_run


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--checkpoint", type=Path, default=None, help="training checkpoint or model.pt (default: none)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a ContextCorrelationNet argument (JSON value or string), e.g. coarse_units=1")
    ap.add_argument("--samples", type=int, default=6)
    add_common_options(ap, seed=5)
    args = ap.parse_args()
    out = Tee()
    monitor, t0 = start_run(out, __spec__.name if __spec__ else "bench_coarse_consistency", args.threads, "cpu",
                            str(args.checkpoint or "freshly initialised"))
    import torch
    import torch.nn.functional as F
    from torch import nn

    from benchmarks.ablation.context_setup import sampler_sources, train_config
    from monai_rigidreg.engine import RigidPairSampler

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    parser = train_config(args.set)
    net = parser.get_parsed_content("network_def")
    if args.checkpoint is not None:
        state = torch.load(args.checkpoint, map_location="cpu", weights_only=True)
        net.load_state_dict(state.get("network", state))
    net.eval()
    r = net.regression
    norms = [m for m in r.coarse_encoder.modules() if isinstance(m, nn.modules.instancenorm._InstanceNorm)]
    stats: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
    mode = {"v": "plain"}
    for m in norms:
        def forward(x: torch.Tensor, m: nn.Module = m) -> torch.Tensor:
            if mode["v"] == "record":
                stats[id(m)] = (x.mean((2, 3, 4), keepdim=True), x.var((2, 3, 4), keepdim=True, unbiased=False))
            if mode["v"] == "use":
                mu, var = stats[id(m)]
                return (x - mu) / torch.sqrt(var + m.eps)
            return F.instance_norm(x, eps=m.eps)
        m.forward = forward  # type: ignore[method-assign]

    def feats(x: torch.Tensor) -> torch.Tensor:
        return F.normalize(r.coarse_project(r.coarse_encoder(x)[-1]), dim=1)

    sources, size, spacing, factor = sampler_sources(parser, args.data, args.shared)
    it = iter(RigidPairSampler(sources, size, spacing, context_factor=factor, seed=args.seed))
    n_ctx = [s // 4 for s in r.context_size]
    lo = [s // 4 for s in r.context_size]  # context voxels 16..48 of 64: the crop
    names = ("crop as is", "crop with the context's norm statistics")
    acc: dict[str, list[float]] = {k: [] for k in names}
    for _ in range(args.samples):
        ctx = next(it)["context"][None].float()
        q = [s // 4 for s in ctx.shape[2:]]
        crop = ctx[..., q[0]:3 * q[0], q[1]:3 * q[1], q[2]:3 * q[2]]
        with torch.no_grad():
            mode["v"] = "record"
            fc = feats(ctx).flatten(2)[0]
            mode["v"] = "plain"
            a = feats(crop)
            mode["v"] = "use"
            b = feats(crop)
        cells = torch.stack(torch.meshgrid(*[torch.arange(s) for s in a.shape[2:]], indexing="ij"), -1).reshape(-1, 3)
        own = cells + torch.tensor([lo[0] // 4, lo[1] // 4, lo[2] // 4])
        want = (own[:, 0] * n_ctx[1] + own[:, 1]) * n_ctx[2] + own[:, 2]
        valid = F.avg_pool3d((crop > 0.1).float(), 4).flatten() > 0.5
        for k, f in zip(names, (a, b)):
            best = (f.flatten(2)[0].T @ fc).argmax(-1)
            acc[k].append(float((best == want)[valid].float().mean()))
    out(f"variant: {' '.join(args.set) or 'the train config'}; {args.samples} CT contexts")
    for k in names:
        out(f"- {k}: {np.mean(acc[k]):.3f} of the cells find their own context cell (per sample: "
            f"{', '.join(f'{v:.2f}' for v in acc[k])})")
    end_run(out, monitor, t0, args.results, [])


if __name__ == "__main__":
    main()
