"""How much of the CBCT the CT covers, and a match restricted to that part where it does not cover all of it.

A planning CT shorter than the CBCT (a short scan, a CT cut to the target region) leaves part of the CBCT's anatomy
with no CT behind it: there the CT is padded with air, and a match over the whole field of view pulls the CBCT's
anatomy onto that air, and the CT's cut face (tissue ending in a plane) onto anatomy the CBCT shows continuing.

:func:`overlap_shares` measures it on a coarse sampling of the CBCT's field of view (:func:`FovSample`): the share of
the field of view whose point lies inside the CT's box under an estimate (``fov_in_ct``), and the share of the
CBCT's tissue that does (``tissue_in_ct``), the one that matters: a head CBCT whose field of view reaches past a
small head CT shows only air there, as the padding does. Where the tissue share under the identity or under the
network's estimate is below :data:`OVERLAP_WEIGHTED_BELOW`, the registrar multiplies :func:`ct_domain_weight` (the
CT's box less :data:`CT_EDGE_MARGIN_MM` at its faces) into the match weights of the network's runs, the last level
and the confidence signals, so the match uses the part of the CBCT the CT covers; elsewhere nothing changes (the
estimates of pairs the CT covers are those of 0.4.9, bit for bit). ``details.overlap`` reports both shares under the
identity and under the estimate; an estimate whose tissue share is below :data:`OVERLAP_FLAG_BELOW` is flagged
(``details.flag_reasons``: ``"overlap"``). Inputs whose boxes overlap by less than 5 % of the smaller are refused
before anything runs (:func:`~monai_rigidreg.registration.inputs.read_inputs`), and so is a CBCT whose field of view
holds no tissue (:data:`MIN_TISSUE_SHARE`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import Grid, grid_points, invert_matrix, target_registration_error, transform_points
from monai_rigidreg.registration.match_region import weight_on_grid

if TYPE_CHECKING:
    import torch

    from monai_rigidreg.registration.state import RegistrationState

__all__ = ["CT_EDGE_MARGIN_MM", "OVERLAP_WEIGHTED_BELOW", "OVERLAP_FLAG_BELOW", "TISSUE_HU", "MIN_TISSUE_SHARE",
           "AMBIGUOUS_DISTANCE_MM",
           "FOV_SAMPLE_MAX_POINTS",
           "FovSample", "fov_sample", "overlap_shares", "ct_domain_weight", "OverlapStage"]

CT_EDGE_MARGIN_MM = 8.0
"""The CT's faces are left out of the match by this much (mm) where the CT does not cover the CBCT's tissue: the
local-contrast features (4-16 mm) see the cut face, where tissue ends in a plane, as an edge the CBCT does not have.
The same margin the last level and the fine stage leave at the CBCT's own field-of-view edge
(``support_erosion_mm``)."""
OVERLAP_WEIGHTED_BELOW = 0.99
"""Where less than this share of the CBCT's tissue in view lies inside the CT's box (less
:data:`CT_EDGE_MARGIN_MM`), under the identity or under the network's estimate, the match is restricted to the CT's
box."""
OVERLAP_FLAG_BELOW = 0.2
"""An estimate under which less than this share of the CBCT's tissue in view lies inside the CT's box is flagged:
too little of the CBCT is matched to trust it. On the 305 cases of the shipped calibration (74 with the CT cut to a
part of its length; ``python -m benchmarks.confidence.bench_confidence_calibration --fit --overlap-flag-below``,
``docs/trust.md``) the rule caught no failure that the calibrated confidence missed at any threshold from 0 to 0.35,
and flagged right results: 10 of 134 default-path successes at 0.35 (0.4.9's value), 2 at 0.2."""
TISSUE_HU = -500.0
"""CBCT voxels above this (HU) are tissue for :func:`overlap_shares` (air and lung below)."""
AMBIGUOUS_DISTANCE_MM = 10.0
"""Another start's estimate this far (mm, mean over the network grid's points) from the kept one counts as a distinct
pose for the ``"ambiguous"`` flag (``details.overlap.other_starts.alternative_ncc_gap``). Farther than the
swapped-input estimate's 3 mm (``confidence.SWAP_AGREE_MM``): the other starts' last levels may stop short of their
optimum; on a clinical-geometry head pair one ended 5.3 mm from a right estimate (0.9 mm) at an NCC 0.0009 below it,
while the distinct basin the rule is for lay 33-35 mm away (a 66.8 mm failure; ``docs/trust.md``). Chosen on these
few cases."""
MIN_TISSUE_SHARE = 0.002
"""A CBCT whose field of view holds less than this share of tissue voxels is refused: nothing to register."""


FOV_SAMPLE_MAX_POINTS = 20000
"""At most this many samples of the field of view are kept (a share's sampling error stays under about 0.4 %, for
the 99 % test of :data:`OVERLAP_WEIGHTED_BELOW` under 0.1 %): a 128^3 CBCT at 1.5 mm (block-averaged to 3 mm) gave
208 000, and each overlap share then cost 0.1-0.17 s (three per registration)."""


@dataclass
class FovSample:
    """The CBCT's field of view sampled at about 4 mm: ``points`` ``[N, 3]`` (LPS mm, CBCT frame) and ``tissue``
    ``[N]`` (the block-averaged CBCT above :data:`TISSUE_HU`)."""

    points: np.ndarray
    tissue: np.ndarray

    @property
    def tissue_share(self) -> float:
        """Share of the field of view's samples that are tissue (0 for an empty sample)."""
        return float(self.tissue.mean()) if len(self.tissue) else 0.0


def fov_sample(moving: sitk.Image, fov: sitk.Image, spacing_mm: float = 4.0) -> FovSample:
    """:class:`FovSample` of ``moving`` (HU) inside ``fov`` (its field-of-view mask on its grid), block-averaged by
    integer factors to about ``spacing_mm`` (``BinShrink``), then every k-th sample in raster order so that at most
    :data:`FOV_SAMPLE_MAX_POINTS` remain."""
    factors = [max(1, int(spacing_mm / s + 1e-6)) for s in moving.GetSpacing()]
    small = sitk.BinShrink(sitk.Cast(moving, sitk.sitkFloat32), factors) if max(factors) > 1 else moving
    fov_small = sitk.BinShrink(sitk.Cast(fov != 0, sitk.sitkFloat32), factors) if max(factors) > 1 else sitk.Cast(
        fov != 0, sitk.sitkFloat32)
    values = sitk.GetArrayViewFromImage(small)  # [z, y, x]
    inside = sitk.GetArrayViewFromImage(fov_small) >= 0.5
    idx = np.argwhere(inside)[:, ::-1].astype(np.float64)  # (i, j, k)
    tissue = values[inside] > TISSUE_HU
    stride = max(1, -(-len(idx) // FOV_SAMPLE_MAX_POINTS))  # every stride-th sample in raster order
    idx, tissue = idx[::stride], tissue[::stride]
    points = transform_points(Grid.from_sitk(small).index_to_physical(), idx) if len(idx) else np.zeros((0, 3))
    return FovSample(points, tissue)


def _inside_box(fixed_grid: Grid, points: np.ndarray, margin_mm: float) -> np.ndarray:
    """Which CT-frame ``points`` ``[N, 3]`` lie inside the CT's voxel box (half a voxel beyond the outer voxel
    centres) less ``margin_mm`` at every face."""
    idx = transform_points(fixed_grid.physical_to_index(), points)
    lo = -0.5 + margin_mm / np.asarray(fixed_grid.spacing)
    hi = np.asarray(fixed_grid.size) - 0.5 - margin_mm / np.asarray(fixed_grid.spacing)
    return np.all((idx >= lo) & (idx <= hi), axis=1)


def overlap_shares(fixed_grid: Grid, sample: FovSample, matrix: np.ndarray | None = None,
                   margin_mm: float = 0.0) -> dict[str, float]:
    """How much of the CBCT's field of view the CT covers under an estimate.

    Args:
        fixed_grid: the CT's grid.
        sample: the CBCT's field of view (:func:`fov_sample`).
        matrix: the estimate, 4x4 fixed -> moving (LPS mm; ``None``: the identity, the scanners' coordinates).
        margin_mm: the CT's box less this at every face.

    Returns:
        ``{"fov_in_ct": share of the field of view's samples, "tissue_in_ct": share of its tissue samples}`` whose
        CT-frame point (``matrix^-1`` of the CBCT point) lies inside the CT's box; NaN where there are none.
    """
    points = sample.points if matrix is None else transform_points(invert_matrix(matrix), sample.points)
    inside = _inside_box(fixed_grid, points, margin_mm)
    n_tissue = int(sample.tissue.sum())
    return {"fov_in_ct": float(inside.mean()) if len(inside) else float("nan"),
            "tissue_in_ct": float(inside[sample.tissue].mean()) if n_tissue else float("nan")}


def ct_domain_weight(fixed: sitk.Image, margin_mm: float = CT_EDGE_MARGIN_MM, spacing_mm: float = 4.0) -> sitk.Image:
    """float32 weight image on the CT's physical space (a coarse grid of about ``spacing_mm`` with the CT's
    orientation): 1 inside the CT's box less ``margin_mm`` at every face, 0 at the faces. Multiplied into the match
    weights (:func:`~monai_rigidreg.registration.match_region.weight_on_grid`: bilinear, 0 outside), it leaves out
    the CBCT's part that the CT does not cover and the CT's cut faces."""
    grid = Grid.from_sitk(fixed)
    size = np.asarray(grid.size, dtype=np.float64)
    spacing = np.asarray(grid.spacing, dtype=np.float64)
    box = size * spacing  # the voxel box, half a voxel beyond the outer voxel centres
    n = np.maximum(2, np.ceil(box / spacing_mm).astype(int) + 1)
    step = box / (n - 1)
    origin_index = np.full(3, -0.5)  # the coarse grid's first sample sits on the box's corner
    origin = transform_points(grid.index_to_physical(), origin_index[None])[0]
    coords = [np.arange(k) * s for k, s in zip(n, step)]  # distance from the corner along each axis
    inside = [(c >= margin_mm - 1e-6) & (c <= b - margin_mm + 1e-6) for c, b in zip(coords, box)]
    arr = (inside[2][:, None, None] & inside[1][None, :, None] & inside[0][None, None, :]).astype(np.float32)
    out = sitk.GetImageFromArray(arr)  # [z, y, x]
    out.SetSpacing([float(v) for v in step])
    out.SetOrigin([float(v) for v in origin])
    out.SetDirection(fixed.GetDirection())
    return out


class OverlapStage:
    """The overlap checks of :class:`~monai_rigidreg.registration.RigidRegistrar`, between its stages: the field of
    view sampled and an empty one refused (stage 1), the match restricted to the CT's box where the CT does not
    cover the CBCT's tissue under the identity (stage 2) or under the network's estimate (after stage 5), and the
    shares under the final estimate reported (stage 8). For a class with the registrar's ``_native``,
    ``_image_match`` and ``_on_grid``."""

    _native: Callable[..., tuple[np.ndarray, dict[str, Any]]]
    _image_match: Callable[..., list[float]]
    _on_grid: Callable[..., Any]

    @staticmethod
    def _fixed_support(state: RegistrationState) -> torch.Tensor | None:
        """Where the CT has data on the winning run's grid (``[x, y, z]``), where the match is restricted to the CT's
        box (``state.domain``); ``None`` elsewhere."""
        if state.domain is None:
            return None
        return weight_on_grid([state.domain], state.run.grid)[0]

    def _sample_fov(self, state: RegistrationState) -> None:
        """Stage 1: the CBCT's field of view sampled (``state.fov_sample``); a field of view without tissue is
        refused (:data:`MIN_TISSUE_SHARE`)."""
        if state.fov_img is None:
            return
        state.fov_sample = fov_sample(state.inputs.moving, state.fov_img)
        share = state.fov_sample.tissue_share
        if share < MIN_TISSUE_SHARE:
            raise InputError(f"the moving (CBCT) image's field of view holds no tissue ({100 * share:.2f} % of it "
                             f"above {TISSUE_HU:g} HU): there is nothing to register (an empty or blank CBCT?)")

    def _within_ct(self, state: RegistrationState, matrix: np.ndarray | None, pose: bool) -> None:
        """Restrict the match to the CT's box (``state.domain``) where the CT leaves part of the CBCT's tissue
        uncovered under ``matrix`` (``None``: the identity): in the last level's and the checks' weights, and with
        ``pose`` in the network's runs too. Records ``details.overlap.matched_within_ct`` (under which pose)."""
        if state.fov_sample is None or state.domain is not None:
            return
        shares = overlap_shares(state.inputs.fixed_grid, state.fov_sample, matrix, CT_EDGE_MARGIN_MM)
        if not shares["tissue_in_ct"] < OVERLAP_WEIGHTED_BELOW:
            return
        state.domain = ct_domain_weight(state.inputs.fixed)
        state.weights = [*state.weights, state.domain]
        if pose:
            state.pose_weights = [*state.pose_weights, state.domain]
        state.details.setdefault("overlap", {})["matched_within_ct"] = "identity" if matrix is None else "estimate"

    def _runner_up_within_ct(self, state: RegistrationState, refined: np.ndarray) -> tuple[np.ndarray, bool]:
        """Where the match is restricted to the CT's box, the other starts also get their last level (the one that
        matched best of the others, and the identity's), and the best image match after it goes on (``refined``: the
        winning start's, fixed -> moving). With part of the CBCT uncovered, the network's estimates before the last
        level are a poorer guide to the basin: on a pair cut to half the CT, search starts matched better than the
        identity's before the last level and ended 3.4-4.7 mm off, the identity's 0.5 mm. Returns the estimate and
        whether another start's replaced it (then ``state.run`` is that start's run); records
        ``details.overlap.other_starts``."""
        if state.domain is None or not state.other_runs:
            return refined, False
        others = state.other_runs[:1] + [r for r in state.other_runs[1:] if np.allclose(r.start, np.eye(4))]
        finals = [self._native(state.inputs.fixed, state.inputs.moving, r.total, state.fov_img, state.weights,
                               r.grid, region=state.weight_img is not None) for r in others]
        region = state.weight_img if state.weight_img is not None else state.domain
        scores = self._image_match(state.inputs.fixed, state.inputs.moving, state.fov_img,
                                   [refined, *[m for m, _ in finals]], region)
        best = int(np.argmax(np.nan_to_num(np.asarray(scores, dtype=np.float64), nan=-np.inf)))
        # how far each candidate ended from the kept one (the network grid's points), and how close the nearest
        # distant one came in the image match (calibration.AMBIGUOUS_NCC_GAP, with the twin's)
        poses = [refined, *[m for m, _ in finals]]
        points = grid_points(state.run.grid, 8)
        distance = [float(target_registration_error(p, poses[best], points)) for p in poses]
        gaps = [abs(float(scores[best]) - float(v)) for k, v in enumerate(scores)
                if k != best and distance[k] > AMBIGUOUS_DISTANCE_MM and np.isfinite(v)]
        state.details.setdefault("overlap", {})["other_starts"] = {
            "estimate_ncc": round(float(scores[0]), 4), "other_ncc": [round(float(v), 4) for v in scores[1:]],
            "distance_mm": [round(v, 2) for k, v in enumerate(distance) if k != best], "replaced": best > 0,
            **({"alternative_ncc_gap": round(min(gaps), 4)} if gaps else {})}
        if best == 0:
            return refined, False
        run, (matrix, detail) = others[best - 1], finals[best - 1]
        state.other_runs = [state.run, *[r for r in state.other_runs if r is not run]]
        state.run = run
        state.details["native_level"] = detail
        state.details["start"] = "identity" if np.allclose(run.start, np.eye(4)) else "search"
        state.fov_t = self._on_grid(state.fov_img, run.grid, "nearest", 0.0, run.sampling)[0]
        return matrix, True

    def _overlap_report(self, state: RegistrationState, matrix: np.ndarray) -> float:
        """``details.overlap``: the shares (:func:`overlap_shares`) under the identity and under the final estimate
        ``matrix`` (fixed -> moving); returns the estimate's tissue share (NaN: not measured)."""
        if state.fov_sample is None:
            return float("nan")
        grid = state.inputs.fixed_grid
        report = state.details.setdefault("overlap", {})
        report.setdefault("matched_within_ct", None)
        report["identity"] = {k: round(v, 4) for k, v in overlap_shares(grid, state.fov_sample).items()}
        report["estimate"] = {k: round(v, 4) for k, v in overlap_shares(grid, state.fov_sample, matrix).items()}
        return float(report["estimate"]["tissue_in_ct"])
