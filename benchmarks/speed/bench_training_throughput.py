"""Training throughput on the CPU: samples per second of the data pipeline and of the network step, separately.

The data side is the bundle's training chain (:func:`monai_rigidreg.engine.registration_transforms`, ``mode="train"``):
its deterministic head (load, resample onto the network grid) is cached as ``CacheDataset`` does, and what is timed
is the random tail every sample pays (isocentre crop, rigid motion of the CBCT on the context grid, cut to the network
grid, CBCT degradation, HU window), with the motion ranges and isocentre offsets of ``train.json``. The network side is
one optimisation step of the network ``train.json`` builds (:class:`~monai_rigidreg.networks.TwoStageRigidNet` with
the learned :class:`~monai_rigidreg.networks.CorrelationRigidNet` and the fine stage off, as trained, through
:class:`~monai_rigidreg.engine.StagedInferer`) with :class:`~monai_rigidreg.engine.RegistrationCriterion`: the
shipped training's supervised loss, and the reference's full composite loss. The slower of the two bounds training.

``--context`` measures the next network's training instead (``configs/train_context.json``): the data side is
:class:`~monai_rigidreg.engine.RigidPairSampler` drawing one sample (from the simulated pairs of ``--datalist`` and
the real CTs of ``--ct``), the network side one step of :class:`~monai_rigidreg.networks.ContextCorrelationNet` with
its training passes, bfloat16 encoders where available and the match loss.

Usage::

    python -m benchmarks.speed.bench_training_throughput --datalist data/train.json --threads 2
    python -m benchmarks.speed.bench_training_throughput --context --datalist data/train.json \
        data/clinical/dataset.json --ct ../shared/data/thorax_tcia_cptac_pda_ct.nii.gz --threads 2
"""

from __future__ import annotations

import os
import statistics
import time
from typing import Any

import torch
from monai.bundle import ConfigParser
from monai.data import CacheDataset, load_decathlon_datalist
from monai.utils import set_determinism

from benchmarks.bench_common import script_parser
from monai_rigidreg.bundle.loader import default_bundle_path
from monai_rigidreg.engine import RegistrationCriterion, RegistrationPrepareBatch, StagedInferer
from monai_rigidreg.engine.data import registration_transforms
from monai_rigidreg.losses import RigidRegistrationLoss

LOSSES = {
    "supervised (shipped training)": {"w_ssim": 0.0, "w_ncc": 0.0, "w_mi": 0.0, "w_grad": 0.1, "w_sup": 1.0},
    "composite SSIM+NCC+MI+grad+L2 + supervised": {"w_ssim": 1.0, "w_ncc": 0.1, "w_mi": 0.1, "w_grad": 0.1,
                                                   "w_sup": 1.0},
}


