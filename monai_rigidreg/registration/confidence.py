"""How much to trust a registration: the CBCT field-of-view mask, the failure signals and the confidence score.

The rule score (:func:`confidence_score`) and the calibrated confidence
(:mod:`~monai_rigidreg.registration.calibration`) combine signals computed by :func:`assess_estimate` on the grids:
whether a small perturbation of the estimate aligns edges better (a correct estimate sits at the optimum; with a match
region, e.g. ``--roi``, the edges inside it only), whether the estimate with the inputs swapped agrees with the inverse
of this one, and how much of the CT's tissue it puts on CBCT air (:func:`tissue_on_air`: a gross failure, wherever its
edge optimum lies); with ``--roi`` a fourth, computed on the images by the registrar: how far the estimate leaves the
region's structures from where the CBCT shows them (:mod:`monai_rigidreg.registration.region_check`). Their limits:
``benchmarks/confidence/bench_confidence.py`` (spoiled estimates) and ``bench_confidence_clinical.py``.

A disagreement with the swapped-input estimate does not say which of the two is wrong. Above
:data:`SWAP_AGREE_MM` the registrar scores both on the images, as it chooses between its starts, and trusts the
better match: a better swapped estimate replaces the estimate, a worse one does not count against it
(``benchmarks/confidence/bench_confidence_clinical.py`` shows both cases on the clinical-geometry pairs).
"""

from __future__ import annotations

import logging
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
    target_registration_error,
)
from monai_rigidreg.core.image_ops import erode, gradient_magnitude, masked_ncc, pyramid
from monai_rigidreg.core.warp import warp_volume_params
from monai_rigidreg.registration.bone_check import bone_agreement
from monai_rigidreg.registration.calibration import verdict
from monai_rigidreg.registration.match_region import match_weight, weight_on_grid
from monai_rigidreg.registration.overlap import OVERLAP_FLAG_BELOW
from monai_rigidreg.registration.region_check import REGION_SHIFT_LIMIT_MM, block_shifts
from monai_rigidreg.registration.tissue_air import (
    AIR_HU,
    DEEP_LIMIT,
    TISSUE_HU,
    TISSUE_ON_AIR_LIMIT,
    deep_air_radius,
    tissue_on_air,
)

if TYPE_CHECKING:
    from monai_rigidreg.registration.state import Background, NetworkRun, RegistrationState

__all__ = ["CONFIDENCE_THRESHOLD", "FLAG_REASON_TEXT", "LOCAL_GAIN_LIMIT", "EDGE_OFFSET_LIMIT", "EDGE_SPACING_MM",
           "SWAP_AGREE_MM", "edge_offset", "AMBIGUOUS_TWIN_MM", "TISSUE_ON_AIR_LIMIT", "TISSUE_HU", "AIR_HU",
           "cylindrical_fov_mask", "tissue_on_air", "fov_ncc", "confidence_score", "assess_estimate", "swap_inputs",
           "ConfidenceStage"]

logger = logging.getLogger(__name__)

