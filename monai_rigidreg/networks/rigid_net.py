"""Dual-encoder CNN that regresses the six rigid parameters of a CBCT (moving) to Sim-CT (fixed) registration.

This is the learned stage alone; :class:`~monai_rigidreg.networks.TwoStageRigidNet` chains it with the weight-free
:class:`~monai_rigidreg.networks.GaussNewtonStage` as shipped in the bundle.

The network sees only the two volumes resampled onto one *network grid* (axis-aligned, in the fixed frame) and
knows nothing else about physical space. Its outputs ``(tx, ty, tz, rx, ry, rz)`` are physical millimetres and
degrees of the transform ``T(x) = R (x - c) + c + t`` that maps fixed points to moving points, ``c`` the centre of
the network grid (see :mod:`monai_rigidreg.core.geometry`). The mm scale is learned for the grid spacing it is trained
at: a checkpoint is tied to that spacing (keep it in the bundle config).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

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
        ``benchmarks/speed/bench_network.py --ablation`` measures them on a synthetic task.

    Units and frame: outputs are physical mm / degrees of the fixed->moving transform about the centre of the
    network grid (see :mod:`monai_rigidreg.core.geometry`); turn them into a matrix with
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
    ) -> None:
        super().__init__()
        if len(channels) != len(strides) or len(channels) == 0:
            raise ValueError(f"channels and strides must be non-empty and of equal length, got {channels}, {strides}")
        if fusion not in FUSIONS:
            raise ValueError(f"fusion must be one of {FUSIONS}, got {fusion!r}")
        if max_translation <= 0 or max_rotation <= 0:
            raise ValueError("max_translation and max_rotation must be > 0")
        self.in_channels = int(in_channels)
        self.fusion_name = fusion

        # imported here, not at the top: the register path imports this package (CorrelationRigidNet) and must not
        # pay for MONAI's import (see monai_rigidreg.networks.blocks); this network takes any MONAI act/norm/dropout
        from monai.networks.blocks import ResidualUnit

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
        return torch.tanh(z) * self.bounds.to(z.dtype)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        """Rigid parameters from the MONAI bundle form ``[B, 2 * in_channels, x, y, z]`` (moving, then fixed).

        Returns:
            ``[B, 6]`` as :meth:`forward_pair`.
        """
        if image.shape[1] != 2 * self.in_channels:
            raise ValueError(f"expected {2 * self.in_channels} channels (moving, fixed), got {image.shape[1]}")
        return self.forward_pair(image[:, : self.in_channels], image[:, self.in_channels :])

