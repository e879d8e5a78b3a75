"""Turn a collated registration batch into network inputs and loss targets (MONAI ``PrepareBatch``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from monai.engines.utils import PrepareBatch

from monai_rigidreg.transforms import RIGID_KEY

__all__ = ["RegistrationPrepareBatch"]


class RegistrationPrepareBatch(PrepareBatch):
    """``prepare_batch`` for MONAI's ``SupervisedTrainer`` / ``SupervisedEvaluator``.

    Input: a collated batch dict with ``moving`` and ``fixed`` (``[B, 1, x, y, z]`` on the network grid,
    normalized), the ground truth written by :class:`~monai_rigidreg.transforms.RandRigid6DoFd` under
    ``gt_key`` (``{"params": [B, 6], ...}``), and optionally a CBCT field-of-view mask (``mask_key``).

    Output: ``(inputs, targets)`` with ``inputs = cat([moving, fixed], 1)`` (``[B, 2, x, y, z]``, the bundle's
    network input; ``cat([moving, fixed, context], 1)`` where the batch has a CT context under ``context_key``)
    and ``targets = {"moving", "fixed", "params" ([B, 6] float32), "mask" (or absent)}``.

    Args:
        moving_key, fixed_key: image keys.
        gt_key: ground-truth record key.
        mask_key: field-of-view mask key (skipped where absent).
        context_key: CT context key (skipped where absent; same spatial shape as the network grid).
    """

    def __init__(
        self,
        moving_key: str = "moving",
        fixed_key: str = "fixed",
        gt_key: str = RIGID_KEY,
        mask_key: str | None = "moving_fov",
        context_key: str | None = "context",
    ) -> None:
        self.moving_key, self.fixed_key, self.gt_key, self.mask_key = moving_key, fixed_key, gt_key, mask_key
        self.context_key = context_key

    def __call__(
        self,
        batchdata: Mapping[str, Any],
        device: str | torch.device | None = None,
        non_blocking: bool = False,
        **kwargs: Any,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        def to(x: Any, dtype: torch.dtype = torch.float32) -> torch.Tensor:
            t = x.as_tensor() if hasattr(x, "as_tensor") else torch.as_tensor(x)
            return t.to(device=device, dtype=dtype, non_blocking=non_blocking)

        moving = to(batchdata[self.moving_key])
        fixed = to(batchdata[self.fixed_key])
        if moving.shape != fixed.shape or moving.ndim != 5:
            raise ValueError(f"moving {tuple(moving.shape)} and fixed {tuple(fixed.shape)} must be equal [B,C,x,y,z]")
        targets: dict[str, torch.Tensor] = {"moving": moving, "fixed": fixed}
        gt = batchdata.get(self.gt_key)
        if gt is not None:
            targets["params"] = to(gt["params"] if isinstance(gt, Mapping) else gt).reshape(-1, 6)
        if self.mask_key is not None and self.mask_key in batchdata:
            targets["mask"] = to(batchdata[self.mask_key])
        if self.context_key is not None and self.context_key in batchdata:
            return torch.cat([moving, fixed, to(batchdata[self.context_key])], dim=1), targets
        return torch.cat([moving, fixed], dim=1), targets
