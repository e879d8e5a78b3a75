"""Pretraining of :class:`~monai_rigidreg.networks.ContextCorrelationNet`'s coarse level alone, on its match loss.

In the full training run the coarse level (the CBCT's 16 mm cells against the 256 mm CT context's) is one of six
supervised terms over the clinic's whole range of motion, and its match loss stayed near a uniform guess (7.6-7.9
nats against 8.32 over 4 096 cells) for 16 800 samples. Trained alone on small motions it learns within a thousand
samples (``benchmarks/ablation/bench_coarse_learnability.py``). :func:`pretrain_coarse` runs that: only the coarse
level (:meth:`~monai_rigidreg.networks.ContextCorrelationNet._coarse`), only its parameters (the ``coarse_*``
modules and the levels' softmax temperatures), Adam on :func:`~monai_rigidreg.losses.match_loss`, over a schedule of
motion bands (a curriculum: small setup errors first), on samples of the training sampler.

>>> from monai_rigidreg.engine.sampler import MotionRange
>>> schedule = [(MotionRange(10.0, 10.0), 2), (MotionRange(40.0, 30.0), 1)]
>>> [band.max_translation for band, steps in schedule for _ in range(steps)]
[10.0, 10.0, 40.0]
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
import torch

from monai_rigidreg.core.geometry import params_to_matrix_torch
from monai_rigidreg.engine.sampler import MotionRange
from monai_rigidreg.losses import match_loss

__all__ = ["coarse_parameters", "coarse_step", "pretrain_coarse"]

logger = logging.getLogger(__name__)


def coarse_parameters(net: torch.nn.Module) -> list[torch.nn.Parameter]:
    """The coarse level's parameters of a ``ContextCorrelationNet``: its ``coarse_*`` modules and the softmax
    temperatures (``log_temperature``, one per level; the local levels' entries get no gradient here)."""
    return [p for n, p in net.named_parameters() if n.startswith("coarse_") or n == "log_temperature"]


def coarse_step(net: Any, batch: Sequence[dict[str, Any]]) -> tuple[torch.Tensor, float]:
    """The coarse level on a list of sampler samples: ``(match loss, share of the CBCT's cells with anatomy whose best
    context cell lies within one cell, 16 mm at the default grid, of the truth)``.

    Samples: :class:`~monai_rigidreg.engine.RigidPairSampler`'s (``moving`` and ``context`` ``[1, x, y, z]``,
    ``rigid_params["params"]`` ``[6]`` mm/deg fixed -> moving about the grid centre)."""
    moving = torch.stack([b["moving"] for b in batch]).float()
    context = torch.stack([b["context"] for b in batch]).float()
    truth = params_to_matrix_torch(torch.stack([b["rigid_params"]["params"] for b in batch]).double())
    _, record = net._coarse(moving, context)
    loss = match_loss(record, truth)
    with torch.no_grad():
        cell_mm = float((net.cells_context[1] - net.cells_context[0]).norm())
        best = net.cells_context[record["logits"].argmax(-1)]  # [B, Nm, 3]: CT positions of the best matches
        to_ct = torch.linalg.inv(truth)
        want = record["cells"].double() @ to_ct[:, :3, :3].transpose(1, 2) + to_ct[:, None, :3, 3]
        near = ((best - want).norm(dim=-1) < cell_mm)[record["valid"]]
    return loss, float(near.float().mean()) if near.numel() else float("nan")


def pretrain_coarse(net: Any, samples: Callable[[MotionRange], Iterator[dict[str, Any]]],
                    schedule: Sequence[tuple[MotionRange, int]], batch_size: int = 4, lr: float = 1e-3,
                    log_every: int = 25, on_log: Callable[[dict[str, float]], None] | None = None,
                    on_step: Callable[[], None] | None = None) -> list[dict[str, float]]:
    """Train the coarse level of ``net`` (a ``ContextCorrelationNet``) alone, band after band.

    Args:
        net: the network; left in training mode; only :func:`coarse_parameters` change.
        samples: returns an endless sample iterator for a band (e.g. a
            :class:`~monai_rigidreg.engine.RigidPairSampler` with ``motions=(band,)``).
        schedule: ``(band, steps)`` pairs, in order.
        batch_size, lr: per step; Adam, one optimizer over the whole schedule.
        log_every: a record every this many steps (and at the end of each band).
        on_log: called with each record.
        on_step: called after each step (e.g. :meth:`~monai_rigidreg.engine.threads.ThreadTuner.tick`).

    Returns:
        The records: ``step``, ``samples``, ``band_mm``, ``band_deg``, ``match_nats`` and ``near_share`` (means
        over the steps since the last record), ``seconds``.
    """
    net.train()
    params = coarse_parameters(net)
    opt = torch.optim.Adam(params, lr=lr)
    history: list[dict[str, float]] = []
    step, t0 = 0, time.perf_counter()
    for band, steps in schedule:
        it = samples(band)
        losses: list[float] = []
        near: list[float] = []
        for k in range(int(steps)):
            loss, share = coarse_step(net, [next(it) for _ in range(batch_size)])
            opt.zero_grad()
            loss.backward()
            opt.step()
            step += 1
            if on_step is not None:
                on_step()
            losses.append(float(loss.detach()))
            near.append(share)
            if step % log_every == 0 or k == int(steps) - 1:
                record = {"step": step, "samples": step * batch_size, "band_mm": band.max_translation,
                          "band_deg": band.max_rotation, "match_nats": float(np.mean(losses)),
                          "near_share": float(np.nanmean(near)) if near else float("nan"),
                          "seconds": time.perf_counter() - t0}
                history.append(record)
                if on_log is not None:
                    on_log(record)
                losses, near = [], []
    return history
