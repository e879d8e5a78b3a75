"""Ablation of the learned network: design and loss terms, each trained for the same budget, measured alone on
held-out real CTs.

Every variant is trained from scratch with the same seed on the same on-the-fly stream: the bundle's training chain
(:func:`monai_rigidreg.engine.registration_transforms`, ``mode="train"``, with ``train.json``'s motion ranges,
isocentre offsets and CBCT degradation) over the base pairs of ``--datalist`` (``scripts/make_training_data.sh``:
phantoms, synthetic anatomy and the abdomen-pelvis CT; the thorax and head CTs are not in it), for ``--iterations``
optimiser steps of batch ``--batch-size``. Then the learned network alone (no Gauss-Newton stage, no search) registers
every case of the held-out datalists (``benchmarks/accuracy/bench_real_ct.py`` simulates them: paper protocol, cone-beam
CBCT from the projection-domain simulator) and the TRE over CT body points inside the CBCT is summarised.

Variants (``--variants``):

* ``mlp``: the reference design, :class:`~monai_rigidreg.networks.DualEncoderRigidNet` (shared encoder, flattened
  features, MLP, six bounded outputs) with the supervised loss;
* ``corr``: what ships, :class:`~monai_rigidreg.networks.CorrelationRigidNet` (global then local correlation,
  weighted closed-form rigid fit), supervised point distance of the final and the coarse estimate;
* ``corr-nolevels``: the same without the coarse level's supervision (``w_levels=0``);
* ``corr-composite``: the reference's composite loss SSIM + NCC + MI + gradient + L2 (weights 1, 0.1, 0.1, 0.1,
  1e-4) plus the supervised terms;
* ``corr-image-only``: the composite loss without any supervised term (unsupervised, as the reference trains);
* ``context``: the next network, :class:`~monai_rigidreg.networks.ContextCorrelationNet` (``train_context.json``'s
  settings: coarse level over the CT context, 8 mm and 4 mm levels, training passes), supervised point distance of
  every level plus the match loss (:func:`~monai_rigidreg.losses.match_loss`, weight 1);
* ``context-nomatch``: the same without the match loss;
* ``context-no4mm``: the same without the 4 mm level.

``--stream sampler`` trains every variant on the context network's stream instead
(:class:`~monai_rigidreg.engine.RigidPairSampler` over ``--datalist``, e.g. ``data/train.json`` and
``data/clinical/dataset.json``, and the four training CTs: the clinic's range of motion); the networks without a
context get the same samples without it.

Usage (the 2026-12-01 rows; then the context rows on the sampler stream)::

    python -m benchmarks.ablation.bench_ablation --iterations 300 \\
        --results benchmarks/results/0.3.0/bench_ablation_2026-12-01.txt
    python -m benchmarks.ablation.bench_ablation --stream sampler --iterations 150 \\
        --datalist data/train.json data/clinical/dataset.json --variants mlp corr context context-nomatch \\
        context-no4mm --results benchmarks/results/0.4.9/bench_ablation_context_<date>.txt
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_common import script_parser
from monai_rigidreg.io.shared_data import TRAINING_CTS, training_ct_paths

REPO = Path(__file__).resolve().parents[2]

HELD_OUT = ("bench_out/real_ct/thorax_4dct_phase00_itkelastix/dataset.json",
            "bench_out/real_ct/head_tigre_ct/dataset.json")
SUP_ONLY = {"w_ssim": 0.0, "w_ncc": 0.0, "w_mi": 0.0, "w_grad": 0.1, "w_reg": 1e-4, "w_sup": 1.0}
COMPOSITE = {"w_ssim": 1.0, "w_ncc": 0.1, "w_mi": 0.1, "w_grad": 0.1, "w_reg": 1e-4, "w_sup": 1.0}
VARIANTS = {  # name: (design, loss weights, w_levels, w_match)
    "mlp": ("mlp", SUP_ONLY, 0.5, 0.0),
    "corr": ("corr", SUP_ONLY, 0.5, 0.0),
    "corr-nolevels": ("corr", SUP_ONLY, 0.0, 0.0),
    "corr-composite": ("corr", COMPOSITE, 0.5, 0.0),
    "corr-image-only": ("corr", {**COMPOSITE, "w_sup": 0.0}, 0.0, 0.0),
    "context": ("context", SUP_ONLY, 0.5, 1.0),
    "context-nomatch": ("context", SUP_ONLY, 0.5, 0.0),
    "context-no4mm": ("context-no4mm", SUP_ONLY, 0.5, 1.0),
}
TRAIN_CTS = TRAINING_CTS
"""The real CTs of the ``sampler`` stream (the training CTs of ``scripts/train_context_model.sh``)."""


def build(design: str, train_cfg: dict):
    """The regression network of a design, with train.json's settings for the shipped one and
    train_context.json's for the context network."""
    from monai_rigidreg.networks import ContextCorrelationNet, CorrelationRigidNet, DualEncoderRigidNet

    if design.startswith("context"):
        ctx = json.loads((REPO / "bundles/cbct_ct_rigid/configs/train_context.json").read_text())
        kw = {k: v for k, v in ctx["network_def#regression"].items()
              if not k.startswith("_") and not (isinstance(v, str) and v.startswith(("@", "$")))}
        passes = tuple(ctx["train_passes"])
        return ContextCorrelationNet(grid_size=train_cfg["network_size"], grid_spacing=train_cfg["network_spacing"],
                                     passes=(passes[0], 0) if design == "context-no4mm" else passes,
                                     context_factor=ctx["context_factor"], **kw)

    if design == "mlp":  # the reference design as bundle 0.2 shipped it
        return DualEncoderRigidNet(channels=(8, 16, 32, 32), strides=(2, 2, 2, 2), num_res_units=2, fusion="flatten",
                                   fusion_channels=16, pool_size=4, hidden=(128,), max_translation=40.0,
                                   max_rotation=45.0)
    kw = {k: v for k, v in train_cfg["network_def"]["regression"].items() if not k.startswith("_")}
    kw["grid_size"] = train_cfg["network_size"]
    kw["grid_spacing"] = train_cfg["network_spacing"]
    return CorrelationRigidNet(**kw)