def median_step_seconds(network, criterion, inferer, optimizer, inputs, targets, steps: int) -> float:
    """Median seconds of one training step (forward, loss, backward, optimizer step) over ``max(2, steps)`` steps
    after one warm-up step, on the same batch."""
    times = []
    for k in range(max(2, steps) + 1):
        t0 = time.perf_counter()
        optimizer.zero_grad()
        loss = criterion(inferer(inputs, network), targets)
        loss.backward()
        optimizer.step()
        if k:  # the first step warms up
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--datalist", nargs="+", default=["data/train.json"])
    ap.add_argument("--context", action="store_true", help="the context network's sampler and step (train_context)")
    ap.add_argument("--ct", nargs="*", default=[], help="--context: real CTs as sources too")
    ap.add_argument("--precision", nargs="+", choices=["config", "float32"], default=["config"],
                    help="--context: the encoders' training precision, the config's choice for this machine "
                         "(bfloat16 where the CPU has the kernels) and/or float32; each timed on the same batch")
    ap.add_argument("--items", type=int, default=6, help="datalist items cached")
    ap.add_argument("--samples", type=int, default=12, help="samples timed per measurement")
    ap.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    set_determinism(seed=0)
    if args.context:
        return context_throughput(args)
    args.datalist = args.datalist[0]
    cfg = ConfigParser()
    cfg.read_config(str(default_bundle_path() / "configs" / "train.json"))
    size, spacing = cfg["network_size"], cfg["network_spacing"]
    pre = cfg["train"]["preprocessing"]
    print(f"threads {args.threads}; network grid {size} at {spacing} mm; load {os.getloadavg()[0]:.2f}")

    data = load_decathlon_datalist(args.datalist, is_segmentation=False, data_list_key="training")[: args.items]
    chain = registration_transforms("train", size, spacing, translate_range=cfg["translate_range"],
                                    rotate_range=cfg["rotate_range"], axis_prob=cfg["axis_prob"],
                                    degradation_kwargs=pre["degradation_kwargs"], context_size=cfg["context_size"],
                                    isocenter_offset=cfg["isocenter_offset"])
    t0 = time.perf_counter()
    dataset = CacheDataset(data, chain, cache_rate=1.0, num_workers=0, progress=False)
    cache_s = (time.perf_counter() - t0) / len(data)
    dataset[0]  # warm-up
    times = []
    for i in range(args.samples):
        t0 = time.perf_counter()
        dataset[i % len(dataset)]
        times.append(time.perf_counter() - t0)
    data_s = statistics.median(times)
    print("\n| data pipeline | s per sample | samples per second |")
    print("|---|---|---|")
    print(f"| cached head (load + network-grid resampling), once per item | {cache_s:.3f} | {1 / cache_s:.1f} |")
    print(f"| random tail (isocentre crop + motion + cut + CBCT degradation + HU window), per sample | {data_s:.3f} | "
          f"{1 / data_s:.1f} |")

    network = cfg.get_parsed_content("network_def", instantiate=True)
    network.train()
    prepare, inferer = RegistrationPrepareBatch(), StagedInferer()
    optimizer = torch.optim.Adam(network.parameters(), lr=1e-5)
    print("\n| network step (forward + loss + backward + Adam) | batch | s per step | samples per second |")
    print("|---|---|---|---|")
    for name, weights in LOSSES.items():
        criterion = RegistrationCriterion(size, spacing, RigidRegistrationLoss(**weights))
        for b in args.batch_sizes:
            batch = torch.utils.data.default_collate([dataset[i % len(dataset)] for i in range(b)])
            inputs, targets = prepare(batch, device="cpu")
            step = median_step_seconds(network, criterion, inferer, optimizer, inputs, targets, args.samples // b)
            print(f"| {name} | {b} | {step:.3f} | {b / step:.2f} |")
    print(f"\nload at the end {os.getloadavg()[0]:.2f}")


def context_config() -> ConfigParser:
    """The bundle's ``train.json`` with ``train_context.json`` over it, as ``scripts/train_context_model.sh`` runs."""
    configs = default_bundle_path() / "configs"
    cfg = ConfigParser()
    cfg.read_config([str(configs / "train.json"), str(configs / "train_context.json")])
    return cfg


def context_sampler(cfg: ConfigParser, datalists: list[str], cts: list[str]) -> tuple[Any, float]:
    """The training run's :class:`RigidPairSampler` over ``datalists`` and ``cts`` (seed 0) and the seconds reading
    its sources took."""
    from monai_rigidreg.engine.sampler import RigidPairSampler, load_sources

    size, spacing = cfg["network_size"], cfg["network_spacing"]
    t0 = time.perf_counter()
    sources = load_sources(datalists=datalists, cts=cts, network_spacing=spacing[0],
                           context_spacing=spacing[0] * cfg["context_factor"])
    load_s = time.perf_counter() - t0
    return RigidPairSampler(sources, network_size=size, network_spacing=spacing, seed=0), load_s


def context_throughput(args) -> None:
    """The data side (one :class:`RigidPairSampler` sample, one core as in the run's worker) and the network side
    (one step of the context network with the match loss) of ``scripts/train_context_model.sh``."""
    import numpy as np
    from monai.data import list_data_collate

    cfg = context_config()
    size, spacing = cfg["network_size"], cfg["network_spacing"]
    print(f"threads {args.threads}; network grid {size} at {spacing} mm; load {os.getloadavg()[0]:.2f}")
    sampler, load_s = context_sampler(cfg, args.datalist, args.ct)
    rng = np.random.default_rng(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in the run's DataLoader worker
    sampler.draw(rng)
    times = []
    for _ in range(args.samples):
        t0 = time.perf_counter()
        sampler.draw(rng)
        times.append(time.perf_counter() - t0)
    torch.set_num_threads(threads)
    data_s = statistics.median(times)
    print("\n| data pipeline (RigidPairSampler) | s per sample | samples per second |")
    print("|---|---|---|")
    print(f"| reading the {len(sampler.sources)} sources, once | {load_s:.1f} | - |")
    print(f"| one sample (one thread) | {data_s:.3f} | {1 / data_s:.1f} |")
    network = cfg.get_parsed_content("network_def", instantiate=True)
    network.train()
    criterion = cfg.get_parsed_content("loss", instantiate=True)
    prepare, inferer = RegistrationPrepareBatch(), StagedInferer()
    optimizer = torch.optim.Adam(network.parameters(), lr=1e-5)
    chosen = {m: m.train_autocast for m in network.modules() if hasattr(m, "train_autocast")}
    print("\n| network step (forward + loss + backward + Adam) | encoders | batch | s per step | samples per second |")
    print("|---|---|---|---|---|")
    for b in args.batch_sizes:
        inputs, targets = prepare(list_data_collate([sampler.draw(rng) for _ in range(b)]), device="cpu")
        for precision in args.precision:
            for m, autocast in chosen.items():
                m.train_autocast = autocast if precision == "config" else None
            label = ", ".join(sorted({str(m.train_autocast or "float32") for m in chosen})) or "float32"
            step = median_step_seconds(network, criterion, inferer, optimizer, inputs, targets, args.samples // b)
            print(f"| context network, train_context.json's loss | {label} | {b} | {step:.3f} | {b / step:.2f} |")
    print(f"\nload at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
