"""The training criterion: warp the moving volume by the predicted parameters and apply the composite loss."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from monai_rigidreg.core.geometry import Grid, params_to_matrix_torch
from monai_rigidreg.core.network_grid import NetworkGridSpec
from monai_rigidreg.losses import RigidRegistrationLoss, match_loss
from monai_rigidreg.networks import RigidTransformer

__all__ = ["RegistrationCriterion", "canonical_grid"]


def canonical_grid(size: Sequence[int], spacing: Sequence[float]) -> Grid:
    """The network grid centred on the origin (:meth:`~monai_rigidreg.core.network_grid.NetworkGridSpec.canonical`).

    Every item's network grid is axis-aligned, of the same size and spacing, and centred on its fixed image
    centre, and the parameters are expressed about that centre; the voxel-space action of the parameters is
    therefore the same for every item, and one origin-centred grid serves the whole batch.
    """
    return NetworkGridSpec(size, spacing).canonical()


class RegistrationCriterion(nn.Module):
    """``loss_function(pred, targets) -> scalar`` for MONAI engines, with the per-term values kept for logging.

    ``pred`` is ``[B, 6]`` (mm / degrees), or the stage dictionary of
    :meth:`~monai_rigidreg.networks.TwoStageRigidNet.forward_stages` (``{"params": [B, 6], "coarse": [B, 6], ...}``,
    what :class:`~monai_rigidreg.engine.StagedInferer` returns in training); ``targets`` comes from
    :class:`~monai_rigidreg.engine.RegistrationPrepareBatch`. The moving volume (and its field-of-view mask) is
    warped onto the fixed grid by :class:`~monai_rigidreg.networks.RigidTransformer`, then
    :class:`~monai_rigidreg.losses.RigidRegistrationLoss` scores it; its supervised term uses ``targets["params"]``.

    Args:
        network_size, network_spacing: the network grid (voxels, mm).
        loss: the composite loss (default: the paper's weights with a supervised term of weight 1 per mm).
        image_loss_pool: average-pool factor applied to the warped/fixed volumes (and the mask) before the image
            terms (SSIM, NCC, MI, grid gradient): at factor 2 they see 8x fewer voxels (and still 8 mm structure
            on a 4 mm grid). The supervised term samples the same physical extent. 1: no pooling.
        w_coarse: weight (per mm) of the supervised point distance of the coarse (regression) estimate, added when
            ``pred`` carries one (``pred["coarse"]``): the fine stage starts from a detached copy of it, so this
            term is what trains the regression of a two-stage network.
        w_levels: weight (per mm, shared) of the supervised point distance of each intermediate level estimate
            (``pred["levels"]``, from a regression with levels such as
            :class:`~monai_rigidreg.networks.CorrelationRigidNet`): deep supervision of its coarse level.
        w_match: weight (per nat) of each level's match loss (:func:`~monai_rigidreg.losses.match_loss`: the
            cross-entropy of every cell's match against its true position), where ``pred["matches"]`` carries the
            levels' match records (:class:`~monai_rigidreg.networks.ContextCorrelationNet` in training).

    Attributes:
        last_terms: ``{term: float}`` of the last call (unweighted), for handlers.
    """

    def __init__(
        self,
        network_size: Sequence[int],
        network_spacing: Sequence[float],
        loss: RigidRegistrationLoss | None = None,
        image_loss_pool: int = 2,
        w_coarse: float = 0.5,
        w_levels: float = 0.5,
        w_match: float = 0.0,
    ) -> None:
        super().__init__()
        self.w_match = float(w_match)
        self.w_coarse = float(w_coarse)
        self.w_levels = float(w_levels)
        spec = NetworkGridSpec(network_size, network_spacing)
        self.grid = spec.canonical()
        self.image_loss_pool = int(image_loss_pool)
        self.loss = loss if loss is not None else RigidRegistrationLoss(w_sup=1.0)
        self.warp = RigidTransformer(self.grid)
        self.warp_mask = RigidTransformer(self.grid, mode="nearest")
        k = max(1, self.image_loss_pool)
        self._pooled_grid = spec.pooled(k).canonical()
        self.last_terms: dict[str, float] = {}

    def forward(self, pred: torch.Tensor | Mapping[str, torch.Tensor], targets: Mapping[str, torch.Tensor]
                ) -> torch.Tensor:
        coarse = None
        levels: list = []
        matches: list = []
        if isinstance(pred, Mapping):
            matches = list(pred.get("matches") or [])
            pred, coarse, levels = pred["params"], pred.get("coarse"), list(pred.get("levels") or [])
        warped = self.warp(targets["moving"], pred)
        fixed = targets["fixed"]
        mask = targets.get("mask")
        if mask is not None:
            mask = self.warp_mask(mask, pred.detach())
        grid = self.grid
        if self.image_loss_pool > 1:
            k = self.image_loss_pool
            warped, fixed = F.avg_pool3d(warped, k), F.avg_pool3d(fixed, k)
            mask = None if mask is None else (F.avg_pool3d(mask.float(), k) > 0.999).to(warped.dtype)
            grid = self._pooled_grid
        terms = self.loss(warped, fixed, pred, targets.get("params"), mask, grid)
        self.last_terms = terms.as_dict()
        total = terms.total
        # a network without a fine stage returns its regression estimate as both (the same tensor): supervised once
        if coarse is not None and coarse is not pred and self.w_coarse != 0 and targets.get("params") is not None:
            sup_coarse = self.loss.sup_term(coarse, targets["params"], self.grid)
            self.last_terms["coarse"] = float(sup_coarse.detach())
            total = total + self.w_coarse * sup_coarse
        if levels and self.w_levels != 0 and targets.get("params") is not None:
            for i, level in enumerate(levels):
                sup_level = self.loss.sup_term(level, targets["params"], self.grid)
                self.last_terms[f"level{i}"] = float(sup_level.detach())
                total = total + self.w_levels * sup_level
        if matches and self.w_match != 0 and targets.get("params") is not None:
            truth = params_to_matrix_torch(targets["params"].to(torch.float64))
            for i, record in enumerate(matches):
                term = match_loss(record, truth)
                self.last_terms[f"match{i}"] = float(term.detach())
                total = total + self.w_match * term.to(total.dtype)
        return total
