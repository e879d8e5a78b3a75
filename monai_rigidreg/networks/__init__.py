"""Networks of monai-rigidreg: the dual-encoder rigid regressor, the rigid spatial transformer, cascades."""

from __future__ import annotations

from monai_rigidreg.networks.cascade import CascadeRegistration, cascade_register
from monai_rigidreg.networks.rigid_net import FUSIONS, DualEncoderRigidNet
from monai_rigidreg.networks.transformer import RigidTransformer

__all__ = ["DualEncoderRigidNet", "FUSIONS", "RigidTransformer", "cascade_register", "CascadeRegistration"]
