"""Correlation network with a closed-form rigid fit: learned features, local cost volumes, weighted Procrustes.

Where :class:`~monai_rigidreg.networks.DualEncoderRigidNet` asks an MLP to turn a flattened feature map into six
numbers, this network keeps the geometry explicit, so it has far less to learn:

1. one shared 3D CNN encoder (residual stages with MONAI ``ResidualUnit``'s layout,
   :class:`~monai_rigidreg.networks.blocks.ResidualStage3d`) maps the moving (CBCT) and the fixed (CT) volume to
   feature maps at 1/4 and 1/8 of the network grid;
2. for every fixed cell, a cost volume (cosine similarity with the moving features: every moving cell at the
   coarse level, integer cell shifts within ``+-radius`` at the fine level) and a soft-argmax give its matched
   position in mm, and a learned per-cell weight (from the fixed features, times the sharpness of the match) says
   how much to trust it;
3. the weighted rigid fit of the displacements (Horn's closed-form quaternion solution of the Procrustes problem)
   gives the transform;
4. coarse to fine: the estimate of the 1/8 level warps the *original* moving volume (one interpolation), the moving
   volume is encoded again and the 1/4 level estimates a correction (``fine_passes`` times), composed as
   ``T = T_coarse o C``.

Every step is differentiable; the supervised loss on the final (and each level's) parameters trains the features
and the weights. The network is tied to the grid spacing it is built for (``grid_spacing``): the cell positions of
the rigid fit are in mm.

Frames and units: both inputs are on the same axis-aligned network grid (array axes = LPS x, y, z), the output
``(tx, ty, tz, rx, ry, rz)`` (mm, degrees) is the fixed -> moving transform ``T(x) = R (x - c) + c + t`` about the
grid centre ``c`` (see :mod:`monai_rigidreg.core.geometry`), exactly as :class:`DualEncoderRigidNet`'s.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from monai_rigidreg.core.geometry import Grid, matrix_to_params_torch
from monai_rigidreg.core.warp import warp_volume
from monai_rigidreg.networks.blocks import ResidualStage3d

__all__ = ["CorrelationRigidNet", "local_cost_volume", "parabola_shifts", "unit_channels", "weighted_rigid_fit",
           "SUBCELL_MODES"]


def unit_channels(x: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """``x`` scaled to unit norm along its channel axis (dim 1): ``torch.nn.functional.normalize(x, dim=1)``'s value
    and gradient (the norm clamped below at ``eps``: a zero vector stays zero) as a sum of squares over dim 1, which
    on a contiguous ``[B, C, ...]`` map adds whole channel planes; ``F.normalize``'s vector norm strides across them
    and took 10x the forward time on 2 cores (``[4, 16, 32^3]``: 18 ms instead of 1.8 ms;
    ``benchmarks/speed/bench_network_paths.py``).

    Example:
        >>> unit_channels(torch.tensor([[[3.0], [4.0]]]))[0, :, 0].tolist()
        [0.6000000238418579, 0.800000011920929]
    """
    return x / x.square().sum(1, keepdim=True).clamp_min(eps * eps).sqrt()


def local_cost_volume(feat_moving: torch.Tensor, feat_fixed: torch.Tensor, radius: int, unit: bool = False
                      ) -> torch.Tensor:
    """Cosine similarity of each fixed cell with the moving cells at integer shifts within ``+-radius``.

    Args:
        feat_moving, feat_fixed: ``[B, C, X, Y, Z]`` feature maps on the same cell grid (unit norm along C is
            applied here).
        radius: search radius in cells (``K = 2 * radius + 1`` shifts per axis).
        unit: the maps are unit vectors along C already (:func:`unit_channels`): used as they are.

    Returns:
        ``[B, K**3, X, Y, Z]``: entry ``(dx, dy, dz)`` (row-major over ``-radius..radius``) is the similarity of
        fixed cell ``n`` with moving cell ``n + d``; shifts that leave the moving map give 0.

    Example:
        >>> fm = torch.randn(1, 8, 6, 6, 6)
        >>> cost = local_cost_volume(fm, fm, 1)  # [1, 27, 6, 6, 6]; shift (0, 0, 0) is entry 13
        >>> bool(torch.allclose(cost[:, 13], torch.ones(1, 6, 6, 6), atol=1e-5))
        True
    """
    fm = feat_moving if unit else unit_channels(feat_moving)
    ff = feat_fixed if unit else unit_channels(feat_fixed)
    if torch.is_grad_enabled() and (fm.requires_grad or ff.requires_grad):
        return _LocalCorrelation.apply(fm, ff, int(radius))
    return _correlate(fm, ff, int(radius))


def _correlate(fm: torch.Tensor, ff: torch.Tensor, r: int) -> torch.Tensor:
    """:func:`local_cost_volume` of unit-norm features, forward only, on channel-last copies: per ``(dx, dy)`` one
    product of the fixed map with the ``K`` windows along z (a view) and one sum over the contiguous channels.
    On 2 cores under the package's passive thread policy 2-3x faster than an einsum over unfolded windows at batch 1
    and 3x at batch 3-4 (the einsum ran as ``X Y Z`` products of ``[1, C] x [C, K]``); one product per shift, 125
    of them, was no faster than the einsum at batch 1 (every operation wakes the worker threads)
    (``benchmarks/speed/bench_network_paths.py``'s cost-volume rows)."""
    return _correlate_last(*_channel_last(fm, ff, r), r)


def _channel_last(fm: torch.Tensor, ff: torch.Tensor, r: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The channel-last copies :func:`_correlate_last` and :meth:`_LocalCorrelation.backward` work on: the fixed map
    ``[B, X, Y, Z, C]`` and the moving map padded by ``r`` cells with zeros, ``[B, X+2r, Y+2r, Z+2r, C]``."""
    fixed_last = ff.permute(0, 2, 3, 4, 1).contiguous()
    padded_last = F.pad(fm, (r, r, r, r, r, r)).permute(0, 2, 3, 4, 1).contiguous()
    return fixed_last, padded_last


def _correlate_last(fixed_last: torch.Tensor, padded_last: torch.Tensor, r: int) -> torch.Tensor:
    """:func:`_correlate` on :func:`_channel_last`'s copies; ``[B, K**3, X, Y, Z]``."""
    k = 2 * r + 1
    b, x, y, z, _ = fixed_last.shape
    fixed_last = fixed_last.unsqueeze(4)  # [B, X, Y, Z, 1, C]
    out = fixed_last.new_empty((b, k, k, k, x, y, z))
    for dx in range(k):
        for dy in range(k):
            # the z windows of the block: [B, X, Y, K, C, Z] -> [B, X, Y, Z, K, C]
            windows = padded_last[:, dx:dx + x, dy:dy + y].unfold(3, z, 1).permute(0, 1, 2, 5, 3, 4)
            out[:, dx, dy] = (fixed_last * windows).sum(-1).permute(0, 4, 1, 2, 3)
    return out.view(b, k ** 3, x, y, z)


class _LocalCorrelation(torch.autograd.Function):
    """:func:`_correlate` with a backward of the same form: each shift's two gradients are one in-place
    multiply-add over the channel-last maps. Autograd's backward of the earlier einsum over unfolded windows ran as
    ``B X Y Z`` matrix products of shape ``[C, 1] x [1, K]`` and an ``unfold_backward`` per window block, about
    1.3 of a context-network training step's 4.1 profiled seconds (batch 4, 16^3 cells, 32 channels, radius 2,
    two passes; 2 cores)."""

    @staticmethod
    def forward(ctx, fm: torch.Tensor, ff: torch.Tensor, r: int) -> torch.Tensor:  # type: ignore[override]
        fixed_last, padded_last = _channel_last(fm, ff, r)
        ctx.save_for_backward(fixed_last, padded_last)
        ctx.radius = r
        return _correlate_last(fixed_last, padded_last, r)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor | None, None]:  # type: ignore[override]
        fixed_last, padded_last = ctx.saved_tensors
        r = ctx.radius
        k = 2 * r + 1
        x, y, z = fixed_last.shape[1:4]
        need_fm, need_ff = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        grad_fixed = torch.zeros_like(fixed_last) if need_ff else None
        grad_padded = torch.zeros_like(padded_last) if need_fm else None
        # cost[:, i] = sum_c ff * padded[window i]: each shift's gradient reaches ff through that window and the
        # window through ff
        i = 0
        for dx in range(k):
            for dy in range(k):
                for dz in range(k):
                    g = grad[:, i].unsqueeze(-1)  # [B, X, Y, Z, 1]
                    if grad_fixed is not None:
                        grad_fixed.addcmul_(g, padded_last[:, dx:dx + x, dy:dy + y, dz:dz + z])
                    if grad_padded is not None:
                        grad_padded[:, dx:dx + x, dy:dy + y, dz:dz + z].addcmul_(g, fixed_last)
                    i += 1
        grad_fm = None if grad_padded is None else grad_padded[:, r:r + x, r:r + y, r:r + z].permute(0, 4, 1, 2, 3)
        grad_ff = None if grad_fixed is None else grad_fixed.permute(0, 4, 1, 2, 3)
        return grad_fm, grad_ff, None


def weighted_rigid_fit(points_fixed: torch.Tensor, points_moving: torch.Tensor, weights: torch.Tensor,
                       prior: float = 1e-3) -> torch.Tensor:
    """Closed-form weighted least-squares rigid transform (Horn's quaternion method), ``moving ~ R fixed + t``.

    Args:
        points_fixed, points_moving: ``[B, N, 3]`` corresponding points (mm, any common frame).
        weights: ``[B, N]`` non-negative weights.
        prior: relative weight of a pull towards the identity rotation (keeps the fit defined when the weighted
            points are nearly collinear); relative to the weighted spread of the points.

    Returns:
        ``[B, 4, 4]`` float64 matrices mapping ``points_fixed`` to ``points_moving``.

    The maximal eigenvector of Horn's symmetric 4x4 matrix is the rotation quaternion; its eigenvalue is separated
    from the others whenever the fit is determined, which keeps ``eigh``'s gradient finite (an SVD of the 3x3 cross-
    covariance is not: its singular values coincide for the isotropic clouds met here).
    """
    p = points_fixed.to(torch.float64)
    q = points_moving.to(torch.float64)
    w = weights.to(torch.float64).clamp_min(0) + 1e-12
    wsum = w.sum(1, keepdim=True)
    wn = (w / wsum).unsqueeze(-1)  # [B, N, 1]
    pc = (wn * p).sum(1)
    qc = (wn * q).sum(1)
    p0 = p - pc.unsqueeze(1)
    q0 = q - qc.unsqueeze(1)
    h = torch.einsum("bni,bnj->bij", wn * p0, q0)  # [B, 3, 3] cross-covariance
    spread = (wn * p0 * p0).sum((1, 2))
    h = h + prior * spread.view(-1, 1, 1) * torch.eye(3, dtype=h.dtype, device=h.device)
    sxx, sxy, sxz = h[:, 0, 0], h[:, 0, 1], h[:, 0, 2]
    syx, syy, syz = h[:, 1, 0], h[:, 1, 1], h[:, 1, 2]
    szx, szy, szz = h[:, 2, 0], h[:, 2, 1], h[:, 2, 2]
    n = torch.stack([
        torch.stack([sxx + syy + szz, syz - szy, szx - sxz, sxy - syx], -1),
        torch.stack([syz - szy, sxx - syy - szz, sxy + syx, szx + sxz], -1),
        torch.stack([szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy], -1),
        torch.stack([sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz], -1),
    ], -2)
    _, vecs = torch.linalg.eigh(n)
    quat = vecs[..., -1]  # [B, 4] (w, x, y, z), unit norm
    qw, qx, qy, qz = quat.unbind(-1)
    r = torch.stack([
        torch.stack([qw * qw + qx * qx - qy * qy - qz * qz, 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)], -1),
        torch.stack([2 * (qx * qy + qw * qz), qw * qw - qx * qx + qy * qy - qz * qz, 2 * (qy * qz - qw * qx)], -1),
        torch.stack([2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), qw * qw - qx * qx - qy * qy + qz * qz], -1),
    ], -2)
    t = qc - (r @ pc.unsqueeze(-1)).squeeze(-1)
    b = p.shape[0]
    out = torch.zeros(b, 4, 4, dtype=torch.float64, device=p.device)
    out[:, :3, :3] = r
    out[:, :3, 3] = t
    out[:, 3, 3] = 1.0
    return out