def train_variant(name: str, args: argparse.Namespace, train_cfg: dict, out) -> tuple:
    import torch
    from monai.data import CacheDataset, DataLoader, load_decathlon_datalist
    from monai.utils import set_determinism

    from monai_rigidreg.engine import RegistrationCriterion, RegistrationPrepareBatch
    from monai_rigidreg.engine.data import registration_transforms
    from monai_rigidreg.losses import RigidRegistrationLoss
    from monai_rigidreg.networks import TwoStageRigidNet

    design, weights, w_levels, w_match = VARIANTS[name]
    set_determinism(seed=args.seed)
    net = build(design, train_cfg)
    model = TwoStageRigidNet(net, None)
    if args.stream == "sampler":  # every variant sees the same samples (seeded); the context only where taken
        loader = DataLoader(_sampler(args, train_cfg), batch_size=args.batch_size, num_workers=1,
                            persistent_workers=True)
    else:
        pre = train_cfg["train"]["preprocessing"]
        chain = registration_transforms(
            "train", train_cfg["network_size"], train_cfg["network_spacing"],
            translate_range=train_cfg["translate_range"], rotate_range=train_cfg["rotate_range"],
            axis_prob=train_cfg["axis_prob"], degradation_kwargs=pre["degradation_kwargs"],
            context_size=train_cfg["context_size"], isocenter_offset=train_cfg["isocenter_offset"])
        items = load_decathlon_datalist(str(args.datalist[0]), is_segmentation=False, data_list_key="training")
        ds = CacheDataset(items, chain, cache_rate=1.0, num_workers=0, progress=False)
        loader = DataLoader(ds, batch_size=args.batch_size, shuffle=True, num_workers=1, persistent_workers=True)
    crit = RegistrationCriterion(train_cfg["network_size"], train_cfg["network_spacing"],
                                 loss=RigidRegistrationLoss(**weights), w_levels=w_levels, w_match=w_match)
    opt = torch.optim.Adam(model.parameters(), lr=args.learning_rate)
    prepare = RegistrationPrepareBatch(context_key="context" if getattr(net, "takes_context", False) else None)
    step, t0, losses = 0, time.perf_counter(), []
    while step < args.iterations:
        for batch in loader:
            inputs, targets = prepare(batch)
            loss = crit(model(inputs, stages=True), targets)
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(crit.last_terms.get("sup", float(loss.detach())))
            step += 1
            if step % 50 == 0:
                out(f"  {name}: step {step}/{args.iterations}, supervised term (last 50) "
                    f"{np.mean(losses[-50:]):.2f} mm, {(time.perf_counter() - t0) / step:.2f} s/step")
            if step >= args.iterations:
                break
    seconds = time.perf_counter() - t0
    return model, seconds


_SOURCES: list = []


