"""Context correlation network: a wide CT context for the capture range, three learned levels down to 4 mm cells.

:class:`ContextCorrelationNet` keeps the explicit geometry of :class:`~monai_rigidreg.networks.CorrelationRigidNet`
(learned features, matches read out of cost volumes, a weighted closed-form rigid fit per level, composed coarse to
fine) and changes what limits it on real anatomy:

1. **Coarse level over a wide CT context.** The moving (CBCT) grid, average-pooled to 4 mm, and the fixed (CT)
   *context*, the CT on a grid of the same centre at 4 mm over twice the extent (256 mm for the 64^3 x 2 mm
   network grid), are encoded by their own small encoder to 16 mm cells. Every CBCT cell is matched against every CT
   context cell (cosine similarity, softmax, soft-argmax), so a 60 mm setup error still finds its anatomy inside
   the CT context where the 128 mm network grid alone holds only half of it. The weights are learned from the
   CBCT's features (times the match's peak), and the fit is made robust by two closed-form reweightings
   (Cauchy, ``robust_sigma`` cells).
2. **8 mm level, then 4 mm level.** The CBCT is warped by the estimate so far (one interpolation from the original
   volume), encoded by the shared encoder, and every CT cell is matched locally (``+-radius`` cells); the sub-cell
   match is read by a parabola per axis (weight-free, also in training, so the network is trained as it runs),
   weighted by a head on both images' features, fitted and composed. The 4 mm level's features add the 8 mm
   stage's features, up-sampled (a small feature pyramid). Each level runs ``passes`` times.

Training supervises every level's estimate (point distance) and, through :meth:`ContextCorrelationNet.
forward_levels` with ``matches=True``, every cell's match (cross-entropy against the true position, see
:func:`~monai_rigidreg.losses.match_loss`): thousands of supervised matches per sample instead of six numbers.

Frames and units as :class:`~monai_rigidreg.networks.CorrelationRigidNet`: the inputs share one axis-aligned network
grid (array axes LPS x, y, z) centred on the CBCT; the context grid has the same centre; the output
``(tx, ty, tz, rx, ry, rz)`` (mm, degrees) is the fixed -> moving transform about the grid centre.

>>> import torch
>>> net = ContextCorrelationNet(grid_size=(32, 32, 32), grid_spacing=(4.0, 4.0, 4.0))
>>> moving = torch.rand(1, 1, 32, 32, 32)
>>> net(torch.cat([moving, moving], 1)).shape
torch.Size([1, 6])
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from monai_rigidreg.core.geometry import Grid, matrix_to_params_torch
from monai_rigidreg.core.image_ops import masked_ncc
from monai_rigidreg.core.warp import warp_volume
from monai_rigidreg.networks.blocks import ResidualStage3d, pointwise_columns
from monai_rigidreg.networks.correlation_net import local_cost_volume, unit_channels, weighted_rigid_fit

__all__ = ["COARSE_STARTS", "ContextCorrelationNet", "robust_rigid_fit", "context_from_fixed", "subcell_shifts",
           "sparse_cost_volume"]


CONTENT_LEVEL = 0.1
"""Normalized intensity above which a voxel counts as anatomy for the match loss's cell weights (-700 HU with the
bundle's window of -1000..2000 HU)."""


def robust_rigid_fit(points_fixed: torch.Tensor, points_moving: torch.Tensor, weights: torch.Tensor,
                     sigma_mm: float, iterations: int = 2) -> torch.Tensor:
    """:func:`~monai_rigidreg.networks.weighted_rigid_fit` followed by ``iterations`` Cauchy reweightings.

    Each reweighting multiplies the weights by ``1 / (1 + (r / sigma_mm)^2)``, ``r`` the distance (mm) between a
    moving point and its fixed point mapped by the current fit, and fits again (closed form; differentiable).

    Returns:
        ``[B, 4, 4]`` float64 fixed -> moving matrices.
    """
    fit = weighted_rigid_fit(points_fixed, points_moving, weights)
    p = points_fixed.to(torch.float64)
    q = points_moving.to(torch.float64)
    for _ in range(int(iterations)):
        mapped = p @ fit[:, :3, :3].transpose(1, 2) + fit[:, None, :3, 3]
        r2 = ((mapped - q) ** 2).sum(-1)
        fit = weighted_rigid_fit(p, q, weights.to(torch.float64) / (1.0 + r2 / float(sigma_mm) ** 2))
    return fit


