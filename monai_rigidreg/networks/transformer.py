"""Differentiable rigid spatial transformer: six parameters -> sampling grid -> moving volume on the fixed grid."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from monai_rigidreg.core.geometry import Grid, params_to_matrix_torch
from monai_rigidreg.core.warp import warp_volume

__all__ = ["RigidTransformer"]


class RigidTransformer(nn.Module):
    """Warp a moving volume onto the fixed grid under ``(tx, ty, tz, rx, ry, rz)`` (the STN of the paper).

    A thin :class:`torch.nn.Module` around :func:`monai_rigidreg.core.geometry.params_to_matrix_torch` and
    :func:`monai_rigidreg.core.warp.warp_volume` (no second derivation of the conventions): the output is the torch twin
    of ``SimpleITK.Resample(moving, fixed, params_to_sitk(params, center))``, i.e. ``out(x) = moving(T(x))`` with
    ``T(x) = R (x - c) + c + t`` mapping fixed points to moving points (LPS mm). So ``tx = +s`` mm gives
    ``out(x) = moving(x + s e_x)``: the content moves by ``-s`` along LPS x.

    Args:
        fixed_grid: output grid (usually the network grid).
        moving_grid: grid of the moving tensor (default: ``fixed_grid``).
        center: rotation centre in LPS mm, ``[3]`` (default: ``fixed_grid.center()``).
        mode: ``"bilinear"`` (trilinear) or ``"nearest"``.
        padding_mode: ``"zeros"``, ``"border"`` or ``"reflection"``.

    Shapes:
        ``forward(moving [B, C, x, y, z] on moving_grid, params [B, 6] mm/deg) -> [B, C, *fixed_grid.size]``,
        differentiable w.r.t. both ``moving`` and ``params``; dtype/device of ``moving``.
    """

    def __init__(
        self,
        fixed_grid: Grid,
        moving_grid: Grid | None = None,
        center: Any = None,
        mode: str = "bilinear",
        padding_mode: str = "zeros",
    ) -> None:
        super().__init__()
        self.fixed_grid = fixed_grid
        self.moving_grid = fixed_grid if moving_grid is None else moving_grid
        # kept as float64 numpy (not a buffer): ``module.half()`` must not round the centre (mm) to fp16
        self.center = fixed_grid.center() if center is None else np.asarray(center, dtype=np.float64).reshape(3)
        self.mode = mode
        self.padding_mode = padding_mode

    def matrix(self, params: torch.Tensor) -> torch.Tensor:
        """``[B, 4, 4]`` float64 fixed->moving matrices (LPS mm) of ``params`` ``[B, 6]`` about the centre."""
        return params_to_matrix_torch(params.to(torch.float64), self.center)

    def forward(self, moving: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
        if params.ndim != 2 or params.shape[-1] != 6:
            raise ValueError(f"params must be [B, 6], got {tuple(params.shape)}")
        return warp_volume(moving, self.matrix(params), self.fixed_grid, self.moving_grid, self.mode, self.padding_mode)
