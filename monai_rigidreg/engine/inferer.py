"""The training inferer: the network's stage estimates as the engine's prediction (for the criterion)."""

from __future__ import annotations

from typing import Any

import torch
from monai.inferers import Inferer
from torch import nn

__all__ = ["StagedInferer"]


class StagedInferer(Inferer):
    """``inferer(inputs, network)`` for MONAI's ``SupervisedTrainer`` with a two-stage network.

    Calls ``network(inputs, stages=True)`` (a :class:`~monai_rigidreg.networks.TwoStageRigidNet`, possibly wrapped
    in ``DistributedDataParallel``, whose ``forward`` passes the keyword on) and returns its dictionary
    ``{"params": [B, 6], "coarse": [B, 6], "from_coarse": [B]}``, so
    :class:`~monai_rigidreg.engine.RegistrationCriterion` receives the regression's estimate as a value. A network
    without that keyword (e.g. a bare :class:`~monai_rigidreg.networks.DualEncoderRigidNet`) is called plainly and
    its ``[B, 6]`` output returned. Evaluation keeps MONAI's ``SimpleInferer`` (the final ``[B, 6]`` estimate).
    """

    def __call__(self, inputs: torch.Tensor, network: nn.Module, *args: Any, **kwargs: Any) -> Any:
        inner = network.module if isinstance(network, nn.parallel.DistributedDataParallel) else network
        if hasattr(inner, "forward_stages"):
            return network(inputs, *args, stages=True, **kwargs)
        return network(inputs, *args, **kwargs)
