"""Networks of monai-rigidreg: the learned regression, the weight-free Gauss-Newton stage, their composition, the
rigid spatial transformer and cascades."""

from __future__ import annotations

from monai_rigidreg.networks.cascade import CascadeRegistration, cascade_register
from monai_rigidreg.networks.context_net import ContextCorrelationNet
from monai_rigidreg.networks.correlation_net import CorrelationRigidNet, local_cost_volume, weighted_rigid_fit
from monai_rigidreg.networks.gauss_newton import GaussNewtonStage
from monai_rigidreg.networks.rigid_net import FUSIONS, DualEncoderRigidNet
from monai_rigidreg.networks.transformer import RigidTransformer
from monai_rigidreg.networks.two_stage import STAGE_KEYS, TwoStageRigidNet

__all__ = [
    "ContextCorrelationNet",
    "CorrelationRigidNet",
    "local_cost_volume",
    "weighted_rigid_fit",
    "DualEncoderRigidNet",
    "FUSIONS",
    "GaussNewtonStage",
    "TwoStageRigidNet",
    "STAGE_KEYS",
    "RigidTransformer",
    "cascade_register",
    "CascadeRegistration",
]
