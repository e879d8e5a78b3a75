"""The match loss of :class:`~monai_rigidreg.networks.ContextCorrelationNet`: every cell's match supervised.

The network's levels read each cell's match out of a softmax over candidate positions (every CT context cell at the
global level, integer shifts at the local levels); :func:`match_loss` is the cross-entropy of that softmax against
the true position of the match, as trilinear soft labels on the candidates' lattice. With the supervised point
distance of each level's estimate it trains the network (``RegistrationCriterion(w_match=...)``): thousands of
supervised matches per sample instead of six numbers.

>>> import torch
>>> from monai_rigidreg.core.geometry import params_to_matrix_torch
>>> ax = torch.arange(-1, 2, dtype=torch.float64) * 4.0
>>> shifts = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
>>> record = {"kind": "local", "cells": torch.zeros(1, 3, dtype=torch.float64), "shifts": shifts,
...           "start": torch.eye(4, dtype=torch.float64)[None],
...           "logits": 20.0 * (shifts == torch.tensor([4.0, 0, 0], dtype=torch.float64)).all(-1).float()[None, None]}
>>> truth = params_to_matrix_torch(torch.tensor([[4.0, 0, 0, 0, 0, 0]], dtype=torch.float64))
>>> float(match_loss(record, truth)) < 1e-3
True
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

__all__ = ["match_loss"]


def _trilinear_targets(pos: torch.Tensor, size: Sequence[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Continuous lattice coordinates ``[B, N, 3]`` -> the 8 corner indices (row-major over ``size``) ``[B, N, 8]``
    and their trilinear weights ``[B, N, 8]`` (0 for corners outside the lattice)."""
    base = torch.floor(pos)
    frac = pos - base
    idx, wts = [], []
    for corner in range(8):
        off = torch.tensor([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1], dtype=pos.dtype, device=pos.device)
        c = base + off
        w = torch.where(off.bool(), frac, 1 - frac).prod(-1)
        inside = torch.ones_like(w, dtype=torch.bool)
        for a in range(3):
            inside &= (c[..., a] >= 0) & (c[..., a] <= size[a] - 1)
        flat = ((c[..., 0].clamp(0, size[0] - 1) * size[1] + c[..., 1].clamp(0, size[1] - 1)) * size[2]
                + c[..., 2].clamp(0, size[2] - 1))
        idx.append(flat.long())
        wts.append(torch.where(inside, w, torch.zeros_like(w)))
    return torch.stack(idx, -1), torch.stack(wts, -1)


def match_loss(record: dict[str, Any], matrix_true: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Cross-entropy of one level's matches against the true positions (trilinear soft labels).

    Args:
        record: a match record of :meth:`ContextCorrelationNet.forward_levels` (``matches=True``).
        matrix_true: ``[B, 4, 4]`` true fixed -> moving transforms about the grid centre (mm).
        valid: optional ``[B, N]`` weights of the level's cells (default: the record's ``valid``, its cells with
            anatomy in both images).

    Global level: for every moving cell ``q`` the true CT position ``T^-1(q)`` on the context cell lattice; local
    level: for every CT cell ``x`` the position in the warped CBCT, ``S^-1(T(x))`` with ``S`` the estimate the CBCT
    was warped by, as a shift on the level's shift lattice. Cells whose truth lies outside the candidates, or whose
    soft label is mostly outside, carry no loss. Returns the weighted mean over cells (a scalar).
    """
    logits = record["logits"]
    m = matrix_true.to(torch.float64)
    if record["kind"] == "global":
        cells = record["cells"]  # moving cells [N, 3]
        inv = torch.linalg.inv(m)
        truth = cells @ inv[:, :3, :3].transpose(1, 2) + inv[:, None, :3, 3]  # [B, N, 3] CT positions
        cand = record["candidates"]
        lo = cand.min(0).values
        step = _lattice_step(cand)
        n_axis = [int(round(float(v))) + 1 for v in (cand.max(0).values - lo) / step]
        pos = (truth - lo) / step
    else:
        cells = record["cells"]  # fixed cells [N, 3] or [B, N, 3]
        start = record["start"].to(torch.float64)
        rel = torch.linalg.inv(start) @ m  # x -> S^-1 T x
        truth = cells @ rel[:, :3, :3].transpose(1, 2) + rel[:, None, :3, 3]
        shifts = record["shifts"]  # [K^3, 3] mm
        k = round(shifts.shape[0] ** (1 / 3))
        n_axis = [k, k, k]
        step = _lattice_step(shifts)
        pos = (truth - cells - shifts.min(0).values) / step
    idx, wts = _trilinear_targets(pos, n_axis)
    coverage = wts.sum(-1)  # 1 inside, < 1 near the border, 0 outside
    logp = torch.log_softmax(logits, dim=-1)
    nll = -(logp.gather(-1, idx) * wts.to(logp.dtype)).sum(-1) / coverage.to(logp.dtype).clamp_min(1e-6)
    w = (coverage > 0.5).to(nll.dtype)
    if valid is None:
        valid = record.get("valid")
    if valid is not None:
        w = w * valid.to(nll.dtype)
    return (nll * w).sum() / w.sum().clamp_min(1.0)


def _lattice_step(points: torch.Tensor) -> torch.Tensor:
    """Per-axis spacing of a regular lattice of points ``[N, 3]`` (the smallest positive coordinate difference)."""
    steps = []
    for a in range(3):
        u = torch.unique(points[:, a])
        steps.append((u[1:] - u[:-1]).min() if u.numel() > 1 else torch.ones((), dtype=points.dtype,
                                                                               device=points.device))
    return torch.stack(steps)
