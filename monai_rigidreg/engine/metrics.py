"""Per-axis parameter error and target registration error as MONAI metrics and Ignite handlers."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from monai.handlers import IgniteMetricHandler
from monai.metrics import CumulativeIterationMetric

from monai_rigidreg.core.geometry import PARAM_NAMES, Grid, grid_points, point_distances_torch, wrap_degrees

__all__ = ["RigidErrorMetric", "RigidErrorHandler", "from_registration_output", "error_handlers"]


def from_registration_output(output: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """Ignite ``output_transform``: ``(pred [B, 6], true params [B, 6])`` from a MONAI engine's output."""
    if isinstance(output, list):  # decollated
        pred = torch.stack([o["pred"] for o in output])
        label = torch.stack([o["label"]["params"] for o in output])
        return pred, label
    return output["pred"], output["label"]["params"]


class RigidErrorMetric(CumulativeIterationMetric):
    """Absolute error of one rigid parameter, or the mean target registration error, per case.

    Args:
        quantity: one of ``tx, ty, tz`` (mm), ``rx, ry, rz`` (degrees), ``"trans"`` / ``"rot"`` (mean over the
            three axes), or ``"tre"`` (mm: mean over points of a centred grid of ``extent_mm`` half-size, every
            ``step_mm``; the parameters are about the grid centre).
        extent_mm, step_mm: TRE point grid.
        reduction: ``"mean"`` (default) or ``"none"`` in :meth:`aggregate`.
    """

    def __init__(self, quantity: str = "tre", extent_mm: float = 80.0, step_mm: float = 16.0,
                 reduction: str = "mean") -> None:
        super().__init__()
        if quantity not in (*PARAM_NAMES, "trans", "rot", "tre"):
            raise ValueError(f"unknown quantity {quantity!r}")
        self.quantity = quantity
        self.reduction = reduction
        n = int(2 * extent_mm / step_mm) + 1
        pts = grid_points(Grid.centered((n, n, n), (step_mm,) * 3, (0, 0, 0)), 1)
        self._points = torch.as_tensor(pts, dtype=torch.float64)

    def _compute_tensor(self, y_pred: torch.Tensor, y: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        p = y_pred.detach().double().reshape(-1, 6)
        t = y.detach().double().to(p.device).reshape(-1, 6)
        if self.quantity == "tre":
            return point_distances_torch(p, t, self._points).mean(dim=1, keepdim=True)
        d = p - t
        d[:, 3:] = wrap_degrees(d[:, 3:])
        d = d.abs()
        if self.quantity == "trans":
            return d[:, :3].mean(1, keepdim=True)
        if self.quantity == "rot":
            return d[:, 3:].mean(1, keepdim=True)
        return d[:, PARAM_NAMES.index(self.quantity)].reshape(-1, 1)

    def aggregate(self) -> torch.Tensor:  # type: ignore[override]
        data = self.get_buffer()
        if not isinstance(data, torch.Tensor):
            raise ValueError("no data to aggregate")
        return data if self.reduction == "none" else data.mean()


class RigidErrorHandler(IgniteMetricHandler):
    """Ignite handler of :class:`RigidErrorMetric` (for ``key_val_metric`` / ``additional_metrics``).

    Args:
        quantity: see :class:`RigidErrorMetric`.
        output_transform: maps the engine output to ``(pred, true params)``.
        save_details: keep per-case values in the engine state.
    """

    def __init__(self, quantity: str = "tre", output_transform: Callable = from_registration_output,
                 save_details: bool = False, **kwargs: Any) -> None:
        super().__init__(metric_fn=RigidErrorMetric(quantity, **kwargs), output_transform=output_transform,
                         save_details=save_details)


def error_handlers(quantities: Sequence[str] = ("tre", *PARAM_NAMES)) -> dict[str, RigidErrorHandler]:
    """``{"val_<quantity>": handler}`` for every quantity (convenience for configs)."""
    return {f"val_{q}": RigidErrorHandler(q) for q in quantities}