COARSE_STARTS = ("coarse", "identity", "both")
"""Where :class:`ContextCorrelationNet`'s local levels start at inference: the coarse level's estimate (as trained),
the identity, or both, per sample the one whose final estimate matches the images better (:func:`_warped_ncc`)."""


def _warped_ncc(moving: torch.Tensor, fixed: torch.Tensor, matrix: torch.Tensor, grid: Grid) -> torch.Tensor:
    """``[B]`` intensity NCC of ``moving`` warped by ``matrix`` (``[B, 4, 4]`` fixed -> moving) with ``fixed``, over
    the voxels that the warp samples inside ``moving``'s box (``[B, C, x, y, z]`` on ``grid``)."""
    inside = warp_volume(torch.ones_like(moving[:, :1]), matrix, grid, grid) > 0.999
    return masked_ncc(warp_volume(moving, matrix, grid, grid), fixed, inside.to(moving.dtype))


def context_from_fixed(fixed: torch.Tensor, factor: int = 2, context_size: Sequence[int] | None = None
                       ) -> torch.Tensor:
    """The CT context when only the network grid's CT is at hand: ``fixed`` average-pooled by ``factor`` and padded
    with 0 (air after HU normalization) to ``context_size`` (default: the network grid's size), same centre.

    ``[B, C, x, y, z]`` -> ``[B, C, *context_size]``.
    """
    pooled = F.avg_pool3d(fixed, factor)
    size = tuple(fixed.shape[2:]) if context_size is None else tuple(int(s) for s in context_size)
    pads: list[int] = []
    for have, want in zip(reversed(pooled.shape[2:]), reversed(size)):
        extra = want - have
        if extra < 0 or extra % 2:
            raise ValueError(f"context size {size} cannot hold the pooled grid {tuple(pooled.shape[2:])} centred")
        pads += [extra // 2, extra // 2]
    return F.pad(pooled, pads)


class _Encoder(nn.Module):
    """Residual stages (stride 2 unless ``strides`` says otherwise); returns every stage's output."""

    def __init__(self, in_channels: int, channels: Sequence[int], strides: Sequence[int], num_res_units: int,
                 norm: str | tuple) -> None:
        super().__init__()
        stages = []
        c_in = int(in_channels)
        for c, s in zip(channels, strides):
            stages.append(ResidualStage3d(c_in, int(c), stride=int(s), subunits=num_res_units, norm=norm))
            c_in = int(c)
        self.stages = nn.ModuleList(stages)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for stage in self.stages:
            x = stage(x)
            out.append(x)
        return out


def _weight_head(in_channels: int) -> nn.Sequential:
    head = nn.Sequential(nn.Conv3d(in_channels, 16, kernel_size=1), nn.PReLU(), nn.Conv3d(16, 1, kernel_size=1))
    nn.init.zeros_(head[-1].weight)
    nn.init.zeros_(head[-1].bias)
    return head


def _lattice(size: Sequence[int], grid: Grid, stride: float, offset: float) -> torch.Tensor:
    """``[N, 3]`` mm positions of cells ``n`` at grid index ``stride * n + offset`` (row-major over ``size``)."""
    axes = [torch.arange(int(s), dtype=torch.float64) * stride + offset for s in size]
    index = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    to_mm = torch.as_tensor(grid.index_to_physical(), dtype=torch.float64)
    return index @ to_mm[:3, :3].T + to_mm[:3, 3]


class ContextCorrelationNet(nn.Module):
    """Wide-context global matching + 8 mm and 4 mm local matching, each with a closed-form rigid fit.

    Args:
        grid_size: network grid in voxels (each axis divisible by 8).
        grid_spacing: network grid spacing, mm.
        in_channels: channels of each volume.
        channels: widths of the shared encoder's two stages (4 mm and 8 mm cells at 2 mm).
        coarse_channels: widths of the coarse encoder's stages on the 4 mm grids (two of stride 2, then stride 1).
        num_res_units: convolutions per residual stage.
        norm: norm layer (MONAI's names; instance norm copes with CBCT/CT intensity differences).
        feat_channels: matching feature widths of the (coarse, 8 mm, 4 mm) levels.
        radius: local search radius in cells of the (8 mm, 4 mm) levels.
        temperature: initial softmax temperature on cosine similarities (each level learns its own).
        passes: passes of the (8 mm, 4 mm) levels.
        context_factor: the context grid's spacing over the network grid's (the coarse level's grid).
        context_size: the context grid in voxels (default: ``grid_size``: twice the extent at ``context_factor`` 2).
        robust_iterations: Cauchy reweightings of each fit (``robust_sigma`` cells).
        robust_sigma: the Cauchy scale in cells of the level.
        select_cells: how many 4 mm cells are matched: those where both images have the most structure.
        train_autocast: in training mode only, run the encoders' convolutions in this lower precision
            (``"bfloat16"``: about 30 % less CPU time per step where oneDNN has bfloat16 kernels, measured with
            one thread on the training machine); their features are cast back to float32 before any matching, so the
            cost volumes, sub-cell readout and fits stay float32. Inference always runs in float32.
        coarse_units, coarse_norm: the coarse encoder's conv units per stage and norm (default: ``num_res_units``
            and ``norm``). One unit (a 60 mm receptive field, not 140 mm) and ``"NONE"`` make an untrained CBCT
            cell's features more like its context cell's (``benchmarks/ablation/bench_coarse_consistency.py``) but
            learn the match more slowly (``bench_coarse_learnability.py``): the defaults are kept in training.
        coarse_start: where the local levels start in evaluation mode (:data:`COARSE_STARTS`); training always
            starts them from the coarse level's estimate, which it supervises.
        coarse_passes: in evaluation mode, how often the coarse level runs: each further pass matches the CBCT
            resampled by the estimate so far against the context and composes its correction (training runs it
            once).

    Shapes:
        ``forward``: ``[B, 2 * C, x, y, z]`` (moving, fixed) or ``[B, 3 * C, ...]`` (moving, fixed, context: the
        context on ``context_size`` voxels, the same shape as the grid by default) -> ``[B, 6]``.
        ``forward_levels``: ``moving, fixed[, context]`` -> list of ``[B, 6]`` (after the coarse level and after
        every pass; the last is the output).
    """

    takes_context = True
    """:class:`~monai_rigidreg.networks.TwoStageRigidNet` passes a third block of input channels as the context."""

    def __init__(
        self,
        grid_size: Sequence[int] = (64, 64, 64),
        grid_spacing: Sequence[float] = (2.0, 2.0, 2.0),
        in_channels: int = 1,
        channels: Sequence[int] = (16, 32),
        coarse_channels: Sequence[int] = (16, 32, 32),
        num_res_units: int = 2,
        norm: str | tuple = "INSTANCE",
        feat_channels: Sequence[int] = (32, 32, 16),
        radius: Sequence[int] = (2, 1),
        temperature: float = 30.0,
        passes: Sequence[int] = (2, 1),
        context_factor: int = 2,
        context_size: Sequence[int] | None = None,
        robust_iterations: int = 2,
        robust_sigma: float = 1.0,
        select_cells: int = 4096,
        train_autocast: str | None = None,
        coarse_start: str = "coarse",
        coarse_units: int | None = None,
        coarse_norm: str | tuple | None = None,
        coarse_passes: int = 1,
    ) -> None:
        super().__init__()
        if coarse_start not in COARSE_STARTS:
            raise ValueError(f"coarse_start must be one of {COARSE_STARTS}, got {coarse_start!r}")
        self.coarse_start = coarse_start
        self.in_channels = int(in_channels)
        self.grid_size = tuple(int(s) for s in grid_size)
        self.grid_spacing = tuple(float(s) for s in grid_spacing)
        if any(s % 8 for s in self.grid_size):
            raise ValueError(f"grid_size {self.grid_size} must be divisible by 8")
        if len(channels) != 2 or len(coarse_channels) != 3 or len(feat_channels) != 3 or len(radius) != 2:
            raise ValueError("channels (2), coarse_channels (3), feat_channels (3) and radius (2) per level")
        self.context_factor = int(context_factor)
        self.context_size = self.grid_size if context_size is None else tuple(int(s) for s in context_size)
        if any(s % 4 for s in self.context_size):
            raise ValueError(f"context_size {self.context_size} must be divisible by 4")
        self.passes = tuple(int(p) for p in passes)
        self.coarse_passes = int(coarse_passes)
        if self.coarse_passes < 1:
            raise ValueError(f"coarse_passes must be at least 1, got {coarse_passes}")
        self.radius = tuple(int(r) for r in radius)
        self.robust_iterations = int(robust_iterations)
        self.robust_sigma = float(robust_sigma)
        self.select_cells = int(select_cells)
        if train_autocast not in (None, "bfloat16", "float16"):
            raise ValueError(f"train_autocast must be None, 'bfloat16' or 'float16', got {train_autocast!r}")
        self.train_autocast = train_autocast
        c1, c2 = (int(c) for c in channels)
        self.encoder = _Encoder(self.in_channels, (c1, c2), (2, 2), num_res_units, norm)
        self.coarse_encoder = _Encoder(self.in_channels, coarse_channels, (2, 2, 1),
                                       num_res_units if coarse_units is None else int(coarse_units),
                                       norm if coarse_norm is None else coarse_norm)
        fc, f8, f4 = (int(f) for f in feat_channels)
        cc = int(coarse_channels[-1])
        self.coarse_project = nn.Conv3d(cc, fc, 1)
        self.coarse_weight = _weight_head(cc)
        self.project8 = nn.Conv3d(c2, f8, 1)
        self.weight8 = _weight_head(2 * c2)
        self.lateral4 = nn.Conv3d(c1, f4, 1)
        self.top4 = nn.Conv3d(c2, f4, 1)
        self.weight4 = _weight_head(2 * f4)
        # one softmax temperature per level: the levels choose among 4096, 125 and 27 candidates
        self.log_temperature = nn.Parameter(torch.full((3,), float(temperature)).log())
        self.grid = Grid.centered(self.grid_size, self.grid_spacing)
        self.context_grid = Grid.centered(self.context_size, [s * self.context_factor for s in self.grid_spacing])
        f = self.context_factor
        cells_moving = [s // (4 * f) for s in self.grid_size]
        # pooled voxel j covers grid voxels f*j .. f*j+f-1 (centre f*j + (f-1)/2); the coarse cells sit on every
        # fourth pooled voxel (two stride-2 stages)
        self.register_buffer("cells_coarse_moving", _lattice(cells_moving, self.grid, 4 * f, (f - 1) / 2),
                             persistent=False)
        self.register_buffer("cells_context", _lattice([s // 4 for s in self.context_size], self.context_grid, 4, 0),
                             persistent=False)
        self.register_buffer("cells8", _lattice([s // 4 for s in self.grid_size], self.grid, 4, 0), persistent=False)
        self.register_buffer("cells4", _lattice([s // 2 for s in self.grid_size], self.grid, 2, 0), persistent=False)
        for name, r in (("shifts8", self.radius[0]), ("shifts4", self.radius[1])):
            ax = torch.arange(-r, r + 1, dtype=torch.float64)
            self.register_buffer(name, torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3),
                                 persistent=False)

    # ---------------------------------------------------------------------------------------------------------
    def _split(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        c = self.in_channels
        if image.shape[1] not in (2 * c, 3 * c):
            raise ValueError(f"expected {2 * c} (moving, fixed) or {3 * c} (+ context) channels, got {image.shape[1]}")
        context = image[:, 2 * c:] if image.shape[1] == 3 * c else None
        return image[:, :c], image[:, c:2 * c], context

    def _encode(self, encoder: nn.Module, x: torch.Tensor) -> list[torch.Tensor]:
        """``encoder(x)`` (in the training autocast precision where set), every output as float32."""
        if self.training and self.train_autocast is not None:
            with torch.autocast(x.device.type, dtype=getattr(torch, self.train_autocast)):
                feats = encoder(x)
            return [f.float() for f in feats]
        return encoder(x)

    def _features4(self, feats: list[torch.Tensor]) -> torch.Tensor:
        top = F.interpolate(self.top4(feats[1]), size=feats[0].shape[2:], mode="trilinear", align_corners=False)
        return self.lateral4(feats[0]) + top

    def _coarse(self, moving: torch.Tensor, context: torch.Tensor) -> tuple[torch.Tensor, dict[str, Any]]:
        b = moving.shape[0]
        pooled = F.avg_pool3d(moving, self.context_factor)
        fm = self._encode(self.coarse_encoder, pooled)[-1]
        fc = self._encode(self.coarse_encoder, context)[-1]
        pm = unit_channels(self.coarse_project(fm).flatten(2))  # [B, C, Nm]
        pc = unit_channels(self.coarse_project(fc).flatten(2))  # [B, C, Nc]
        logits = torch.bmm(pm.transpose(1, 2), pc) * self.log_temperature[0].exp()  # [B, Nm, Nc]
        prob = torch.softmax(logits, dim=-1)
        matched = (prob @ self.cells_context.to(prob.dtype)).to(torch.float64)  # [B, Nm, 3] CT positions
        weight = torch.sigmoid(self.coarse_weight(fm)).flatten(1) * prob.max(-1).values
        cells = self.cells_coarse_moving.unsqueeze(0).expand(b, -1, -1)
        sigma = self.robust_sigma * 4 * self.context_factor * min(self.grid_spacing)
        fit = robust_rigid_fit(matched, cells, weight, sigma, self.robust_iterations)
        valid = (F.avg_pool3d((pooled > CONTENT_LEVEL).to(pooled.dtype), 4).flatten(1) > 0.5).detach()
        record = {"kind": "global", "logits": logits, "cells": self.cells_coarse_moving,
                  "candidates": self.cells_context, "weight": weight, "valid": valid}
        return fit, record

    def _select(self, fixed: torch.Tensor, warped: torch.Tensor) -> torch.Tensor:
        """``[B, N]`` flat indices of the 4 mm cells where both images have the most structure (weight-free: the
        smaller of the two images' mean squared gradient over the cell; the same rule in training and inference)."""
        def energy(img: torch.Tensor) -> torch.Tensor:
            gx = F.pad(img[:, :, 1:] - img[:, :, :-1], (0, 0, 0, 0, 0, 1))
            gy = F.pad(img[:, :, :, 1:] - img[:, :, :, :-1], (0, 0, 0, 1))
            gz = F.pad(img[..., 1:] - img[..., :-1], (0, 1))
            return F.avg_pool3d(gx * gx + gy * gy + gz * gz, 2).sum(1).flatten(1)
        score = torch.minimum(energy(fixed), energy(warped))
        n = min(self.select_cells, score.shape[1])
        return score.topk(n, dim=1, sorted=False).indices

    def _local(self, level: int, fm_feats: list[torch.Tensor], ff: torch.Tensor, total: torch.Tensor,
               fixed_weight: torch.Tensor | None, fixed: torch.Tensor, warped: torch.Tensor
               ) -> tuple[torch.Tensor, dict[str, Any]]:
        """One pass of a local level: ``ff`` (the fixed image's features at that level) has unit norm along C."""
        b = warped.shape[0]
        scale = self.log_temperature[1 if level == 8 else 2].exp()
        if level == 8:
            radius, stride, head = self.radius[0], 4, self.weight8
            fm = unit_channels(self.project8(fm_feats[1]))
            cost = local_cost_volume(fm, ff, radius, unit=True).flatten(2).transpose(1, 2)  # [B, N, K^3]
            cells = self.cells8.unsqueeze(0).expand(b, -1, -1)
            both = torch.cat([ff, fm], 1)
            weight = torch.sigmoid(head(both)).flatten(1)
            valid = torch.minimum(F.avg_pool3d((fixed > CONTENT_LEVEL).to(fixed.dtype), stride),
                                  F.avg_pool3d((warped > CONTENT_LEVEL).to(warped.dtype), stride)).flatten(1) > 0.5
            shifts = self.shifts8
        else:
            radius, stride, head = self.radius[1], 2, self.weight4
            fm = unit_channels(self._features4(fm_feats))
            index = self._select(fixed, warped)  # [B, N]
            cost = sparse_cost_volume(fm, ff, index, radius, unit=True)
            cells = self.cells4[index]  # [B, N, 3]
            pick = index[:, None].expand(b, ff.shape[1], -1)
            both = torch.cat([ff.flatten(2).gather(2, pick), fm.flatten(2).gather(2, pick)], 1)
            weight = torch.sigmoid(pointwise_columns(head, both)).flatten(1)
            valid = torch.ones_like(weight, dtype=torch.bool)
            shifts = self.shifts4
        step = torch.tensor([stride * s for s in self.grid_spacing], dtype=torch.float64, device=warped.device)
        logits = cost * scale
        prob = torch.softmax(logits, dim=-1)
        matched = cells + subcell_shifts(cost, radius) * step
        weight = weight * prob.max(-1).values
        if fixed_weight is not None:
            share = F.avg_pool3d(fixed_weight.to(weight.dtype), stride).flatten(1)
            weight = weight * (share if level == 8 else share.gather(1, index))
        sigma = self.robust_sigma * stride * min(self.grid_spacing)
        correction = robust_rigid_fit(cells, matched, weight, sigma, self.robust_iterations)
        record = {"kind": "local", "logits": logits, "cells": cells, "shifts": shifts * step, "weight": weight,
                  "start": total.detach(), "valid": valid.detach()}
        return correction, record

    # ---------------------------------------------------------------------------------------------------------
    def forward_levels(self, moving: torch.Tensor, fixed: torch.Tensor, context: torch.Tensor | None = None,
                       fixed_weight: torch.Tensor | None = None, matches: bool = False) -> Any:
        """Estimates ``[B, 6]`` after the coarse level and after each pass (mm / degrees about the grid centre).

        Args:
            moving, fixed: ``[B, C, *grid_size]`` on the network grid.
            context: ``[B, C, *context_size]``, the fixed image on the context grid (same centre,
                ``context_factor`` times the spacing); ``None``: :func:`context_from_fixed`.
            fixed_weight: optional ``[B, 1, *grid_size]`` weights in [0, 1] on the fixed grid (a match region, the
                body without the couch): the local levels' cell weights are multiplied by their mean.
            matches: also return each level's match record (for :func:`~monai_rigidreg.losses.match_loss`).

        Returns:
            The list of estimates, or ``(estimates, records)`` with ``matches=True``.
        """
        if moving.shape != fixed.shape:
            raise ValueError(f"moving {tuple(moving.shape)} and fixed {tuple(fixed.shape)} must have the same shape")
        if tuple(moving.shape[2:]) != self.grid_size:
            raise ValueError(f"inputs {tuple(moving.shape[2:])} are not on the network grid {self.grid_size}")
        if context is None:
            context = context_from_fixed(fixed, self.context_factor, self.context_size)
        if tuple(context.shape[2:]) != self.context_size:
            raise ValueError(f"context {tuple(context.shape[2:])} is not on the context grid {self.context_size}")
        total, record = self._coarse(moving, context)
        for _ in range(0 if self.training else self.coarse_passes - 1):
            warped = warp_volume(moving, total.detach(), self.grid, self.grid)
            total = total @ self._coarse(warped, context)[0]
        levels = [matrix_to_params_torch(total).to(moving.dtype)]
        records = [record]
        start = "coarse" if self.training else self.coarse_start
        b = moving.shape[0]
        if start == "identity":
            total = torch.eye(4, dtype=total.dtype, device=total.device).expand_as(total).clone()
        elif start == "both":  # both starts in one batch: [coarse estimates; identities]
            total = torch.cat([total, torch.eye(4, dtype=total.dtype, device=total.device).expand_as(total)])
            moving, fixed = moving.repeat(2, 1, 1, 1, 1), fixed.repeat(2, 1, 1, 1, 1)
            fixed_weight = None if fixed_weight is None else fixed_weight.repeat(2, 1, 1, 1, 1)
        ff_feats = self._encode(self.encoder, fixed)
        ff = {8: unit_channels(self.project8(ff_feats[1])), 4: unit_channels(self._features4(ff_feats))}
        finals = []
        for level, count in ((8, self.passes[0]), (4, self.passes[1])):
            for _ in range(count):
                warped = warp_volume(moving, total.detach(), self.grid, self.grid)
                correction, record = self._local(level, self._encode(self.encoder, warped), ff[level], total,
                                                 fixed_weight, fixed, warped)
                total = total @ correction
                finals.append(matrix_to_params_torch(total).to(moving.dtype))
                records.append(record)
        if start == "both":
            # per sample, the start whose final estimate matches the images better (intensity NCC inside the warped
            # CBCT's box; weight-free): the coarse level misleads the local levels on moderate motions that they
            # capture from the identity (benchmarks/ablation/bench_levels_by_motion.py)
            score = _warped_ncc(moving, fixed, total, self.grid)
            pick = (score[b:] > score[:b]).to(moving.dtype)[:, None]
            finals = [p[:b] * (1 - pick) + p[b:] * pick for p in finals]
        levels += finals
        return (levels, records) if matches else levels

    def forward_pair(self, moving: torch.Tensor, fixed: torch.Tensor, context: torch.Tensor | None = None,
                     fixed_weight: torch.Tensor | None = None) -> torch.Tensor:
        """The estimate ``[B, 6]`` (mm, degrees; fixed -> moving about the grid centre)."""
        return self.forward_levels(moving, fixed, context, fixed_weight)[-1]

    def forward(self, image: torch.Tensor, fixed_weight: torch.Tensor | None = None) -> torch.Tensor:
        """``[B, 2 * C or 3 * C, x, y, z]`` (moving, fixed[, context]) -> ``[B, 6]``."""
        moving, fixed, context = self._split(image)
        return self.forward_pair(moving, fixed, context, fixed_weight)


def subcell_shifts(cost: torch.Tensor, radius: int) -> torch.Tensor:
    """The best integer shift of each cell refined by a parabola per axis.

    ``cost``: ``[B, N, K**3]`` similarities of ``N`` cells at the integer shifts within ``+-radius`` (row-major over
    ``(dx, dy, dz)``, ``K = 2 * radius + 1``) -> ``[B, N, 3]`` float64 shifts in cells: the integer argmax plus an
    offset in ``[-0.5, 0.5]`` per axis, the vertex of the parabola through three neighbouring costs along the axis
    (0 where they are not concave). Inside the window the three are centred on the argmax; on its border they are
    the argmax and its two inner neighbours (the parabola is extrapolated by up to half a cell), so that a match
    half a cell from the border is read as such, not snapped onto the border: with ``radius`` 1 a residual of half a
    cell would otherwise come out as a whole cell in every cell whose argmax falls on the border
    (``tests/networks/test_context_net.py``). Differentiable through the gathered costs; the argmax is taken in the
    cost's own dtype.
    """
    k = 2 * int(radius) + 1
    if k < 3:
        raise ValueError(f"radius must be >= 1, got {radius}")
    best = cost.argmax(-1, keepdim=True)  # [B, N, 1]
    index = torch.cat([best // (k * k), (best // k) % k, best % k], -1)  # [B, N, 3]
    shifts = []
    for axis, stride in enumerate((k * k, k, 1)):
        i = index[..., axis:axis + 1]
        centre = i.clamp(1, k - 2)  # the middle of the three costs
        mid = best + stride * (centre - i)
        lo = cost.gather(-1, mid - stride).to(torch.float64)
        c0 = cost.gather(-1, mid).to(torch.float64)
        hi = cost.gather(-1, mid + stride).to(torch.float64)
        den = lo - 2.0 * c0 + hi
        concave = den < -1e-9
        vertex = torch.where(concave, 0.5 * (lo - hi) / torch.where(concave, den, torch.ones_like(den)),
                             torch.zeros_like(den))  # relative to the middle
        offset = (vertex + (centre - i).to(torch.float64)).clamp(-0.5, 0.5)  # relative to the argmax
        offset = torch.where(concave, offset, torch.zeros_like(offset))
        shifts.append(i.to(torch.float64) - radius + offset)
    return torch.cat(shifts, -1)


def sparse_cost_volume(feat_moving: torch.Tensor, feat_fixed: torch.Tensor, index: torch.Tensor, radius: int,
                       unit: bool = False) -> torch.Tensor:
    """Cosine similarity of the selected fixed cells with the moving cells at integer shifts within ``+-radius``.

    Args:
        feat_moving, feat_fixed: ``[B, C, X, Y, Z]`` on the same cell grid (unit norm along C is applied here).
        index: ``[B, N]`` flat (row-major) indices of the fixed cells.
        radius: search radius in cells.
        unit: the maps have unit norm along C already (``unit_channels``): used as they are.

    Returns:
        ``[B, N, K**3]`` (row-major over ``(dx, dy, dz)``; shifts leaving the moving map give 0): what
        :func:`~monai_rigidreg.networks.correlation_net.local_cost_volume` has at those cells, for the cost of ``N``
        cells rather than of the whole grid.
    """
    fm = feat_moving if unit else unit_channels(feat_moving)
    ff = feat_fixed if unit else unit_channels(feat_fixed)
    b, c, x, y, z = ff.shape
    r = int(radius)
    k = 2 * r + 1
    padded = F.pad(fm, (r, r, r, r, r, r)).flatten(2)  # [B, C, X' Y' Z']
    yp, zp = y + 2 * r, z + 2 * r
    ix, iy, iz = index // (y * z), (index // z) % y, index % z
    ax = torch.arange(k, device=index.device)
    offsets = ((ax[:, None, None] * yp + ax[None, :, None]) * zp + ax[None, None, :]).reshape(-1)  # [K^3]
    start = (ix * yp + iy) * zp + iz  # [B, N] window corner in padded coordinates
    windows = (start[..., None] + offsets).reshape(b, -1)  # [B, N K^3]
    win = padded.gather(2, windows[:, None].expand(b, c, -1)).view(b, c, -1, k ** 3)
    sel = ff.flatten(2).gather(2, index[:, None].expand(b, c, -1))  # [B, C, N]
    # a product and a channel sum: an einsum ran as N tiny matrix products, 3x the time (bench_network_paths.py)
    return (sel.unsqueeze(-1) * win).sum(1)