CONFIDENCE_THRESHOLD = 0.5
"""Results whose rule score (:func:`confidence_score`, ``details.signals.rule_score``) falls below this are flagged
as likely failures, whatever the calibrated confidence says (``details.flag_reasons``: ``"rule"``); without a
calibration it is also the confidence's flag threshold."""
FLAG_REASON_TEXT = {
    "not_hu": "an input is not in HU",
    "swapped": "the inputs look swapped",
    "overlap": "the CT covers too little of the CBCT",
    "rule": "a failure signal is past its limit",
    "confidence": "the calibrated confidence is low",
    "ambiguous": "another estimate far from this one matches the images about as well",
    "unpolished": "the last level would move the learned network's estimate too far",
    "unconverged": "the last level did not settle on a pose",
}
"""``details.flag_reasons`` in words, for the log."""
LOCAL_GAIN_LIMIT = 0.01
"""Edge-alignment gain (see :func:`confidence_score`) above which an estimate is treated as likely wrong."""
EDGE_OFFSET_LIMIT = 1.0
"""The edge gain (:data:`LOCAL_GAIN_LIMIT`) flags only where the edge optimum lies further than this many probe steps
from the estimate along some parameter, or has no optimum there (:func:`edge_offset`): one step is 2 mm or 2
degrees, the success criterion's scale. On the 286 cases of bundle 0.5.0's calibration the right results the gain
flagged had their optimum 0.55-0.85 steps away (four false alarms of the default path: partial overlap, a few
thousand, or a few dozen, pooled voxels in view), the failures it caught 1.17 steps or more (most with no optimum
along some parameter); ``docs/trust.md``."""
EDGE_SPACING_MM = 4.0
"""Resolution (mm) at which :meth:`RigidRegistrar.assess` compares edges (finer network grids are pooled to it)."""
SWAP_AGREE_MM = 3.0
"""Above this disagreement (mm) between an estimate and its swapped-input estimate, the registrar scores both on
the images (the CBCT field of view's NCC with the CT mapped into it, as it chooses between starts): a better
swapped estimate replaces the estimate (``details.start == "swapped"``), a worse one does not count against it
(``details.signals.swap_counted`` false)."""
AMBIGUOUS_TWIN_MM = 6.0
"""The swapped-input estimate counts for the ``"ambiguous"`` flag (``calibration.AMBIGUOUS_NCC_GAP``) only beyond this
distance (mm): the twin is the network's unpolished estimate, the estimate ran the last level to convergence, so a
twin a few mm away that matches almost as well sits in the same basin (a first collection with bundle 0.5.0's
weights: three right results flagged by twins 3.05-3.62 mm away; the failures it flagged had it 6.7 mm or more away,
or another flag; ``docs/trust.md``)."""


def cylindrical_fov_mask(image: sitk.Image, margin_mm: float = 2.0) -> sitk.Image:
    """uint8 mask of the largest cylinder (axis along the image's z index axis) inside the image's grid.

    CBCT scanners reconstruct a cylindrical field of view; outside it a CBCT holds no information, so similarity
    metrics (refinement, confidence) are restricted to this mask.
    """
    size, spacing = np.array(image.GetSize()), np.array(image.GetSpacing())
    half = (size - 1) / 2.0
    radius_mm = float(min(half[0] * spacing[0], half[1] * spacing[1])) - margin_mm
    yy, xx = np.meshgrid(np.arange(size[1]), np.arange(size[0]), indexing="ij")
    r2 = ((xx - half[0]) * spacing[0]) ** 2 + ((yy - half[1]) * spacing[1]) ** 2
    disk = (r2 <= radius_mm**2).astype(np.uint8)
    arr = np.broadcast_to(disk, (size[2], size[1], size[0])).copy()
    mask = sitk.GetImageFromArray(arr)
    mask.CopyInformation(image)
    return mask


