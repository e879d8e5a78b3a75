"""Iterative (cascade) use of a rigid-parameter network: estimate, warp, re-estimate a correction, compose."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from monai_rigidreg.core.geometry import Grid, matrix_to_params_torch, params_to_matrix_torch
from monai_rigidreg.core.warp import warp_volume

__all__ = ["cascade_register", "CascadeRegistration"]


def _call_pair(net: nn.Module | Callable, moving: torch.Tensor, fixed: torch.Tensor) -> torch.Tensor:
    if hasattr(net, "forward_pair"):
        return net.forward_pair(moving, fixed)
    return net(torch.cat([moving, fixed], dim=1))


def cascade_register(
    net: nn.Module | Callable,
    moving: torch.Tensor,
    fixed: torch.Tensor,
    grid: Grid,
    steps: int = 2,
    mode: str = "bilinear",
    padding_mode: str = "zeros",
    return_all: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, list[torch.Tensor]]:
    """Register by ``steps`` applications of ``net`` with composition of the corrections.

    Step 1 predicts ``T_1 = net(moving, fixed)``. At step k > 1 the *original* moving volume is warped by the
    current estimate, ``W(x) = M(T_{k-1}(x))`` (one interpolation only, never a warp of a warp), the net predicts
    a correction ``C = net(W, fixed)`` (so that ``F(x) ~ W(C(x)) = M(T_{k-1}(C(x)))``) and the estimate becomes
    ``T_k = T_{k-1} o C`` (matrix ``T_{k-1} @ C``). All matrices are fixed->moving, LPS mm, about
    ``grid.center()``; the result is converted back with ``matrix_to_params_torch``. Differentiable end to end.

    Args:
        net: a :class:`~monai_rigidreg.networks.DualEncoderRigidNet` (``forward_pair`` is used when present,
            otherwise ``net(cat([moving, fixed], 1))``) returning ``[B, 6]`` mm/degrees about the grid centre.
        moving: ``[B, C, x, y, z]`` on ``grid``.
        fixed: ``[B, C, x, y, z]`` on ``grid``.
        grid: the network grid (both volumes are on it).
        steps: number of network applications K >= 1 (1 = plain single pass).
        mode, padding_mode: interpolation of the intermediate warps (see :func:`monai_rigidreg.core.warp.warp_volume`).
        return_all: also return the list of per-step total estimates (``[B, 6]`` each).

    Returns:
        ``[B, 6]`` total parameters ``(tx, ty, tz, rx, ry, rz)`` (mm, degrees) about ``grid.center()``, dtype of
        the net output; with ``return_all`` a tuple ``(params, [params_1, ..., params_K])``.
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    center = grid.center()
    params = _call_pair(net, moving, fixed)
    history = [params]
    total = params_to_matrix_torch(params.to(torch.float64), center)
    for _ in range(steps - 1):
        warped = warp_volume(moving, total, grid, grid, mode=mode, padding_mode=padding_mode)
        correction = _call_pair(net, warped, fixed)
        total = total @ params_to_matrix_torch(correction.to(torch.float64), center)
        history.append(matrix_to_params_torch(total, center).to(params.dtype))
    out = history[-1] if steps > 1 else params
    return (out, history) if return_all else out


class CascadeRegistration(nn.Module):
    """:func:`cascade_register` as a module (``forward(image [B, 2C, x, y, z]) -> [B, 6]``, bundle form).

    Args:
        net: the rigid-parameter network.
        grid: the network grid.
        steps: number of network applications.
    """

    def __init__(self, net: nn.Module, grid: Grid, steps: int = 2) -> None:
        super().__init__()
        self.net = net
        self.grid = grid
        self.steps = int(steps)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        c = image.shape[1] // 2
        out = cascade_register(self.net, image[:, :c], image[:, c:], self.grid, steps=self.steps)
        assert isinstance(out, torch.Tensor)
        return out
