"""Losses of monai-rigidreg."""

from __future__ import annotations

from monai_rigidreg.core.image_ops import masked_ncc
from monai_rigidreg.losses.match_loss import match_loss
from monai_rigidreg.losses.rigid_loss import (
    LossTerms,
    RigidRegistrationLoss,
    grid_gradient_penalty,
    image_gradient_difference,
    masked_mutual_information,
    masked_ssim,
    supervised_point_distance,
)

__all__ = ["LossTerms", "RigidRegistrationLoss", "grid_gradient_penalty", "image_gradient_difference",
           "masked_mutual_information", "masked_ncc", "masked_ssim", "match_loss", "supervised_point_distance"]
