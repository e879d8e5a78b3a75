"""The last level: Gauss-Newton alignment over the whole CBCT field of view at the inputs' own resolution.

The network (learned estimate and Gauss-Newton stage) works on a 128 mm cube at 2 mm around the CBCT centre. A
clinical CBCT covers more (a 250 mm field of view, 150-200 mm long) and is often finer; elastix, given the whole
images, uses all of it. :func:`refine_native` adds one level after the network: the same contrast-robust features
(:func:`~monai_rigidreg.networks.gauss_newton.alignment_features`, intensity and local contrast) and the same
inverse-compositional Gauss-Newton steps with the smooth intensity bias
(:func:`~monai_rigidreg.networks.gauss_newton.gauss_newton_align`), on an axis-aligned grid that covers the CBCT's
field of view (capped at ``max_extent_mm``) at the finer of the two images' spacings (not below ``min_spacing_mm``,
and coarser where the voxel count would exceed ``max_voxels``).

Frames: the grid is placed in the CT (fixed) frame around the CT point the current estimate maps to the CBCT
centre; the CBCT is sampled through the estimate ``T`` onto it (one interpolation), the steps estimate a residual
``C`` from the identity, and the result is ``T o C`` (fixed -> moving, LPS mm). Weights: the CBCT's field of view as
placed by ``T``, eroded by ``support_erosion_mm`` (its own edge is no anatomy), times an optional match-region
weight on the CT.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.core.geometry import (
    Grid,
    grid_points,
    invert_matrix,
    matrix_to_params,
    params_to_matrix,
    transform_points,
)
from monai_rigidreg.core.grid_sampling import normalize_hu, sitk_on_grid
from monai_rigidreg.core.image_ops import erode
from monai_rigidreg.networks.gauss_newton import alignment_features, gauss_newton_align
from monai_rigidreg.registration.confidence import swap_inputs
from monai_rigidreg.registration.match_region import weight_on_grid
from monai_rigidreg.registration.precision import expected_tre_mm, pose_covariance
from monai_rigidreg.registration.search import matrix_distance_mm

if TYPE_CHECKING:
    from monai_rigidreg.registration.state import Background, RegistrationState

__all__ = ["CANDIDATE_SHARE_MAX", "EARLY_SWAP_MAX_CHANGE_MM", "FINAL_NORM_MAX_MM", "FINE_STAGE_CHOICE_MM",
           "NATIVE_CONVERGED_MM", "NATIVE_MAX_PASSES", "LastLevelStage", "native_grid", "refine_native",
           "support_reach"]

NATIVE_CONVERGED_MM = 0.5
"""The last level runs again from its own result while its latest pass moved the estimate by more than this (mm, the
mean over the network grid's points), up to :data:`NATIVE_MAX_PASSES` passes. One pass (four Gauss-Newton steps, each
re-using the CBCT sampled through the pass's start) stops short when it starts several millimetres away: on a
clinical-geometry head pair without the search one pass moved the estimate 4.6 mm and left it 7.9 mm off; run until
a pass moved it under 0.5 mm (6 passes, 15.8 mm in all) it ended 0.6 mm off (a CT cut at the isocentre: 9.0 ->
1.1 mm). A converged estimate is moved a few tenths of a millimetre by the first pass, so most pairs run one pass.
Measured with ``python -m benchmarks.confidence.bench_confidence_calibration`` (``docs/trust.md``)."""
NATIVE_MAX_PASSES = 6
"""At most this many passes of the last level (:data:`NATIVE_CONVERGED_MM`); ``details.native_level.passes`` and
``last_pass_mm`` say how many ran and how far the last one moved the estimate."""

EARLY_SWAP_MAX_CHANGE_MM = 1.0
"""The confidence check's swapped-input estimate, started beside the last level with the CT masked by the field of
view as the network's estimate places it, is used when the last level moved that estimate by at most this (mm,
``details.native_level.change_mm``, the mean over the network grid's points); beyond it the twin is computed again
from the refined estimate (``details.swap_estimate``: ``"beside the last level"`` or ``"after the last level"``).
On the clinical-geometry pairs the last level moves a converged estimate by a few tenths of a millimetre."""

FINAL_NORM_MAX_MM = 1.5
"""The last level's final pass on the normalised local contrast (``RigidRegistrar(native_final_norm_mm=)``, off by
default) is kept where it moves the converged estimate by at most this (mm, the mean over the network grid's
points): the shading bias it removes measured up to about 0.9 mm (``docs/trust.md``); a larger move is another
optimum, not a correction."""

FINE_STAGE_CHOICE_MM = 5.0
"""Where the network's fine stage moved the learned regression's estimate by more than this (mm, the mean over the
network grid's points), the last level also runs from the regression's estimate and the better image match goes on
(``LastLevelStage._fine_stage_choice``, ``RigidRegistrar(fine_stage_choice_mm=)``). On a large patient's clinical
CBCTs the fine stage's coarse levels carried right estimates 24-62 mm away; where it corrects a regression a few
millimetres off, both end poses agree or the fine stage's matches better (``docs/results.md``, "The fine-stage
choice")."""

CANDIDATE_SHARE_MAX = 0.8
"""The last level's steps go over the candidate voxels (:func:`support_reach`) only where these are at most this
share of its grid: gathered at arbitrary voxels, a step costs about 1.1-1.2x per voxel what it costs over the whole
grid (``python -m benchmarks.speed.bench_network_paths``'s last-level rows: with 69 % of a 102^3 grid 0.31 s instead of
0.39 s, with 97 % of a paper-protocol 64^3 grid 0.107 s instead of 0.091 s)."""


def native_grid(fixed: sitk.Image, moving: sitk.Image, matrix: np.ndarray, min_spacing_mm: float = 1.0,
                max_extent_mm: float = 256.0, max_voxels: int = 1_500_000) -> Grid:
    """The last level's grid (CT frame): centred on ``T^-1`` of the CBCT centre, the CBCT's extent (capped), the
    finer of the two images' spacings (at least ``min_spacing_mm``; coarser where it would hold more voxels than
    ``max_voxels``)."""
    m_grid = Grid.from_sitk(moving)
    lo, hi = m_grid.physical_extent()
    extent = np.minimum(np.asarray(hi) - np.asarray(lo) + np.asarray(m_grid.spacing), max_extent_mm)
    spacing = max(min_spacing_mm, min(min(fixed.GetSpacing()), min(moving.GetSpacing())))
    while np.prod(np.floor(extent / spacing)) > max_voxels:
        spacing *= 1.25
    size = [max(8, int(np.floor(e / spacing))) for e in extent]
    center = transform_points(invert_matrix(matrix), m_grid.center()[None])[0]
    return Grid.centered(size, (spacing,) * 3, center)


@torch.no_grad()
def refine_native(
    fixed: sitk.Image,
    moving: sitk.Image,
    matrix: np.ndarray,
    moving_fov: sitk.Image,
    weights: Sequence[sitk.Image] = (),
    iterations: int = 4,
    hu_range: tuple[float, float] = (-1200.0, 2000.0),
    highpass_sigma_mm: float = 16.0,
    highpass_weight: float = 3.0,
    support_erosion_mm: float = 8.0,
    bias_degree: int = 2,
    min_spacing_mm: float = 1.0,
    max_extent_mm: float = 256.0,
    max_voxels: int = 1_500_000,
    device: str | torch.device = "cpu",
    tolerance: tuple[float, float] | None = (0.01, 0.01),
    secant: bool = False,
    report: dict[str, Any] | None = None,
    contrast_norm_sigma_mm: float | None = None,
    intensity_weight: float = 1.0,
) -> tuple[np.ndarray, Grid]:
    """Refine a fixed -> moving 4x4 ``matrix`` (LPS mm) at native resolution over the CBCT field of view.

    Args:
        fixed, moving: the CT and the CBCT (HU), any grids.
        matrix: the current estimate (e.g. the network's), fixed -> moving.
        moving_fov: the CBCT's field-of-view mask on its grid.
        weights: match-region weights on the CT's physical space (any grids; they multiply,
            :func:`~monai_rigidreg.registration.match_region.weight_on_grid`), e.g. the ROI weight and the body mask.
        iterations: Gauss-Newton steps (each at most 10 mm / 5 degrees).
        hu_range: the HU window mapped to [0, 1]. Its lower end lies below air on purpose: clipped at -1000 HU, the
            noise of a CBCT's air is clipped on one side only, its mean rises above the CT's, and the intensity
            channel pulls the body surface: measured in ``tests/test_precision.py``'s pair (25 HU noise), a 0.42 mm
            bias with -1000, 0.004 mm with -1200.
        highpass_sigma_mm, highpass_weight, contrast_norm_sigma_mm, intensity_weight: the feature maps (the fine
            stage's settings; :func:`~monai_rigidreg.networks.gauss_newton.alignment_features`).
        support_erosion_mm: erosion of the CBCT field of view.
        bias_degree: the smooth intensity bias estimated with the pose (-1: none).
        min_spacing_mm, max_extent_mm, max_voxels: the grid (:func:`native_grid`).
        device: where to compute.
        tolerance: ``(mm, degrees)``: stop early once a step is below both (``None``: all ``iterations``).
        secant: secant-scaled steps (see :func:`~monai_rigidreg.networks.gauss_newton.gauss_newton_align`).
        report: a dict to fill with the result's ``expected_tre_mm``, ``residual_var`` and ``weighted_voxels``
            (:func:`~monai_rigidreg.registration.precision.pose_covariance`; ``None``: not computed).

    Returns:
        ``(refined matrix, the grid used)``.
    """
    grid = native_grid(fixed, moving, matrix, min_spacing_mm, max_extent_mm, max_voxels)
    a, b = hu_range

    fixed_t = normalize_hu(sitk_on_grid(fixed, grid, "bilinear", a), a, b)[None].to(device)
    moving_t = normalize_hu(sitk_on_grid(moving, grid, "bilinear", a, matrix=matrix), a, b)[None].to(device)
    fov = (sitk_on_grid(moving_fov, grid, "nearest", 0.0, matrix=matrix) > 0).to(torch.float32)[None].to(device)
    radius = [max(1, round(support_erosion_mm / s)) for s in grid.spacing]
    support = erode(fov, radius)
    w = weight_on_grid(weights, grid)
    w = None if w is None else w[None].to(device)
    feats = alignment_features(torch.cat([moving_t, fixed_t]), grid.spacing, 1e-3, highpass_sigma_mm, highpass_weight,
                               contrast_norm_sigma_mm=contrast_norm_sigma_mm, intensity_weight=intensity_weight)
    candidates, reach = support_reach(fov, radius, grid.spacing, w)
    if float(candidates.float().mean()) > CANDIDATE_SHARE_MAX:
        candidates = None  # nearly the whole grid: the dense steps are cheaper
    # the support rides with the moving image (it was sampled through the estimate too): identity start
    eye = torch.eye(4, dtype=torch.float64, device=device)[None]
    residual = gauss_newton_align(feats[:1], feats[1:], grid, eye, iterations=iterations, weight=w,
                                  moving_support=support, bias_degree=bias_degree, tolerance=tolerance,
                                  secant=secant, candidates=candidates, reach_mm=reach)
    if report is not None:  # how precisely the images fix the pose at the result (registration.precision)
        cov, s2, n = pose_covariance(feats[:1], feats[1:], grid, residual, w, support, bias_degree)
        report.update(expected_tre_mm=round(expected_tre_mm(cov, grid), 4), residual_var=float(f"{s2:.4g}"),
                      weighted_voxels=int(n))
    return matrix @ residual[0].cpu().numpy(), grid


def support_reach(fov: torch.Tensor, radius: Sequence[int], spacing: Sequence[float],
                  weight: torch.Tensor | None) -> tuple[torch.Tensor, float]:
    """The voxels :func:`refine_native`'s Gauss-Newton steps sum over, and how far the estimate may move while they
    hold every voxel that can carry weight (``gauss_newton_align``'s ``candidates`` and ``reach_mm``).

    ``fov``: ``[1, 1, x, y, z]`` field of view (0/1) on the grid; ``radius``: the support's erosion (voxels per
    axis: the support is ``erode(fov, radius)``); ``weight``: ``[1, 1, x, y, z]`` or ``None``. Returns the
    ``[1, 1, x, y, z]`` boolean candidates, the field of view where the weight is positive, and
    ``min_a (radius_a + 1/2) * spacing_a`` (mm).

    Why: a voxel counts where the support warped by the estimate covers it (trilinear value > 0.999), which needs
    the grid voxel nearest to its sampling point in the support (that voxel's trilinear weight is at least 1/8). A
    voxel outside the field of view is more than ``radius_a`` voxels from every support voxel along some axis
    ``a`` (the support is the field of view eroded by a box), so its sampling point must have moved by at least
    ``(radius_a + 1/2) * spacing_a`` mm.
    """
    inside = fov > 0
    reach = min((r + 0.5) * s for r, s in zip(radius, spacing))
    return (inside if weight is None else inside & (weight > 0)), float(reach)


class LastLevelStage:
    """Stage 6 of :class:`~monai_rigidreg.registration.RigidRegistrar`: the last level at native resolution, with the
    confidence check's swapped-input estimate beside it. For a class with the registrar's ``network``, ``device``,
    ``estimate``, ``native_*`` settings, ``_in_background``, ``_fixed_support`` and ``_runner_up_within_ct``."""

    network: Any
    device: Any
    native_bias_degree: int
    native_bias_degree_roi: int
    native_highpass_sigma_mm: float | None
    native_max_voxels: int
    native_final_norm_mm: float | None
    estimate: Callable[..., np.ndarray]
    _in_background: Callable[..., Background]
    _fixed_support: Callable[..., torch.Tensor | None]
    _runner_up_within_ct: Callable[..., tuple[np.ndarray, bool]]
    _image_match: Callable[..., list[float]]
    fine_stage_choice_mm: float | None

    def _last_level(self, state: RegistrationState, swap_beside: bool = True) -> None:
        """Stage 6: the last level (:meth:`_native`) from the network's estimate, where it runs. The confidence
        check's swapped-input estimate starts beside it in a worker thread: the network's many small operations
        keep about one core busy whatever the thread count, and the last level has the other. Its CT is masked by
        the field of view as the network's estimate places it; where the last level moves the estimate by more than
        :data:`EARLY_SWAP_MAX_CHANGE_MM`, that mask is stale and the twin is computed again after it, from the
        refined estimate. ``swap_beside=False``: no swapped-input estimate beside it."""
        if not state.native:
            return
        run, details = state.run, state.details
        if swap_beside and state.options.assess and not state.options.refine:
            state.early_swap = self._in_background(
                self.estimate, *swap_inputs(run.moving_t, run.fixed_t, run.grid, run.residual, state.fov_t,
                                            self._fixed_support(state)),
                run.grid, thread_name="monai-rigidreg-swap")
        t = time.perf_counter()
        refined, details["native_level"] = self._native(state.inputs.fixed, state.inputs.moving, run.total,
                                                        state.fov_img, state.weights, run.grid,
                                                        region=state.weight_img is not None)
        choice_before = state.timings.get("fine_stage_choice", 0.0)
        refined, chose_regression = self._fine_stage_choice(state, refined)
        refined, switched = self._runner_up_within_ct(state, refined)  # partial overlap only (registration.overlap)
        switched = switched or chose_regression
        state.params = matrix_to_params(refined, state.run.grid.center())
        state.net_params = state.params.copy()
        # the choice's own last level is timed apart (timings["fine_stage_choice"])
        state.timings["native_level"] = (time.perf_counter() - t
                                         - (state.timings.get("fine_stage_choice", 0.0) - choice_before))
        if state.early_swap is not None:
            stale = switched or details["native_level"]["change_mm"] > EARLY_SWAP_MAX_CHANGE_MM
            details["swap_estimate"] = "after the last level" if stale else "beside the last level"
            if stale:
                state.early_swap.wait()
                state.early_swap = None

    def _fine_stage_choice(self, state: RegistrationState, refined: np.ndarray) -> tuple[np.ndarray, bool]:
        """Where the fine stage moved the learned regression's estimate by more than ``fine_stage_choice_mm`` (mm, the
        mean over the network grid's points), the last level also runs from the regression's estimate and the end
        pose whose CBCT field of view matches the CT better (:meth:`_image_match`, inside the match region, or the
        CT's box where the CT does not cover the CBCT's tissue) goes on; the fine stage's on a tie. The fine stage's
        coarse levels correct a regression a few millimetres off, but on a large patient's noisy, scatter-shaded
        CBCTs they carried right estimates tens of millimetres away (:data:`FINE_STAGE_CHOICE_MM`). ``refined``: the
        last level's result from the fine stage's estimate (fixed -> moving). Returns the pose that goes on and
        whether it is the regression's; then ``state.run`` becomes the run with the regression's estimate as its
        residual (what the fallback's choice between starts and the checks compare) and ``details.native_level``
        describes its last level. Records ``details.fine_stage_choice`` (``move_mm``: how far the fine stage moved
        the regression's estimate; where the choice ran, each end pose's ``*_ncc``, ``end_distance_mm`` and
        ``kept``: ``"fine stage"`` or ``"regression"``) for the run it judged, and adds its seconds to
        ``timings["fine_stage_choice"]``. Nothing to choose from (no record): the choice off, no fine stage, or a
        cascade (``cascade_steps > 1``, whose fine stage runs once per step)."""
        limit = self.fine_stage_choice_mm
        run = state.run
        regression_total = run.regression_total
        if limit is None or regression_total is None:
            return refined, False
        t = time.perf_counter()
        points = grid_points(run.grid, 8)
        move = matrix_distance_mm(run.total, regression_total, points)
        record: dict[str, Any] = {"move_mm": round(move, 3)}
        state.details["fine_stage_choice"] = record
        if not move > limit:
            return refined, False
        from_regression, regression_detail = self._native(state.inputs.fixed, state.inputs.moving, regression_total,
                                                          state.fov_img, state.weights, run.grid,
                                                          region=state.weight_img is not None)
        region = state.weight_img if state.weight_img is not None else state.domain
        s_fine, s_regression = self._image_match(state.inputs.fixed, state.inputs.moving, state.fov_img,
                                                 [refined, from_regression], region)
        chose = bool(s_regression > s_fine)  # NaN compares false: the fine stage's stays
        record.update(fine_stage_ncc=round(float(s_fine), 4), regression_ncc=round(float(s_regression), 4),
                      end_distance_mm=round(matrix_distance_mm(refined, from_regression, points), 3),
                      kept="regression" if chose else "fine stage")
        state.timings["fine_stage_choice"] = state.timings.get("fine_stage_choice", 0.0) + time.perf_counter() - t
        if not chose:
            return refined, False
        state.run = dataclasses.replace(run, residual=run.regression, total=regression_total)
        state.details["native_level"] = regression_detail
        return from_regression, True

    def _polish_probe(self, state: RegistrationState) -> float:
        """The learned network alone (``fine_stage=False``): how far the last level, run from its estimate, would
        move it (mm, the mean over the network grid's points), the estimate left as it is; where the last level
        converges, about the estimate's error (:data:`~monai_rigidreg.registration.calibration.POLISH_PROBE_LIMIT_MM`
        flags it). NaN without a field of view or a fine stage's settings. Records ``timings["polish_probe"]``."""
        if getattr(self.network, "fine_stage", None) is None or state.fov_img is None or state.run is None:
            return float("nan")
        t = time.perf_counter()
        matrix = params_to_matrix(state.params, state.run.grid.center())
        # one pass, as the probe's limit was measured (calibration.POLISH_PROBE_LIMIT_MM)
        _, detail = self._native(state.inputs.fixed, state.inputs.moving, matrix, state.fov_img, state.weights,
                                 state.run.grid, region=state.weight_img is not None, converge=False)
        state.timings["polish_probe"] = time.perf_counter() - t
        return float(detail["change_mm"])

    def _native(self, fixed_img: sitk.Image, moving_img: sitk.Image, matrix: np.ndarray, fov_img: sitk.Image,
                weights: list[sitk.Image], grid: Grid, region: bool = False, converge: bool = True
                ) -> tuple[np.ndarray, dict[str, Any]]:
        """The last level (:func:`~monai_rigidreg.registration.last_level.refine_native`) from ``matrix`` with the
        fine stage's feature settings (the local contrast at ``native_highpass_sigma_mm`` when set) and this
        registrar's ``native_bias_degree`` (``native_bias_degree_roi`` when ``region``: a match region, ``--roi``
        or ``--match bone``, is among ``weights``), run again from its result until a pass moves it by at most
        :data:`NATIVE_CONVERGED_MM` (``converge=False``: one pass). Returns the refined matrix and
        ``details.native_level``: the level's grid, bias degree, how far it moved the estimate in all (``change_mm``,
        mean distance over the points of ``grid``, the network grid, mm), ``passes``, ``last_pass_mm``, ``exhausted``
        (it ran all :data:`NATIVE_MAX_PASSES`, where more than one is allowed) and the last pass's ``expected_tre_mm``
        (:mod:`~monai_rigidreg.registration.precision`)."""
        stage = self.network.fine_stage
        degree = self.native_bias_degree_roi if region else self.native_bias_degree
        sigma = stage.highpass_sigma_mm if self.native_highpass_sigma_mm is None else self.native_highpass_sigma_mm

        report: dict[str, Any] = {}
        settings = self._pass_settings(sigma, degree)

        def one_pass(start: np.ndarray) -> tuple[np.ndarray, Grid]:
            return refine_native(fixed_img, moving_img, start, fov_img, weights, report=report, **settings,
                                 contrast_norm_sigma_mm=getattr(stage, "contrast_norm_sigma_mm", None),
                                 intensity_weight=getattr(stage, "intensity_weight", 1.0))

        refined, native_grid = one_pass(matrix)
        points = grid_points(grid, 8)
        moves = [matrix_distance_mm(refined, matrix, points)]  # each pass's move
        while converge and moves[-1] > NATIVE_CONVERGED_MM and len(moves) < NATIVE_MAX_PASSES:
            start = refined
            refined, native_grid = one_pass(start)
            moves.append(matrix_distance_mm(refined, start, points))
        change = moves[0] if len(moves) == 1 else matrix_distance_mm(refined, matrix, points)
        detail = {"spacing_mm": float(native_grid.spacing[0]), "size": list(native_grid.size), "bias_degree": degree,
                  "highpass_sigma_mm": float(sigma), "change_mm": round(change, 3),
                  "passes": len(moves), "last_pass_mm": round(moves[-1], 3),
                  "exhausted": converge and 1 < NATIVE_MAX_PASSES <= len(moves), **report}
        norm = self.native_final_norm_mm
        if converge and norm is not None and moves[-1] <= NATIVE_CONVERGED_MM:
            refined = self._final_norm_pass(fixed_img, moving_img, refined, fov_img, weights, points, settings,
                                            norm, detail)
        return refined, detail

    def _pass_settings(self, sigma: float, degree: int) -> dict[str, Any]:
        """The keyword arguments of :func:`refine_native` every pass of :meth:`_native` shares: the fine stage's
        feature and step settings, the local contrast at ``sigma`` mm, the bias ``degree``, the grid's cap."""
        stage = self.network.fine_stage
        return {"highpass_sigma_mm": sigma, "highpass_weight": stage.highpass_weight,
                "support_erosion_mm": stage.support_erosion_mm, "bias_degree": degree, "device": self.device,
                "tolerance": getattr(stage, "tolerance", None), "secant": getattr(stage, "secant", False),
                "max_voxels": self.native_max_voxels}

    def _final_norm_pass(self, fixed_img: sitk.Image, moving_img: sitk.Image, matrix: np.ndarray,
                         fov_img: sitk.Image, weights: list[sitk.Image], points: np.ndarray,
                         settings: dict[str, Any], norm_mm: float, detail: dict[str, Any]) -> np.ndarray:
        """One more pass of the last level from its converged result with the local contrast normalised over
        ``norm_mm`` and no intensity channel (:func:`~monai_rigidreg.networks.alignment_features.alignment_features`):
        the CBCT's shading (scatter, beam hardening) no longer pulls the pose. Kept where it moves the estimate by at
        most :data:`FINAL_NORM_MAX_MM` (the mean over ``points``, the network grid's, as the passes' moves); records
        ``detail["final_pass"]`` (``move_mm``, ``kept``); ``settings``: the other passes' (:meth:`_pass_settings`).
        The precision report (``expected_tre_mm``, what the calibrated confidence reads) stays the default
        features'."""
        refined, _ = refine_native(fixed_img, moving_img, matrix, fov_img, weights, **settings,
                                   contrast_norm_sigma_mm=norm_mm, intensity_weight=0.0)
        move = matrix_distance_mm(refined, matrix, points)
        kept = move <= FINAL_NORM_MAX_MM
        detail["final_pass"] = {"contrast_norm_sigma_mm": norm_mm, "move_mm": round(move, 3), "kept": bool(kept)}
        return refined if kept else matrix