SUBCELL_MODES = ("softargmax", "parabola")
"""How a local level reads its match out of the cost volume: ``softargmax`` (the softmax-weighted mean shift,
differentiable everywhere; what training uses) or ``parabola`` (the best integer shift plus, per axis, the vertex of
the parabola through the costs at that shift and its two neighbours; weight-free, measured on held-out real CTs in
the bundle docs: a sharp softmax snaps sub-cell residuals to whole cells)."""


def parabola_shifts(cost: torch.Tensor, radius: int) -> torch.Tensor:
    """Sub-cell match of a local cost volume: the best integer shift refined by a parabola per axis.

    Args:
        cost: ``[B, K**3, X, Y, Z]`` (:func:`local_cost_volume`; ``K = 2 * radius + 1``, row-major over
            ``(dx, dy, dz)``).
        radius: the search radius in cells.

    Returns:
        ``[B, N, 3]`` float64 shifts in cells (N = X*Y*Z): the argmax shift plus an offset in [-0.5, 0.5] per axis
        (0 where the argmax is on the border of the search window or the costs are not concave there).
    """
    k = 2 * int(radius) + 1
    b = cost.shape[0]
    c = cost.flatten(2).transpose(1, 2).reshape(b, -1, k, k, k).to(torch.float64)  # [B, N, kx, ky, kz]
    best = c.flatten(2).argmax(-1)  # [B, N]
    index = torch.stack([best // (k * k), (best // k) % k, best % k], -1)  # [B, N, 3]
    flat = c.flatten(2)
    peak = flat.gather(2, best.unsqueeze(-1)).squeeze(-1)
    strides = torch.tensor([k * k, k, 1], device=cost.device)
    shifts = []
    for axis in range(3):
        i = index[..., axis]
        inner = (i > 0) & (i < k - 1)
        lo = (best - strides[axis] * inner.long()).unsqueeze(-1)  # the neighbours (the peak itself on the border)
        hi = (best + strides[axis] * inner.long()).unsqueeze(-1)
        cm, cp = flat.gather(2, lo).squeeze(-1), flat.gather(2, hi).squeeze(-1)
        den = cm - 2.0 * peak + cp
        concave = inner & (den < -1e-9)
        offset = torch.where(concave, 0.5 * (cm - cp) / torch.where(concave, den, torch.ones_like(den)),
                             torch.zeros_like(den)).clamp(-0.5, 0.5)
        shifts.append(i.to(torch.float64) - radius + offset)
    return torch.stack(shifts, -1)


class _MatchLevel(nn.Module):
    """One level: feature projection, cost volume, soft-argmax (or parabola) match, per-cell weight.

    ``radius=None``: global matching (every fixed cell against every moving cell; for the coarse level, whose cells
    are few); otherwise the local cost volume within ``+-radius`` cells, read out by ``subcell``
    (:data:`SUBCELL_MODES`).
    """

    def __init__(self, in_channels: int, feat_channels: int, radius: int | None, temperature: float,
                 subcell: str = "softargmax") -> None:
        super().__init__()
        if subcell not in SUBCELL_MODES:
            raise ValueError(f"subcell must be one of {SUBCELL_MODES}, got {subcell!r}")
        self.subcell = subcell
        self.radius = None if radius is None else int(radius)
        self.project = nn.Conv3d(in_channels, feat_channels, kernel_size=1)
        self.weight_head = nn.Sequential(nn.Conv3d(in_channels, 16, kernel_size=1), nn.PReLU(),
                                         nn.Conv3d(16, 1, kernel_size=1))
        nn.init.zeros_(self.weight_head[-1].weight)
        nn.init.zeros_(self.weight_head[-1].bias)
        self.log_temperature = nn.Parameter(torch.tensor(float(temperature)).log())
        if self.radius is not None:
            k = 2 * self.radius + 1
            r = torch.arange(-self.radius, self.radius + 1, dtype=torch.float32)
            shifts = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(k**3, 3)  # (dx, dy, dz)
            self.register_buffer("shifts", shifts, persistent=False)

    def forward(self, feat_moving: torch.Tensor, feat_fixed: torch.Tensor, cells: torch.Tensor,
                step: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``[B, C, X, Y, Z]`` x 2, cell positions ``[N, 3]`` (mm) and cell size ``[3]`` (mm) -> the matched moving
        position of every fixed cell ``[B, N, 3]`` (mm, float64) and its weight ``[B, N]`` (N = X*Y*Z)."""
        pm, pf = self.project(feat_moving), self.project(feat_fixed)
        scale = self.log_temperature.exp()
        if self.radius is None:
            fm = unit_channels(pm.flatten(2))
            ff = unit_channels(pf.flatten(2))
            prob = torch.softmax(torch.bmm(ff.transpose(1, 2), fm) * scale, dim=-1)  # [B, N fixed, N moving]
            matched = prob.to(torch.float64) @ cells
        else:
            cost = local_cost_volume(pm, pf, self.radius)
            prob = torch.softmax(cost * scale, dim=1).flatten(2).transpose(1, 2)  # [B, N, K^3]
            if self.subcell == "parabola":
                matched = cells + parabola_shifts(cost, self.radius) * step
            else:
                matched = cells + (prob.to(torch.float64) @ self.shifts.to(torch.float64)) * step
        peak = prob.max(dim=-1).values  # sharpness of the match, in [1 / candidates, 1]
        learned = torch.sigmoid(self.weight_head(feat_fixed)).flatten(1)  # 0.5 at initialisation
        return matched, learned * peak


class CorrelationRigidNet(nn.Module):
    """Shared encoder + coarse-to-fine local correlation + weighted closed-form rigid fit (see the module doc).

    Args:
        grid_size: network grid in voxels (each axis divisible by ``2 ** len(channels)``).
        grid_spacing: network grid spacing in mm (the cell positions of the rigid fit).
        in_channels: channels of each of the two volumes.
        channels: encoder stage widths; stages halve the resolution; the last two stages feed the fine (1/4) and
            the coarse (1/8) level for three stages.
        num_res_units: convolutions per residual stage.
        norm: MONAI norm type (instance norm copes with CBCT/CT intensity differences).
        feat_channels: channels of the matching features of (coarse, fine) levels.
        radius: search radius of the fine level in cells (8 mm cells at 2 mm: +-16 mm); the coarse level matches
            every cell against every cell (global search, the whole grid).
        temperature: initial softmax temperature on the cosine similarities.
        fine_passes: fine-level corrections after the coarse estimate (each re-warps the moving volume).
        subcell: how the fine level reads its matches out of the cost volume (:data:`SUBCELL_MODES`; no weights:
            a trained network can be run with either).

    Shapes:
        ``forward``: ``[B, 2 * C, x, y, z]`` (moving channels, then fixed) -> ``[B, 6]``.
        ``forward_pair``: ``moving, fixed`` ``[B, C, x, y, z]`` -> ``[B, 6]``.
        ``forward_levels``: the same -> list of ``[B, 6]``, the estimate after each level (last = output).
    """

    def __init__(
        self,
        grid_size: Sequence[int] = (64, 64, 64),
        grid_spacing: Sequence[float] = (2.0, 2.0, 2.0),
        in_channels: int = 1,
        channels: Sequence[int] = (16, 32, 32),
        num_res_units: int = 2,
        norm: str | tuple = "INSTANCE",
        feat_channels: Sequence[int] = (32, 16),
        radius: int = 2,
        temperature: float = 30.0,
        fine_passes: int = 1,
        subcell: str = "softargmax",
    ) -> None:
        super().__init__()
        if len(channels) < 3:
            raise ValueError(f"channels needs at least 3 stages (1/8 resolution), got {channels}")
        self.in_channels = int(in_channels)
        self.grid_size = tuple(int(s) for s in grid_size)
        self.grid_spacing = tuple(float(s) for s in grid_spacing)
        factor = 2 ** len(channels)
        if any(s % factor for s in self.grid_size):
            raise ValueError(f"grid_size {self.grid_size} must be divisible by {factor}")
        self.fine_passes = int(fine_passes)
        stages: list[nn.Module] = []
        c_in = self.in_channels
        for c in channels:
            stages.append(ResidualStage3d(c_in, int(c), stride=2, subunits=num_res_units, norm=norm))
            c_in = int(c)
        self.stages = nn.ModuleList(stages)
        self.coarse = _MatchLevel(int(channels[-1]), int(feat_channels[0]), None, temperature)
        self.fine = _MatchLevel(int(channels[-2]), int(feat_channels[1]), int(radius), temperature, subcell)
        self.grid = Grid.centered(self.grid_size, self.grid_spacing)
        n = len(channels)
        self.register_buffer("cells_coarse", self._cell_centres(2**n), persistent=False)
        self.register_buffer("cells_fine", self._cell_centres(2 ** (n - 1)), persistent=False)

    def _cell_centres(self, stride: int) -> torch.Tensor:
        """``[N, 3]`` mm positions (about the grid centre) of the cells of a stride-``stride`` feature map.

        A chain of stride-2, kernel-3, padding-1 convolutions centres output cell ``n`` on input voxel
        ``stride * n``; the voxel's position comes from the grid (:meth:`Grid.index_to_physical`)."""
        axes = [torch.arange(size // stride, dtype=torch.float64) * stride for size in self.grid_size]
        index = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        to_mm = torch.as_tensor(self.grid.index_to_physical(), dtype=torch.float64)
        return index @ to_mm[:3, :3].T + to_mm[:3, 3]

    def _encode(self, x: torch.Tensor, stages: int | None = None) -> list[torch.Tensor]:
        """The outputs of the first ``stages`` encoder stages (all by default)."""
        feats = []
        for stage in self.stages[:stages]:
            x = stage(x)
            feats.append(x)
        return feats

    def _fit(self, level: _MatchLevel, cells: torch.Tensor, fm: torch.Tensor, ff: torch.Tensor,
             stride: int, fixed_weight: torch.Tensor | None = None) -> torch.Tensor:
        step = torch.tensor([stride * s for s in self.grid_spacing], dtype=torch.float64, device=fm.device)
        matched, weight = level(fm, ff, cells, step)
        if fixed_weight is not None:  # the share of each cell inside the match region
            weight = weight * F.avg_pool3d(fixed_weight.to(weight.dtype), stride).flatten(1)
        return weighted_rigid_fit(cells.unsqueeze(0).expand(fm.shape[0], -1, -1), matched, weight)

    def forward_levels(self, moving: torch.Tensor, fixed: torch.Tensor,
                       fixed_weight: torch.Tensor | None = None) -> list[torch.Tensor]:
        """Estimates ``[B, 6]`` after the coarse level and after each fine pass (mm / degrees, grid centre).

        ``fixed_weight``: optional ``[B, 1, x, y, z]`` weights in [0, 1] on the fixed grid (the match region: a
        region of interest, bone, the body without the couch); each cell's weight in the rigid fit is multiplied by
        its mean, so only matches inside the region move the estimate (no weights are learned for it).
        """
        if moving.shape != fixed.shape:
            raise ValueError(f"moving {moving.shape} and fixed {fixed.shape} must have the same shape")
        if tuple(moving.shape[2:]) != self.grid_size:
            raise ValueError(f"inputs {tuple(moving.shape[2:])} are not on the network grid {self.grid_size}")
        if fixed_weight is not None and tuple(fixed_weight.shape[2:]) != self.grid_size:
            raise ValueError(f"fixed_weight {tuple(fixed_weight.shape)} is not on the network grid {self.grid_size}")
        b = moving.shape[0]
        n = len(self.stages)
        feats = self._encode(torch.cat([moving, fixed], 0))
        ff_fine, ff_coarse = feats[n - 2][b:], feats[n - 1][b:]
        total = self._fit(self.coarse, self.cells_coarse, feats[n - 1][:b], ff_coarse, 2**n, fixed_weight)
        levels = [matrix_to_params_torch(total).to(moving.dtype)]
        for _ in range(self.fine_passes):
            warped = warp_volume(moving, total, self.grid, self.grid)
            fm_fine = self._encode(warped, n - 1)[-1]
            correction = self._fit(self.fine, self.cells_fine, fm_fine, ff_fine, 2 ** (n - 1), fixed_weight)
            total = total @ correction
            levels.append(matrix_to_params_torch(total).to(moving.dtype))
        return levels

    def forward_pair(self, moving: torch.Tensor, fixed: torch.Tensor,
                     fixed_weight: torch.Tensor | None = None) -> torch.Tensor:
        """Rigid parameters ``[B, 6]`` (mm, degrees; fixed -> moving about the grid centre)."""
        return self.forward_levels(moving, fixed, fixed_weight)[-1]

    def forward(self, image: torch.Tensor, fixed_weight: torch.Tensor | None = None) -> torch.Tensor:
        """``[B, 2 * C, x, y, z]`` (moving, then fixed) -> ``[B, 6]`` (``fixed_weight``: see :meth:`forward_levels`)."""
        if image.shape[1] != 2 * self.in_channels:
            raise ValueError(f"expected {2 * self.in_channels} channels (moving, fixed), got {image.shape[1]}")
        return self.forward_pair(image[:, : self.in_channels], image[:, self.in_channels :], fixed_weight)
