"""Dual-encoder CNN that regresses the six rigid parameters of a CBCT (moving) to Sim-CT (fixed) registration.

The network sees only the two volumes resampled onto one *network grid* (axis-aligned, in the fixed frame) and
knows nothing else about physical space. Its outputs ``(tx, ty, tz, rx, ry, rz)`` are physical millimetres and
degrees of the transform ``T(x) = R (x - c) + c + t`` that maps fixed points to moving points, ``c`` the centre of
the network grid (see :mod:`monai_rigidreg.geometry`). The mm scale is learned for the grid spacing it is trained
at: a checkpoint is tied to that spacing (keep it in the bundle config).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from monai.networks.blocks import ResidualUnit
from torch import nn

from monai_rigidreg.geometry import Grid, matrix_to_params_torch, params_to_matrix_torch
from monai_rigidreg.networks.alignment import alignment_features, erode, gauss_newton_align, pyramid

__all__ = ["DualEncoderRigidNet", "FUSIONS"]

FUSIONS: tuple[str, ...] = ("flatten", "correlation", "gap")
"""Available ways of fusing the two encoded feature maps (constructor argument ``fusion``)."""


class _FlattenFusion(nn.Module):
    """Keeps position: 1x1x1 channel reduction, adaptive pooling to ``pool_size``^3, flatten, concatenate.

    ``[B, C, n, n, n]`` x 2 -> ``[B, 2 * reduced * pool_size**3]``.
    """

    def __init__(self, in_channels: int, reduced_channels: int, pool_size: int) -> None:
        super().__init__()
        self.reduce = nn.Conv3d(in_channels, reduced_channels, kernel_size=1)
        self.pool = nn.AdaptiveAvgPool3d(pool_size)
        self.out_features = 2 * reduced_channels * pool_size**3

    def forward(self, feat_m: torch.Tensor, feat_f: torch.Tensor) -> torch.Tensor:
        fm = self.pool(self.reduce(feat_m)).flatten(1)
        ff = self.pool(self.reduce(feat_f)).flatten(1)
        return torch.cat([fm, ff], dim=1)


class _CorrelationFusion(nn.Module):
    """Global cost volume: cosine similarity of every moving location with every fixed location.

    Both maps are pooled to ``pool_size``^3 locations (``N = pool_size**3``); the ``[B, N, N]`` similarity matrix
    (moving location i, fixed location j, in [-1, 1]) is flattened: ``[B, N * N]``. The position of the best match
    of each moving location encodes the displacement explicitly.
    """

    def __init__(self, in_channels: int, reduced_channels: int, pool_size: int) -> None:
        super().__init__()
        self.reduce = nn.Conv3d(in_channels, reduced_channels, kernel_size=1)
        self.pool = nn.AdaptiveAvgPool3d(pool_size)
        self.out_features = pool_size**6

    def forward(self, feat_m: torch.Tensor, feat_f: torch.Tensor) -> torch.Tensor:
        fm = F.normalize(self.pool(self.reduce(feat_m)).flatten(2), dim=1)  # [B, C, N]
        ff = F.normalize(self.pool(self.reduce(feat_f)).flatten(2), dim=1)
        return torch.bmm(fm.transpose(1, 2), ff).flatten(1)


class _GapFusion(nn.Module):
    """Global average pooling of each map, concatenated: ``[B, 2 * C]`` (discards position; ablation baseline)."""

    def __init__(self, in_channels: int) -> None:
        super().__init__()
        self.out_features = 2 * in_channels

    def forward(self, feat_m: torch.Tensor, feat_f: torch.Tensor) -> torch.Tensor:
        return torch.cat([feat_m.mean(dim=(2, 3, 4)), feat_f.mean(dim=(2, 3, 4))], dim=1)


class DualEncoderRigidNet(nn.Module):
    """Shared-weight 3D CNN encoder + fusion MLP that regresses ``(tx, ty, tz, rx, ry, rz)``.

    Architecture: the moving and the fixed volume pass through the *same* encoder (stacked along the batch axis,
    so the weights are shared), a chain of MONAI :class:`~monai.networks.blocks.ResidualUnit` blocks with
    ``channels``/``strides``; the two feature maps are fused (``fusion``) into a vector; a compact MLP maps it to
    six numbers; a scaled tanh bounds them: translations to ``+-max_translation`` mm, rotations to
    ``+-max_rotation`` degrees. The last linear layer is zero-initialised, so an untrained network outputs
    exactly the identity transform.

    Fusion options (``fusion``):
        * ``"flatten"`` (default): per-image 1x1x1 channel reduction to ``fusion_channels``, adaptive average
          pooling to ``pool_size``^3 cells, flattened and concatenated; the MLP sees *where* features are.
        * ``"correlation"``: cosine-similarity cost volume between all ``pool_size``^3 moving and fixed cells
          (``pool_size**6`` features).
        * ``"gap"``: global average pooling of each map (discards position; kept as an ablation baseline).
        ``benchmarks/bench_network.py --ablation`` measures them on a synthetic task.

    Units and frame: outputs are physical mm / degrees of the fixed->moving transform about the centre of the
    network grid (see :mod:`monai_rigidreg.geometry`); turn them into a matrix with
    ``params_to_matrix_torch(params, grid.center())``. The network itself knows nothing of physical space; the mm
    scale it learns is specific to the network-grid spacing it is trained at.

    Args:
        in_channels: channels of *each* of the two volumes (1 for CT/CBCT).
        channels: output channels of the encoder stages.
        strides: stride of each encoder stage (same length as ``channels``).
        num_res_units: convolutions per residual stage (MONAI ``ResidualUnit`` ``subunits``).
        kernel_size: convolution kernel size.
        norm: MONAI norm type, e.g. ``"INSTANCE"`` (default; robust to CBCT/CT intensity differences) or
            ``"BATCH"``.
        act: MONAI activation type.
        dropout: dropout probability in the encoder and MLP (0 disables it).
        fusion: ``"flatten"``, ``"correlation"`` or ``"gap"`` (see above).
        fusion_channels: channels after the 1x1x1 reduction (``flatten``/``correlation``).
        pool_size: cells per axis after adaptive pooling (``flatten``/``correlation``); use the encoder's output
            size (grid size / prod(strides)) to avoid extra pooling.
        hidden: hidden widths of the fusion MLP.
        max_translation: bound of ``|t|`` per axis in mm (scaled tanh).
        max_rotation: bound of ``|r|`` per axis in degrees (scaled tanh).
        align_iterations: Gauss-Newton steps per pyramid level of the fine stage (empty: no fine stage, the
            network is the regression alone). See :meth:`align` and :mod:`monai_rigidreg.networks.alignment`.
        align_levels: pooling factor of each level, coarse to fine (same length as ``align_iterations``).
        align_highpass_sigma_mm, align_highpass_weight, align_gradient_weight: the fine stage's feature maps, see
            :func:`~monai_rigidreg.networks.alignment.alignment_features` (weights 0: align intensities alone).
        align_support_erosion_mm: erosion of the moving support (the CBCT data region) before it weights the
            fine stage's residuals (mm, at least one voxel).
        align_bias_degree: degree of the smooth intensity bias (per feature channel, a polynomial over the grid)
            that the fine stage estimates jointly with the pose and discards, so CBCT cupping and scatter shading do
            not pull the pose (-1: none); see :func:`~monai_rigidreg.networks.alignment.gauss_newton_align`. Used
            from the second pyramid level on: on the coarsest level, where large motions are captured, a smooth
            field can stand in for a shift of broad structures (``benchmarks/bench_capture_range.py``, run once
            with the terms on every level: fewer large motions captured from the identity than without them).
        align_jacobian: image gradients of the Gauss-Newton steps: ``"fixed"`` (inverse compositional, the
            default), ``"moving"`` or ``"symmetric"``
            (see :func:`~monai_rigidreg.networks.alignment.gauss_newton_align`); one for all levels or one per
            level (same length as ``align_iterations``).
        align_robust_scale: optional Geman-McClure scale of the fine stage's residuals (None: plain least squares).
        grid_spacing: network-grid spacing in mm (the fine stage works in physical units; set it to the bundle's
            ``network_spacing``).
        support_threshold: normalized intensity above which a moving voxel counts as data for the fine stage.

    Two stages (when ``align_iterations`` is given): the regression above gives a coarse estimate (kept in
    ``last_coarse`` for the training loss), then the fine stage aligns contrast-robust feature maps of both volumes
    (intensity and local contrast) by coarse-to-fine Gauss-Newton steps restricted to the moving
    image's support (the CBCT field of view). The fine stage has no trainable weights; it is differentiable with
    respect to the images, but its start is detached, so the regression learns from its own supervised term
    (:class:`~monai_rigidreg.engine.RegistrationCriterion` ``w_coarse``). Measured reason for fixed features: learned
    feature channels trained through the (detached-Jacobian) Gauss-Newton steps degraded the validation TRE of the
    untrained stage from 2.6 mm to 15 mm within one CPU epoch, while the fixed features reach about 0.4 mm
    (``benchmarks/bench_alignment_features.py``). With a fine stage the module is exported to TorchScript by
    tracing at a fixed grid size (scripting covers the regression-only network).

    Shapes:
        ``forward``: ``[B, 2 * in_channels, x, y, z]`` (moving channels first, then fixed) -> ``[B, 6]``.
        ``forward_pair``: ``moving, fixed`` ``[B, in_channels, x, y, z]`` each -> ``[B, 6]``.
        The output has the dtype and device of the input (no hard-coded device); TorchScript-able.
    """

    def __init__(
        self,
        in_channels: int = 1,
        channels: Sequence[int] = (8, 16, 32, 32),
        strides: Sequence[int] = (2, 2, 2, 2),
        num_res_units: int = 2,
        kernel_size: int = 3,
        norm: str | tuple = "INSTANCE",
        act: str | tuple = "PRELU",
        dropout: float = 0.0,
        fusion: str = "flatten",
        fusion_channels: int = 16,
        pool_size: int = 4,
        hidden: Sequence[int] = (128,),
        max_translation: float = 40.0,
        max_rotation: float = 45.0,
        align_iterations: Sequence[int] = (),
        align_levels: Sequence[int] = (4, 2, 1),
        align_highpass_sigma_mm: float = 16.0,
        align_highpass_weight: float = 3.0,
        align_gradient_weight: float = 0.0,
        align_robust_scale: float | None = None,
        align_support_erosion_mm: float = 8.0,
        align_bias_degree: int = -1,
        align_jacobian: str | Sequence[str] = "fixed",
        grid_spacing: Sequence[float] = (4.0, 4.0, 4.0),
        support_threshold: float = 1e-3,
    ) -> None:
        super().__init__()
        if len(channels) != len(strides) or len(channels) == 0:
            raise ValueError(f"channels and strides must be non-empty and of equal length, got {channels}, {strides}")
        if fusion not in FUSIONS:
            raise ValueError(f"fusion must be one of {FUSIONS}, got {fusion!r}")
        if max_translation <= 0 or max_rotation <= 0:
            raise ValueError("max_translation and max_rotation must be > 0")
        align_iterations = tuple(int(i) for i in align_iterations)
        if align_iterations and len(align_iterations) != len(align_levels):
            raise ValueError(
                f"align_iterations {align_iterations} and align_levels {tuple(align_levels)} differ in length"
            )
        self.align_iterations = align_iterations
        self.has_align: torch.jit.Final[bool] = len(align_iterations) > 0
        self.align_levels = tuple(int(v) for v in align_levels)
        self.align_robust_scale = align_robust_scale
        self.align_support_erosion_mm = float(align_support_erosion_mm)
        self.align_bias_degree = int(align_bias_degree)
        self.align_jacobian = align_jacobian if isinstance(align_jacobian, str) else tuple(align_jacobian)
        if not isinstance(self.align_jacobian, str) and len(self.align_jacobian) != len(self.align_levels):
            raise ValueError(f"align_jacobian {self.align_jacobian} needs one entry per level {self.align_levels}")
        self.align_highpass_sigma_mm = float(align_highpass_sigma_mm)
        self.align_highpass_weight = float(align_highpass_weight)
        self.align_gradient_weight = float(align_gradient_weight)
        self.grid_spacing = tuple(float(v) for v in grid_spacing)
        self.support_threshold = float(support_threshold)
        self.last_coarse: torch.Tensor | None = None
        self.last_start: torch.Tensor | None = None  # per case: True where the fine stage started from the regression
        self.in_channels = int(in_channels)
        self.fusion_name = fusion

        layers: list[nn.Module] = []
        c_in = self.in_channels
        for c, s in zip(channels, strides):
            layers.append(
                ResidualUnit(
                    spatial_dims=3,
                    in_channels=c_in,
                    out_channels=int(c),
                    strides=int(s),
                    kernel_size=kernel_size,
                    subunits=num_res_units,
                    act=act,
                    norm=norm,
                    dropout=dropout if dropout > 0 else None,
                )
            )
            c_in = int(c)
        self.encoder = nn.Sequential(*layers)

        self.fusion: nn.Module
        if fusion == "flatten":
            self.fusion = _FlattenFusion(c_in, fusion_channels, pool_size)
        elif fusion == "correlation":
            self.fusion = _CorrelationFusion(c_in, fusion_channels, pool_size)
        else:
            self.fusion = _GapFusion(c_in)
        n_feat = int(self.fusion.out_features)

        mlp: list[nn.Module] = []
        for h in hidden:
            mlp += [nn.Linear(n_feat, int(h)), nn.PReLU()]
            if dropout > 0:
                mlp.append(nn.Dropout(dropout))
            n_feat = int(h)
        self.mlp = nn.Sequential(*mlp)
        self.head = nn.Linear(n_feat, 6)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        # per-output bound of the scaled tanh: (tx, ty, tz) mm, (rx, ry, rz) degrees
        self.register_buffer("bounds", torch.tensor([max_translation] * 3 + [max_rotation] * 3))

    def forward_pair(self, moving: torch.Tensor, fixed: torch.Tensor) -> torch.Tensor:
        """Rigid parameters from separate volumes.

        Args:
            moving: ``[B, in_channels, x, y, z]`` CBCT on the network grid, intensities ~[0, 1].
            fixed: ``[B, in_channels, x, y, z]`` Sim-CT on the same grid.

        Returns:
            ``[B, 6]``: ``(tx, ty, tz)`` mm and ``(rx, ry, rz)`` degrees, fixed -> moving, about the grid centre.
        """
        if moving.shape != fixed.shape:
            raise ValueError(f"moving {moving.shape} and fixed {fixed.shape} must have the same shape")
        b = moving.shape[0]
        pair = torch.cat([moving, fixed], dim=0)
        feats = self.encoder(pair)  # shared weights: one pass over 2B volumes
        fused = self.fusion(feats[:b], feats[b:])
        z = self.head(self.mlp(fused))
        coarse = torch.tanh(z) * self.bounds.to(z.dtype)
        if not self.has_align:
            return coarse
        return self._fine_stage(moving, fixed, coarse, pair)

    @torch.jit.unused
    def _fine_stage(self, moving: torch.Tensor, fixed: torch.Tensor, coarse: torch.Tensor, pair: torch.Tensor
                    ) -> torch.Tensor:
        # outside TorchScript scripting (the fine stage is exported by tracing)
        self.last_coarse = coarse
        return self.align(moving, fixed, coarse, pair)

    def alignment_features(self, pair: torch.Tensor) -> torch.Tensor:
        """Feature maps the fine stage aligns (:func:`~monai_rigidreg.networks.alignment.alignment_features`)."""
        return alignment_features(pair, self.grid_spacing, self.support_threshold, self.align_highpass_sigma_mm,
                                  self.align_highpass_weight, self.align_gradient_weight)

    def align(
        self, moving: torch.Tensor, fixed: torch.Tensor, coarse: torch.Tensor, pair: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Fine stage: coarse-to-fine Gauss-Newton alignment of the shared feature maps.

        The first level runs from two starts, ``coarse`` and the identity; per case the better fit (lower
        residual) continues (``last_start``: True where that was ``coarse``).

        The moving support (voxels above ``support_threshold`` after normalisation, eroded by
        ``align_support_erosion_mm``: the CBCT field of view, minus air) restricts the residuals, so a truncated
        CBCT is not pulled towards the CT's anatomy outside its field of view. ``[B, 6]`` in and out (mm, degrees
        about the grid centre).
        """
        if not self.has_align:
            raise RuntimeError("this network was built without an alignment stage (align_iterations=())")
        b = moving.shape[0]
        if pair is None:
            pair = torch.cat([moving, fixed], dim=0)
        feat = self.alignment_features(pair)
        feat_m, feat_f = feat[:b], feat[b:]
        support = (moving > self.support_threshold).to(moving.dtype)
        # erode (at least a voxel): keep voxels whose neighbourhood all has data. More than a voxel: near the CBCT
        # field-of-view edge the local contrast of the CT (which has data beyond it) and of the CBCT differ
        # (measured, bench_alignment_features.py: 8 mm takes the validation TRE from 0.63 mm with 1 voxel to 0.42 mm)
        support = erode(support, [max(1, round(self.align_support_erosion_mm / s)) for s in self.grid_spacing])
        grid = Grid.centered(tuple(moving.shape[2:]), self.grid_spacing, (0.0, 0.0, 0.0))
        # two starts, the regression estimate and the identity, run through the first level together; per case
        # the one with the lower residual goes on (the regression can only widen the capture range, never spoil
        # a case the Gauss-Newton stage captures on its own)
        # The start is detached: the regression learns from its own supervised term only. Measured: letting the loss
        # on the final estimate reach it through the Gauss-Newton steps made CPU training diverge within two epochs
        # (the regression saturated at its tanh bounds and stayed there).
        starts = torch.cat([params_to_matrix_torch(coarse.detach().to(torch.float64), grid.center()),
                            torch.eye(4, dtype=torch.float64, device=coarse.device).expand(b, 4, 4)], 0)
        total = starts
        first = True
        jacobians = [self.align_jacobian] * len(self.align_levels) if isinstance(self.align_jacobian, str) \
            else list(self.align_jacobian)
        for level, iters, jacobian in zip(self.align_levels, self.align_iterations, jacobians):
            if iters <= 0:
                continue
            fm, g = pyramid(feat_m, grid, level)
            ff, _ = pyramid(feat_f, grid, level)
            sup = support if level == 1 else (F.avg_pool3d(support, level) > 0.999).to(support.dtype)
            if first:
                fm2, ff2, sup2 = fm.repeat(2, 1, 1, 1, 1), ff.repeat(2, 1, 1, 1, 1), sup.repeat(2, 1, 1, 1, 1)
                both, res, cover = gauss_newton_align(fm2, ff2, g, total, iterations=iters, moving_support=sup2,
                                                      robust_scale=self.align_robust_scale, return_residual=True,
                                                      jacobian=jacobian)
                # a start that leaves little overlap can show a low mean residual: it must keep at least half the
                # overlap of the identity start to be preferred
                pick = ((res[:b] <= res[b:]) & (cover[:b] >= 0.5 * cover[b:])).view(b, 1, 1)
                total = torch.where(pick, both[:b], both[b:])
                self.last_start = pick.view(b).detach()
                first = False
                continue
            total = gauss_newton_align(fm, ff, g, total, iterations=iters, moving_support=sup,
                                       robust_scale=self.align_robust_scale, bias_degree=self.align_bias_degree,
                                       jacobian=jacobian)
        if first:  # no level ran
            total = starts[:b]
        return matrix_to_params_torch(total, grid.center()).to(coarse.dtype)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """Rigid parameters from the MONAI bundle form ``[B, 2 * in_channels, x, y, z]`` (moving, then fixed).

        Returns:
            ``[B, 6]`` as :meth:`forward_pair`.
        """
        if image.shape[1] != 2 * self.in_channels:
            raise ValueError(f"expected {2 * self.in_channels} channels (moving, fixed), got {image.shape[1]}")
        return self.forward_pair(image[:, : self.in_channels], image[:, self.in_channels :])


# TorchScript builds the stub of an ``@torch.jit.unused`` method from real annotation objects, while this module's
# annotations are strings (``from __future__ import annotations``): give the fine-stage hook real ones
DualEncoderRigidNet._fine_stage.__annotations__ = {
    "moving": torch.Tensor, "fixed": torch.Tensor, "coarse": torch.Tensor, "pair": torch.Tensor,
    "return": torch.Tensor,
}
