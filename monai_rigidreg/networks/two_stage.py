"""The shipped registration network: the learned regression followed by the weight-free Gauss-Newton stage."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from monai_rigidreg.networks.gauss_newton import GaussNewtonStage

__all__ = ["TwoStageRigidNet", "STAGE_KEYS"]

STAGE_KEYS: tuple[str, ...] = ("params", "coarse", "from_coarse")
"""Keys of :meth:`TwoStageRigidNet.forward_stages`: the final estimate, the regression's estimate, and per case
whether the fine stage went on from the regression's estimate (True) or from the identity (False). A regression
with levels (:class:`~monai_rigidreg.networks.CorrelationRigidNet`) adds ``"levels"``: its estimate after each
level before the last (a list of ``[B, 6]``), for deep supervision."""


class TwoStageRigidNet(nn.Module):
    """``regression`` (a :class:`~monai_rigidreg.networks.CorrelationRigidNet` or
    :class:`~monai_rigidreg.networks.DualEncoderRigidNet`) -> ``fine_stage``
    (a :class:`~monai_rigidreg.networks.GaussNewtonStage`, or ``None`` for the regression alone).

    The regression gives a coarse estimate in one feed-forward pass; the fine stage refines it on the same network
    grid (no trainable weights). ``forward`` keeps the MONAI bundle form and returns the final ``[B, 6]`` estimate,
    so ``verify_net_in_out``, engines and ``ckpt_export`` see one tensor; the training criterion needs the coarse
    estimate as well and gets it from :meth:`forward_stages` (or ``forward(image, stages=True)``, which is what a
    ``DistributedDataParallel`` wrapper can call), never from state left on the module.

    Checkpoints of bundle 0.2.x, saved when the regression and the fine stage were one module, hold the
    regression's keys without the ``regression.`` prefix; :meth:`load_state_dict` accepts them as they are.

    Args:
        regression: the learned stage; outputs ``(tx, ty, tz, rx, ry, rz)`` mm / degrees about the grid centre.
        fine_stage: the refinement, or ``None``.
        fine_stage_enabled: run the fine stage (``False`` measures the regression alone with the same weights).

    Shapes:
        ``forward``: ``[B, 2 * C, x, y, z]`` (moving channels first, then fixed) -> ``[B, 6]``.
        ``forward_pair``: ``moving, fixed`` ``[B, C, x, y, z]`` each -> ``[B, 6]``.
        ``forward_stages``: the same inputs -> ``{"params": [B, 6], "coarse": [B, 6], "from_coarse": [B] bool}``.
    """

    def __init__(self, regression: nn.Module, fine_stage: GaussNewtonStage | None = None,
                 fine_stage_enabled: bool = True) -> None:
        super().__init__()
        self.regression = regression
        self.fine_stage = fine_stage
        self.fine_stage_enabled = bool(fine_stage_enabled)
        self.in_channels = int(regression.in_channels)
        self._register_load_state_dict_pre_hook(_accept_flat_regression_keys, with_module=True)

    def __prepare_scriptable__(self) -> TwoStageRigidNet:
        """``torch.jit.script`` (and ``ckpt_export`` without ``--use_trace``) stops here with what to do instead."""
        if self.fine_stage is None or not self.fine_stage_enabled:
            raise RuntimeError("script the regression itself: torch.jit.script(net.regression)")
        raise RuntimeError(
            "TwoStageRigidNet cannot be scripted: its Gauss-Newton fine stage builds grids with numpy and caches them. "
            "Export it by tracing at the network grid size, e.g. python -m monai.bundle ckpt_export network_def "
            "--use_trace True --input_shape '[1, 2, 64, 64, 64]' ... (a DualEncoderRigidNet regression also "
            "scripts alone: torch.jit.script(net.regression); a CorrelationRigidNet, whose re-warp uses its grid, "
            "exports by tracing only)")

    def forward_stages(self, moving: torch.Tensor, fixed: torch.Tensor,
                       fixed_weight: torch.Tensor | None = None, context: torch.Tensor | None = None
                       ) -> dict[str, Any]:
        """Both estimates (see :data:`STAGE_KEYS`); ``moving``, ``fixed``: ``[B, C, x, y, z]`` on the network grid.

        ``fixed_weight``: optional ``[B, 1, x, y, z]`` match-region weights in [0, 1] on the fixed grid (region of
        interest, bone, body without couch): they weigh the learned network's cells in its rigid fit (a regression
        with ``forward_levels``; an MLP regression sees the whole grid) and the fine stage's residuals.
        ``context``: the CT on the context grid for a regression that takes one (``takes_context``); such a
        regression also takes it as the second block of ``fixed``'s channels (``[B, 2 * C, ...]``), which is how
        :class:`~monai_rigidreg.registration.RigidRegistrar` passes it through the cascade. Training (``train()``
        mode) adds the levels' match records under ``"matches"``.
        """
        extra: dict[str, Any] = {}
        c = self.in_channels
        if getattr(self.regression, "takes_context", False) and context is None and fixed.shape[1] == 2 * c:
            fixed, context = fixed[:, :c], fixed[:, c:]  # the registrar's form: the context as more fixed channels
        if getattr(self.regression, "takes_context", False):
            levels, records = self.regression.forward_levels(moving, fixed, context, fixed_weight, matches=True)
            coarse = levels[-1]
            extra["levels"] = levels[:-1]
            if self.training:
                extra["matches"] = records
        elif context is not None:
            raise ValueError(f"{type(self.regression).__name__} takes no CT context")
        elif hasattr(self.regression, "forward_levels"):
            levels = (self.regression.forward_levels(moving, fixed) if fixed_weight is None
                      else self.regression.forward_levels(moving, fixed, fixed_weight))
            coarse = levels[-1]
            extra["levels"] = levels[:-1]
        else:
            coarse = self.regression.forward_pair(moving, fixed)
        if self.fine_stage is None or not self.fine_stage_enabled:
            return {"params": coarse, "coarse": coarse,
                    "from_coarse": torch.ones(coarse.shape[0], dtype=torch.bool, device=coarse.device), **extra}
        params, from_coarse = self.fine_stage(moving, fixed, coarse, fixed_weight)
        return {"params": params, "coarse": coarse, "from_coarse": from_coarse, **extra}

    def forward_pair(self, moving: torch.Tensor, fixed: torch.Tensor,
                     fixed_weight: torch.Tensor | None = None) -> torch.Tensor:
        """The final estimate ``[B, 6]`` (mm, degrees, fixed -> moving about the grid centre)."""
        return self.forward_stages(moving, fixed, fixed_weight)["params"]

    def forward(self, image: torch.Tensor, stages: bool = False, fixed_weight: torch.Tensor | None = None) -> Any:
        """``[B, 2 * C, x, y, z]`` (moving, fixed) -> ``[B, 6]`` (or the :meth:`forward_stages` dict with
        ``stages=True``); a regression that takes a CT context (``takes_context``) also accepts ``[B, 3 * C, ...]``,
        the third block of channels the CT on its context grid."""
        c = self.in_channels
        context = None
        if getattr(self.regression, "takes_context", False) and image.shape[1] == 3 * c:
            context = image[:, 2 * c:]
            image = image[:, : 2 * c]
        if image.shape[1] != 2 * c:
            raise ValueError(f"expected {2 * c} channels (moving, fixed), got {image.shape[1]}")
        out = self.forward_stages(image[:, :c], image[:, c:], fixed_weight, context)
        return out if stages else out["params"]


def _accept_flat_regression_keys(module: nn.Module, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
    """Load-time hook: ``encoder.*``, ``fusion.*``, ``mlp.*``, ``head.*``, ``bounds`` (bundle 0.2.x) ->
    ``regression.*``; keys that already carry a sub-module prefix are left alone."""
    own = {name.split(".", 1)[0] for name in module.regression.state_dict()}
    for key in list(state_dict):
        if not key.startswith(prefix):
            continue
        rest = key[len(prefix):]
        if rest.split(".", 1)[0] in own:
            state_dict[f"{prefix}regression.{rest}"] = state_dict.pop(key)