def fov_ncc(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    """Normalized cross-correlation of two ``[x, y, z]`` volumes over the voxels where ``mask`` > 0 (float64;
    NaN when fewer than 10 voxels are in the mask). :func:`~monai_rigidreg.core.image_ops.masked_ncc` computes it."""
    m = (mask > 0).to(torch.float64)
    if int(m.sum()) < 10:
        return float("nan")
    return float(masked_ncc(a.double()[None, None], b.double()[None, None], m[None, None])[0])


def edge_offset(scores: Sequence[float]) -> float:
    """How far the edge optimum lies from the estimate, in probe steps: ``scores`` are the edge NCC at the estimate
    and at the twelve probes of :func:`assess_estimate` (each parameter minus and plus one step, in parameter
    order); per parameter the vertex of the parabola through its three scores, ``|s+ - s-| / (2 (2 s0 - s+ - s-))``,
    infinite where the scores do not curve down (no optimum along it); the largest of the six (NaN if any score is).

    >>> edge_offset([1.0] + [0.9] * 12)
    0.0
    >>> edge_offset([1.0, 0.9, 1.1] + [0.9] * 10)
    inf
    """
    s = np.asarray(scores, dtype=np.float64)
    if s.shape != (13,) or not np.all(np.isfinite(s)):
        return float("nan")
    minus, plus = s[1::2] - s[0], s[2::2] - s[0]
    curvature = -(minus + plus)
    with np.errstate(divide="ignore", invalid="ignore"):
        offsets = np.where(curvature > 1e-9, np.abs(plus - minus) / (2.0 * curvature), np.inf)
    return float(offsets.max())


def confidence_score(
    local_gain: float, swap_tre_mm: float, gain_ref: float = LOCAL_GAIN_LIMIT, tre_ref_mm: float = 3.0,
    swap_counted: bool = True, tissue_on_air_share: float = float("nan"), air_ref: float = DEEP_LIMIT,
    region_shift_mm: float = float("nan"), region_ref_mm: float = REGION_SHIFT_LIMIT_MM,
    edge_offset_steps: float = float("inf"),
) -> float:
    """Combine the failure signals into a score in [0, 1] (below 0.5: flagged).

    * ``local_gain``: how much the edge alignment (NCC of gradient magnitudes in the field of view) improves when
      the estimate is perturbed by half a network voxel or 2 degrees along any parameter. A correct estimate sits
      at the optimum (gain about 0); calibrated on simulated pairs with deliberately spoiled estimates
      (``benchmarks/confidence/bench_confidence.py``), errors of a few mm or degrees give gains above ``gain_ref``.
      It counts only where the edge optimum lies beyond the probe (``edge_offset_steps`` above
      :data:`EDGE_OFFSET_LIMIT`, :func:`edge_offset`; the default, infinite, always counts it).
    * ``swap_tre_mm``: disagreement (mean TRE over the network grid, mm) between the forward estimate and the
      inverse of the estimate with the inputs swapped; ``tre_ref_mm`` gives 0.5. ``swap_counted=False``: the
      disagreement is resolved (the swapped estimate matched the images worse than the estimate, see
      :data:`SWAP_AGREE_MM`) and does not lower the score.
    * ``tissue_on_air_share``: :func:`tissue_on_air` of the estimate on deep air (``tissue_on_air_deep``,
      :data:`~monai_rigidreg.registration.tissue_air.DEEP_AIR_MM`); ``air_ref`` gives 0.5, the logistic's scale is
      ``air_ref / 7.5`` (NaN: not measured, no effect). A gross failure puts CT tissue on CBCT air whether or not the
      estimate sits at an edge optimum.
    * ``region_shift_mm``: with a region of interest, the length of the median residual shift of its structures
      (:func:`~monai_rigidreg.registration.region_check.block_shifts`); ``region_ref_mm`` gives 0.5 (NaN: not measured
      or too few blocks with structure, no effect).

    Each signal maps through a logistic to [0, 1]; the score is the smallest, so any failure mode flags.
    """
    def falling(value: float, ref: float, width: float, unmeasured: float) -> float:
        """1 well below ``ref``, 0.5 at it, 0 well above (``width``: the logistic's scale); ``unmeasured`` for NaN."""
        return 1.0 / (1.0 + np.exp((value - ref) / width)) if np.isfinite(value) else unmeasured

    s_gain = 1.0 if edge_offset_steps <= EDGE_OFFSET_LIMIT else falling(local_gain, gain_ref, 0.003, 0.0)
    s_swap = falling(swap_tre_mm, tre_ref_mm, 0.75, 1.0) if swap_counted else 1.0
    s_air = falling(tissue_on_air_share, air_ref, air_ref / 7.5, 1.0)
    s_region = falling(region_shift_mm, region_ref_mm, 0.25, 1.0)
    return float(min(s_gain, s_swap, s_air, s_region))


def _masked_swap(moving_t: torch.Tensor, fixed_t: torch.Tensor, fov_w: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(moving, fixed)`` inputs of the swapped estimate: the CT restricted to the CBCT's field of view as placed
    by an estimate (``fov_w``: the field of view warped by it) against the CBCT. A network with a fine stage aligns
    only where its moving input has data, so an unmasked CT (data everywhere) against a truncated CBCT would bias the
    swapped estimate even when the forward one is right."""
    return fixed_t * (fov_w > 0.5).to(fixed_t.dtype)[None], moving_t


def swap_inputs(moving_t: torch.Tensor, fixed_t: torch.Tensor, grid: Grid, params: np.ndarray, fov: torch.Tensor,
                fixed_support: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The swapped-input estimator's ``(moving, fixed)`` for an estimate ``params`` (``[6]`` mm/deg about the grid
    centre): what :func:`assess_estimate` hands ``estimate``, for a caller that starts the swapped estimate early.

    Args:
        moving_t, fixed_t: ``[1, x, y, z]`` CBCT and CT on ``grid``.
        grid: the network grid.
        params: the estimate whose field-of-view placement masks the CT.
        fov: ``[x, y, z]`` field-of-view mask of ``moving_t`` on ``grid``.
        fixed_support: ``[x, y, z]`` where the CT has data on ``grid`` (CT frame; ``None``: everywhere), e.g. the
            CT's box where it does not cover the CBCT (:mod:`~monai_rigidreg.registration.overlap`).

    Returns:
        ``([1, x, y, z]`` masked CT, ``[1, x, y, z]`` CBCT): the swapped estimator's moving and fixed inputs.
    """
    with torch.no_grad():
        p = torch.as_tensor(np.asarray(params, dtype=np.float64)[None], dtype=torch.float32)
        return _masked_swap(moving_t, fixed_t, _supported(_placed_fov(fov, p, grid), fixed_support))


def _supported(fov_w: torch.Tensor, fixed_support: torch.Tensor | None) -> torch.Tensor:
    """The placed field of view ``fov_w`` ``[x, y, z]`` where the CT has data (``fixed_support`` > 0.5, CT frame)."""
    if fixed_support is None:
        return fov_w
    return fov_w * (fixed_support.to(fov_w.device) > 0.5).to(fov_w.dtype)


def _placed_fov(fov: torch.Tensor, params: torch.Tensor, grid: Grid) -> torch.Tensor:
    """The field of view ``fov`` ``[x, y, z]`` (of the CBCT on ``grid``) where an estimate ``params`` ``[1, 6]``
    (float32, mm/deg about the grid centre) places it on the CT: nearest-neighbour warp, ``[x, y, z]``."""
    return warp_volume_params(fov[None, None].float(), params, grid, mode="nearest")[0, 0]


def assess_estimate(
    moving_t: torch.Tensor,
    fixed_t: torch.Tensor,
    grid: Grid,
    params: np.ndarray,
    fov: torch.Tensor,
    estimate: Callable[[torch.Tensor, torch.Tensor], np.ndarray] | None = None,
    region: torch.Tensor | None = None,
    hu_range: tuple[float, float] = (-1000.0, 2000.0),
    swapped: Callable[[], np.ndarray] | None = None,
    fixed_support: torch.Tensor | None = None,
) -> dict[str, Any]:
    """Failure signals of an estimate ``params`` (mm/deg about the grid centre) on preprocessed tensors.

    Args:
        moving_t, fixed_t: ``[1, x, y, z]`` CBCT and CT on ``grid`` (the CBCT possibly resampled through a start
            estimate: ``params`` are then the residual in that frame).
        grid: the network grid (CT frame, LPS mm).
        params: the estimate, ``[6]`` mm / degrees about the grid centre, fixed -> moving.
        fov: ``[x, y, z]`` field-of-view mask of ``moving_t`` on ``grid``.
        estimate: the swapped-input estimator ``(moving, fixed) -> [6]`` (``None``: no swap test). It matches
            the whole field of view even with ``region``: restricted to the region (carried into the CBCT's frame)
            it lost three head deformed clinical-geometry pairs that its whole-view estimate rescues by replacement
            (``benchmarks/confidence/bench_confidence_clinical.py``).
        region: ``[x, y, z]`` match-region weight on ``grid`` (CT frame; e.g. the ``--roi`` box): the edge test
            looks only where it is > 0.5, the region the estimate was asked to match (an anatomy that changed
            outside it prefers another pose there by design).
        hu_range: the HU window the tensors were normalized from (``[0, 1]``), for the tissue/air levels of
            :func:`tissue_on_air`.
        swapped: instead of ``estimate``, a function returning the swapped estimate already under way (``[6]``,
            the CT's pose in the CBCT's frame as ``estimate`` returns it), e.g. one started on
            :func:`swap_inputs` of an earlier estimate while the caller refined it.
        fixed_support: ``[x, y, z]`` where the CT has data on ``grid`` (``None``: everywhere): the signals look at
            the placed field of view inside it only (a CT that does not cover the CBCT,
            :mod:`~monai_rigidreg.registration.overlap`).

    Returns ``ncc_before``/``ncc_after`` (intensity NCC in the field of view), ``edge_ncc`` (NCC of gradient
    magnitudes), ``tissue_on_air`` and ``tissue_on_air_deep`` (:func:`tissue_on_air` on every and on deep CBCT air),
    ``bone_share`` and ``bone_agreement`` (:mod:`~monai_rigidreg.registration.bone_check`), ``local_gain`` and
    ``swap_tre_mm`` (see :func:`confidence_score`), ``confidence``, and with ``estimate`` or ``swapped`` also
    ``swap_params``: the inverse of the swapped estimate, ``[6]`` numpy, in the frame of ``params`` (the caller may
    score it as an alternative, :data:`SWAP_AGREE_MM`).
    """
    p0 = np.asarray(params, dtype=np.float64)
    # edges are compared at about 4 mm (the grid pooled by ``factor``), where the gain threshold was calibrated:
    # finer grids see CBCT/CT edge differences (noise, blur) that shift the edge optimum by a fraction of a voxel
    factor = max(1, int(round(EDGE_SPACING_MM / min(grid.spacing))))
    steps = [0.5 * min(grid.spacing) * factor] * 3 + [2.0] * 3
    candidates = [p0]
    for i, step in enumerate(steps):
        for sign in (-1.0, 1.0):
            q = p0.copy()
            q[i] += sign * step
            candidates.append(q)
    with torch.no_grad():
        fixed_f = fixed_t[0].float()
        batch = torch.as_tensor(np.stack(candidates), dtype=torch.float32)
        moved0 = warp_volume_params(moving_t[None].float(), batch[:1], grid)[0, 0]
        fov_w = _supported(_placed_fov(fov, batch[:1], grid), fixed_support)
        out = {"ncc_before": fov_ncc(moving_t[0], fixed_f, fov), "ncc_after": fov_ncc(moved0, fixed_f, fov_w)}
        fov_in = erode(fov_w[None, None], (2, 2, 2))[0, 0]
        out["tissue_on_air"] = tissue_on_air(fixed_f, moved0, fov_in, hu_range)
        out["tissue_on_air_deep"] = tissue_on_air(fixed_f, moved0, fov_in, hu_range, deep_air_radius(grid.spacing))
        out["bone_share"], out["bone_agreement"] = bone_agreement(fixed_f, moved0, fov_in, hu_range)
        # away from the field-of-view border: the CBCT's own edge there (data to zero) is no anatomy, and the
        # candidates move it by up to a pooled voxel (erosion radius: that step plus the gradient stencil)
        r = 2 * factor + 1
        fov_e = erode(fov_w[None, None], (r, r, r))
        # all candidates in one batched warp of the pooled volume on the pooled grid: [13, 1, x, y, z]
        moving_p, grid_p = pyramid(moving_t[None].float(), grid, factor)
        fixed_p, _ = pyramid(fixed_f[None, None], grid, factor)
        fov_e = (pyramid(fov_e, grid, factor)[0][0, 0] > 0.999).to(fov_w.dtype)
        if region is not None:
            if tuple(region.shape) != tuple(grid.size):
                raise ValueError(f"region must be [x, y, z] = {tuple(grid.size)}, got {tuple(region.shape)}")
            region_p = pyramid(region.float()[None, None].to(fov_e.device), grid, factor)[0][0, 0]
            fov_e = fov_e * (region_p > 0.5).to(fov_e.dtype)
        moved = warp_volume_params(moving_p.expand(len(candidates), -1, -1, -1, -1), batch, grid_p)
        edges_f = gradient_magnitude(fixed_p[0, 0])
        edges_m = gradient_magnitude(moved[:, 0])
        scores = [fov_ncc(edges_m[k], edges_f, fov_e) for k in range(len(candidates))]
    edge, best = scores[0], max(scores)
    out["edge_ncc"] = edge
    out["local_gain"] = float(best - edge)
    out["edge_offset"] = edge_offset(scores)
    if swapped is not None or estimate is not None:
        if swapped is not None:
            twin = swapped()
        else:
            twin = estimate(*_masked_swap(moving_t, fixed_t, fov_w))  # type: ignore[misc]
        inv = matrix_to_params(invert_matrix(params_to_matrix(twin, grid.center())), grid.center())
        out["swap_tre_mm"] = float(target_registration_error(params, inv, grid_points(grid, 4),
                                                             center=grid.center()))
        out["swap_params"] = np.asarray(inv, dtype=np.float64)
    else:
        out["swap_tre_mm"] = float("nan")
    out["confidence"] = confidence_score(out["local_gain"], out["swap_tre_mm"],
                                         tissue_on_air_share=out["tissue_on_air_deep"],
                                         edge_offset_steps=out["edge_offset"])
    return out


class ConfidenceStage:
    """Stage 8 of :class:`~monai_rigidreg.registration.RigidRegistrar`: the failure signals, the swapped-input check
    (which may replace the estimate by its better twin) and the confidence. For a class with the registrar's
    ``hu_range``, ``estimate``, ``_image_match``, ``_native`` and ``_fixed_support`` (the overlap stage's)."""

    hu_range: tuple[float, float]
    estimate: Callable[..., np.ndarray]
    _image_match: Callable[..., list[float]]
    _native: Callable[..., tuple[np.ndarray, dict[str, Any]]]
    _fixed_support: Callable[..., torch.Tensor | None]
    _polish_probe: Callable[..., float]

    def assess(
        self, moving_t: torch.Tensor, fixed_t: torch.Tensor, grid: Grid, params: np.ndarray, fov: torch.Tensor,
        swap: bool = True, region: torch.Tensor | None = None, swapped: Callable[[], np.ndarray] | None = None,
        fixed_support: torch.Tensor | None = None,
    ) -> dict[str, Any]:
        """Failure signals of ``params`` (mm/deg about the grid centre): :func:`assess_estimate` with this
        registrar's network as the swapped-input estimator (``swap=False``: without that check); ``region``: the
        match-region weight on ``grid`` (the edge test looks there only); ``swapped``: the swapped estimate already
        under way (its result function); ``fixed_support``: where the CT has data on ``grid``."""
        estimate = (lambda m, f: self.estimate(m, f, grid)) if swap else None
        return assess_estimate(moving_t, fixed_t, grid, params, fov, estimate, region=region, hu_range=self.hu_range,
                               swapped=swapped if swap else None, fixed_support=fixed_support)

    def _assess(self, state: RegistrationState, swap: bool = True, record: bool = True,
                cheap: dict[str, Any] | None = None) -> dict[str, Any] | None:
        """Stage 8, with ``assess``: :meth:`_confidence`, the overlap under the final estimate (``_overlap_report``)
        and the verdict (:func:`~monai_rigidreg.registration.calibration.verdict`): the calibrated confidence and
        ``details.flag_reasons``; inputs not in HU or that look swapped (unless allowed) get confidence 0.
        ``swap=False, record=False``: the cheap signals only, not recorded (the network-led path's check; their
        ``confidence`` is the rule score); ``swap=False, cheap=``: such signals of this estimate recorded, not
        computed again. Returns the signals (``None`` where the call does not assess)."""
        options, timings, details = state.options, state.timings, state.details
        if record and not options.assess:
            return None
        t = time.perf_counter()
        if cheap is not None and not swap:
            replaced, signals = False, {k: v for k, v in cheap.items() if k != "seconds"}
        else:  # the region check looks at the ROI itself (with --match bone too: its blocks need the soft tissue)
            roi = options.roi
            roi_img = None if roi is None else state.weight_img if options.match == "soft" else match_weight(
                state.inputs.fixed, roi)
            state.params, replaced, signals = self._confidence(
                state.inputs.fixed, state.inputs.moving, state.fov_img, state.fov_t, state.run, state.params,
                state.weights, state.weight_img, roi_img, state.native, state.staged and not options.refine, details,
                state.early_swap, self._fixed_support(state), state.domain, swap=swap,
                blocks_cache=state.region_blocks)
        if state.early_swap is not None:
            timings["swap_estimate"] = state.early_swap.seconds
        if replaced:
            state.net_params = state.params.copy()
        if not record:
            signals["seconds"] = time.perf_counter() - t
            return signals
        signals["rule_score"] = signals.pop("confidence")
        if not state.staged:  # the learned network alone: how far the last level would move it (not applied)
            signals["polish_probe_mm"] = self._polish_probe(state)
        elif "last_pass_mm" in details.get("native_level", {}):  # calibration.UNCONVERGED_MM
            signals["last_pass_mm"] = float(details["native_level"]["last_pass_mm"])
            signals["last_level_exhausted"] = bool(details["native_level"].get("exhausted", False))
            signals["expected_tre_mm"] = float(details["native_level"].get("expected_tre_mm", float("nan")))
        overlap = self._overlap_report(state, params_to_matrix(state.params, state.run.grid.center()))
        if np.isfinite(overlap):
            signals["overlap"] = overlap
        if state.inputs.not_hu:
            signals["not_hu"] = state.inputs.not_hu
        signals["swapped"] = bool(state.inputs.swapped)
        if state.inputs.swapped:
            signals.update(swapped_because=list(state.inputs.swapped), swap_allowed=bool(options.allow_swapped))
        calibration = getattr(self, "calibration", None)
        state.confidence, reasons = verdict(signals, calibration, CONFIDENCE_THRESHOLD, OVERLAP_FLAG_BELOW)
        state.flagged = bool(reasons)
        timings["confidence"] = time.perf_counter() - t
        details.update(signals=signals, flag_reasons=reasons,
                       confidence_calibration=None if calibration is None else calibration.record())
        if state.flagged:
            logger.warning("registration flagged as a likely failure (confidence %.2f; %s): check the QC figure",
                           state.confidence, ", ".join(FLAG_REASON_TEXT[r] for r in reasons))
        return signals

    def _confidence(self, fixed_img: sitk.Image, moving_img: sitk.Image, fov_img: sitk.Image, fov_t: torch.Tensor,
                    run: NetworkRun, params: np.ndarray, weights: list[sitk.Image], weight_img: sitk.Image | None,
                    roi_img: sitk.Image | None, native: bool, may_replace: bool, details: dict[str, Any],
                    early_swap: Background | None = None, fixed_support: torch.Tensor | None = None,
                    domain: sitk.Image | None = None, swap: bool = True, blocks_cache: dict[bytes, Any] | None = None
                    ) -> tuple[np.ndarray, bool, dict[str, Any]]:
        """The failure signals and the confidence of ``params`` (mm/deg about ``run.grid``'s centre), with the
        swapped-input check: where the swapped estimate disagrees by more than ``SWAP_AGREE_MM``, the one whose CBCT
        field of view matches the CT better (inside the match region ``weight_img``) is trusted, and a better
        swapped estimate replaces ``params`` once (``may_replace``; after its own last level when ``native``).
        ``roi_img``: the ROI's mask on the CT for the region check
        (:func:`~monai_rigidreg.registration.region_check.block_shifts`; ``None``: no ROI, no check).
        ``early_swap``: the swapped estimate started beside the last level (``_last_level``), used for the first
        assessment (a replacement's is computed here). ``swap=False``: the cheap signals only (edge test,
        ``tissue_on_air``, the region check), without the swapped-input estimate (the network-led path's check,
        :mod:`~monai_rigidreg.registration.lead`); ``swap_tre_mm`` is then NaN and does not lower the score.
        ``blocks_cache``: the region check per estimate, filled and reused (one call judges an estimate twice on the
        network-led path). Records ``details.swap_check`` (and ``start``, ``native_level`` on a replacement).
        Returns ``(params, replaced, signals)``, ``signals["confidence"]`` included."""
        grid = run.grid
        grid_center = grid.center()
        region = None if weight_img is None else weight_on_grid([weight_img], grid)[0]
        replaced, alternative_gap = False, None
        while True:
            # in the frame of the winning start: its resampled CBCT and the residual of the final estimate
            to_start = invert_matrix(run.start)
            residual = matrix_to_params(to_start @ params_to_matrix(params, grid_center), grid_center)
            signals = self.assess(run.moving_t, run.fixed_t, grid, residual, fov_t, swap=swap, region=region,
                                  swapped=None if early_swap is None or replaced else early_swap.result,
                                  fixed_support=fixed_support)
            if not swap:
                break
            swapped = run.start @ params_to_matrix(signals.pop("swap_params"), grid_center)
            if not signals["swap_tre_mm"] > SWAP_AGREE_MM:
                break
            # they disagree: the one whose field of view matches the CT better is trusted; a better twin replaces the
            # estimate once (not after --refine, nor for the network alone). Scored inside the match region: over the
            # whole view the twin tends to win on deformed anatomy (false alarms 2 -> 3 of 7; docs/results.md)
            s_est, s_swap = self._image_match(fixed_img, moving_img, fov_img,
                                              [params_to_matrix(params, grid_center), swapped],
                                              weight_img if weight_img is not None else domain)
            check = {"estimate_ncc": round(s_est, 4), "swapped_ncc": round(s_swap, 4),
                     "swap_tre_mm": round(signals["swap_tre_mm"], 2)}
            if alternative_gap is None and signals["swap_tre_mm"] > AMBIGUOUS_TWIN_MM:
                # the two estimates the images chose between (calibration.AMBIGUOUS_NCC_GAP), where distinct poses
                alternative_gap = abs(float(s_est) - float(s_swap))
            if s_swap > s_est and may_replace and not replaced:
                replaced = True
                details["swap_check"] = {**check, "replaced": True}
                if native:
                    # the last level from the swapped estimate: details.native_level describes this run
                    swapped, details["native_level"] = self._native(fixed_img, moving_img, swapped, fov_img,
                                                                    weights, grid, region=weight_img is not None)
                params = matrix_to_params(swapped, grid_center)
                details["start"] = "swapped"
                continue
            details.setdefault("swap_check", {**check, "replaced": False})
            # a worse twin does not count, unless the estimate is itself a replacing twin: then neither settles the
            # pose (a clinical head pair ended 9.3 mm off that way; docs/results.md, "Confidence")
            signals["swap_counted"] = bool(s_swap >= s_est) or replaced
            if replaced:
                details["swap_check"]["after_replacement"] = check
            break
        other = details.get("overlap", {}).get("other_starts", {}).get("alternative_ncc_gap")  # a distinct start's
        gaps = [g for g in (alternative_gap, other) if g is not None]
        if gaps:
            signals["alternative_ncc_gap"] = round(min(gaps), 4)
        if roi_img is not None:
            # the region's structures against the CBCT (block matching): on flat or deformed anatomy an image optimum
            # can leave them millimetres off while every other signal reads well
            key = np.asarray(params, dtype=np.float64).tobytes()
            cache = {} if blocks_cache is None else blocks_cache
            if key not in cache:
                matrix = params_to_matrix(params, grid_center)
                cache[key] = block_shifts(fixed_img, moving_img, matrix, roi_img, fov_img)
            blocks = cache[key]
            shift = blocks.median_shift()
            signals["region_shift_mm"] = float(np.linalg.norm(shift)) if np.all(np.isfinite(shift)) else float("nan")
            signals["region_shift_vector_mm"] = [round(float(v), 2) for v in shift]
            signals["region_blocks"] = blocks.count
        signals["confidence"] = confidence_score(signals["local_gain"], signals["swap_tre_mm"],
                                                 swap_counted=signals.get("swap_counted", True),
                                                 tissue_on_air_share=signals["tissue_on_air_deep"],
                                                 edge_offset_steps=signals["edge_offset"],
                                                 region_shift_mm=signals.get("region_shift_mm", float("nan")))
        return params, replaced, signals