def _sampler(args: argparse.Namespace, train_cfg: dict):
    """The ``sampler`` stream: :class:`~monai_rigidreg.engine.RigidPairSampler` over ``--datalist`` (simulated
    pairs) and the training CTs of ``--data``, seeded; the sources are read once for all variants."""
    from monai_rigidreg.engine.sampler import RigidPairSampler, load_sources
    from monai_rigidreg.io.shared_data import shared_data_dir

    if not _SOURCES:
        data = args.data or shared_data_dir()
        cts = training_ct_paths(data)
        _SOURCES.extend(load_sources(datalists=args.datalist, cts=cts, network_spacing=train_cfg["network_spacing"][0],
                                     context_spacing=2 * train_cfg["network_spacing"][0]))
    return RigidPairSampler(_SOURCES, network_size=train_cfg["network_size"],
                            network_spacing=train_cfg["network_spacing"], seed=args.seed)


def evaluate(model, datalists: list[Path], train_cfg: dict) -> dict[str, list[float]]:
    from monai_rigidreg.evaluation import evaluate_datalist
    from monai_rigidreg.registration.registrar import RigidRegistrar

    registrar = RigidRegistrar(model.eval(), network_size=train_cfg["network_size"],
                               network_spacing=train_cfg["network_spacing"], device="cpu")
    tre: dict[str, list[float]] = {}
    for dl in datalists:
        res = evaluate_datalist(dl, methods=["network-regression"], registrar=registrar, progress=False, html=False)
        tre[dl.parent.name] = [c.tre_mm for c in res["cases"]]
    return tre


def main() -> int:
    ap = script_parser(__doc__)
    ap.add_argument("--datalist", type=Path, nargs="+", default=[Path("data/train.json")],
                    help="simulated training pairs (the chain stream reads the first)")
    ap.add_argument("--stream", choices=("chain", "sampler"), default="chain",
                    help="chain: the shipped network's training chain (registration_transforms) over --datalist, "
                         "as the 2026-12-01 rows; sampler: the context network's RigidPairSampler over --datalist "
                         "and the training CTs (clinical range of motion)")
    ap.add_argument("--data", type=Path, default=None, help="folder of the real CTs (default ../shared/data)")
    ap.add_argument("--held-out", type=Path, nargs="+", default=[Path(p) for p in HELD_OUT])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--learning-rate", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--results", type=Path, default=None)
    args = ap.parse_args()
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import torch

    torch.set_num_threads(args.threads)
    lines: list[str] = []

    def out(text: str = "") -> None:
        print(text, flush=True)
        lines.append(text)

    missing = [p for p in [*args.datalist, *args.held_out] if not p.is_file()]
    if missing:
        out(f"missing datalist(s): {', '.join(map(str, missing))} (scripts/make_training_data.sh, "
            "benchmarks/accuracy/bench_real_ct.py simulate them)")
        return 2
    train_cfg = json.loads((REPO / "bundles/cbct_ct_rigid/configs/train.json").read_text())
    out(f"command: python {shlex.join([os.path.relpath(sys.argv[0]), *sys.argv[1:]])}")
    out(f"date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}; machine: {platform.node()}, "
        f"{os.cpu_count()} cores, threads {args.threads}; load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    stream = (f"{args.stream} stream from {' '.join(map(str, args.datalist))}"
              + (f" and the CTs {', '.join(TRAIN_CTS)}" if args.stream == "sampler" else ""))
    out(f"training: {args.iterations} steps of batch {args.batch_size}, Adam lr {args.learning_rate}, "
        f"seed {args.seed}, {stream}; held out: {', '.join(p.parent.name for p in args.held_out)}")
    rows = []
    for name in args.variants:
        model, seconds = train_variant(name, args, train_cfg, out)
        tre = evaluate(model, args.held_out, train_cfg)
        rows.append((name, sum(p.numel() for p in model.parameters()), seconds, tre))
    out()
    cts = [p.parent.name for p in args.held_out]
    out("| variant | parameters | train s/step | " + " | ".join(f"{c} mean TRE (mm)" for c in cts)
        + " | all: mean | median | < 2 mm | < 12 mm | max (mm) |")
    out("|---" * (8 + len(cts)) + "|")
    for name, n_params, seconds, tre in rows:
        allv = np.concatenate([tre[c] for c in cts])
        out(f"| {name} | {n_params} | {seconds / args.iterations:.2f} | "
            + " | ".join(f"{np.mean(tre[c]):.2f}" for c in cts)
            + f" | {allv.mean():.2f} | {np.median(allv):.2f} | {np.mean(allv < 2) * 100:.0f} % | "
            f"{np.mean(allv < 12) * 100:.0f} % | {allv.max():.1f} |")
    if args.results:
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
