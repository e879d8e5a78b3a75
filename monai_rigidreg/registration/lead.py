"""The network-led default path: one network estimate, its polish, a cheap check; the rest only as a fallback.

Every registration of the thorough path (``thorough=True``, the default before 0.5.0) pays for the global search,
a second start where the search and the network disagree and a second whole network estimate with the inputs
swapped for the confidence. On most pairs none of them changes the result: the network from the identity is right
and the last level polishes it. :class:`LeadPath` (a stage group of
:class:`~monai_rigidreg.registration.RigidRegistrar`) runs, in order:

1. the network from the identity (``_run_identity``, :mod:`~monai_rigidreg.registration.network_run`);
2. the last level from its estimate (``_last_level``, :mod:`~monai_rigidreg.registration.last_level`), without the
   swapped-input estimate (the calibrated confidence, :mod:`~monai_rigidreg.registration.calibration`, reads only
   the cheap signals: on 305 held-out cases it caught as many default-path failures without it, ``docs/trust.md``);
3. the check (:meth:`LeadPath._lead_check`): the confidence's cheap signals (the edge test, ``tissue_on_air`` and,
   with ``--roi``, the region's block check; :func:`~monai_rigidreg.registration.confidence.confidence_score`
   without the swap term), the share of the CBCT's field of view that the estimate places inside the CT
   (``fov_in_ct`` of :func:`~monai_rigidreg.registration.overlap.overlap_shares`, on the field-of-view sample the
   overlap checks take once), how far the last level moved the network's estimate, whether the estimate lies
   inside the motion range the network was trained on, and whether the network's final estimate stands (where the
   fine-stage choice kept the regression's end pose instead, two of the network's estimates lead to different
   optima and the one kept may be a wrong one that matches well: :data:`LEAD_CHOICE_FALLBACK`);
4. only where the check fails, the fallback (:meth:`LeadPath._fallback`): the global search and the network from
   its candidates (:class:`~monai_rigidreg.registration.search.StartChoice`, the winner by image match), the last
   level again if another start won, and the full confidence with the swapped-input estimate (which may replace the
   estimate, :data:`~monai_rigidreg.registration.confidence.SWAP_AGREE_MM`, and whose disagreement lowers the rule
   score).

``details["path"]`` says which path ran (``"network-led"`` or ``"thorough"``), ``details["lead_check"]`` holds the
check's numbers and ``details["fallback"]`` whether the fallback ran and why (``reasons``: ``"confidence"``,
``"overlap"``, ``"polish"``, ``"range"``, ``"choice"``). Without the fallback the result's confidence is the
calibrated one from the check's own signals (stage 8,
:meth:`~monai_rigidreg.registration.confidence.ConfidenceStage._assess` with ``cheap``: computed once), the same model
as on the thorough path. The thresholds below were measured with ``python -m benchmarks.accuracy.bench_lead_check``
(``docs/results.md``, "The network leads").
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np

from monai_rigidreg.core.geometry import params_to_matrix
from monai_rigidreg.registration.overlap import fov_sample, overlap_shares

if TYPE_CHECKING:
    from monai_rigidreg.registration.state import Background, RegistrationState

__all__ = ["LEAD_CHOICE_FALLBACK", "LEAD_CONFIDENCE", "LEAD_MIN_OVERLAP", "LEAD_POLISH_MAX_MM", "LEAD_RANGE_MM",
           "LEAD_RANGE_DEG", "LeadPath"]

LEAD_CONFIDENCE = 0.8
"""The check fails where the cheap signals' score (:func:`~monai_rigidreg.registration.confidence.confidence_score`
without the swap term) is below this: a margin above the flag's 0.5, so that an estimate near a flag gets the
search and the swapped-input estimate."""
LEAD_MIN_OVERLAP = 0.8
"""The check fails where less than this share of the CBCT's field of view lies inside the CT under the estimate
(``fov_in_ct`` of :func:`~monai_rigidreg.registration.overlap.overlap_shares`): with poor overlap the network sees
little of the CT and the signals less still."""
LEAD_POLISH_MAX_MM = 2.0
"""The check fails where the last level moved the network's estimate by more than this (mm, mean over the network
grid's points, ``details.native_level.change_mm``): a converged network estimate is polished by a few tenths of a
millimetre; a larger move says the network was not at the images' optimum."""
LEAD_RANGE_MM = 60.0
"""The check fails where the estimate translates the CBCT's centre by more than this along any axis (mm): the
shipped network's training range (motions up to 60 mm per axis). Beyond the range test, the other tests
(confidence, polish, overlap) catch the network's wrong 40-60 mm estimates: on 52 clinical-geometry pairs of three
CTs (the held-out thorax and head at two seeds, a training CT's) every pair it got more than 5 mm wrong, with the same
successes and flags as a 30 mm range and the fallback on 20 pairs instead of 30 (``docs/results.md``, "The range test
retuned")."""
LEAD_RANGE_DEG = 45.0
"""Likewise for the rotation angles (degrees): the shipped network's training range on all three axes at once.
The paper protocol's 30-degree cases stay on the led path."""


LEAD_CHOICE_FALLBACK = True
"""The check fails (``"choice"``) where the fine-stage choice
(:meth:`~monai_rigidreg.registration.last_level.LastLevelStage._fine_stage_choice`) kept the regression's end pose
over the fine stage's: the network's own final estimate did not stand, so the search and the swapped-input estimate
judge the kept pose. On a held-out abdomen's clinical CBCT a leave-one-CT-out network's regression led to a pose
about one vertebral level off (38 mm) that matched better than the fine stage's and passed every cheap test
(confidence 0.9994); the fallback's swapped-input estimate matched better still and ended 0.35 mm off
(``docs/trust.md``, "The fine-stage choice judged")."""


class LeadPath:
    """The network-led path of :class:`~monai_rigidreg.registration.RigidRegistrar` (the module's doc): for a class
    with the registrar's stage methods and its ``lead_fallback`` setting (``False``: the check is recorded but the
    fallback never runs, for measuring the check itself)."""

    lead_fallback: bool
    _run_identity: Any
    _choose_start: Any
    _last_level: Any
    _start_search: Any
    _assess: Any
    _on_grid: Any
    _in_background: Any
    estimate: Any

    def _lead(self, state: RegistrationState) -> None:
        """Stages 4 and 6 without the search, the check, and the fallback where the check fails."""
        state.details["path"] = "network-led"
        self._run_identity(state)
        self._choose_start(state, None)  # no search: the identity's run is the estimate
        if state.fov_t is None:  # the check needs the field of view on the grid, with or without ``assess``
            state.fov_t = self._on_grid(state.fov_img, state.run.grid, "nearest", 0.0, state.run.sampling)[0]
        # no swapped-input estimate: the calibrated confidence (registration.calibration) needs none, and the
        # fallback computes it where the check fails
        self._last_level(state, swap_beside=False)
        signals = self._lead_check(state)
        check = state.details["lead_check"]
        run_fallback = bool(check["reasons"]) and self.lead_fallback
        state.details["fallback"] = {"run": run_fallback, "reasons": list(check["reasons"])}
        if run_fallback:
            self._fallback(state)
        else:
            # the check's signals are the confidence's (same estimate): recorded, not computed again
            self._assess(state, swap=False, cheap=signals)

    def _lead_check(self, state: RegistrationState) -> dict[str, Any]:
        """The check of the network's polished estimate (the module's doc, step 3): records
        ``details["lead_check"]`` (``confidence``: the cheap signals' score, ``overlap``, ``polish_mm``,
        ``max_translation_mm`` and ``max_rotation_deg`` of the estimate about the CBCT's centre, ``reasons``: the
        tests it failed) and ``timings["lead_check"]``; returns the cheap signals (:meth:`_assess`'s)."""
        t = time.perf_counter()
        signals = self._assess(state, swap=False, record=False)
        grid_center = state.run.grid.center()
        matrix = params_to_matrix(state.params, grid_center)
        if state.fov_sample is None:  # (stage 1 samples it wherever the field of view is known)
            state.fov_sample = fov_sample(state.inputs.moving, state.fov_img)
        overlap = overlap_shares(state.inputs.fixed_grid, state.fov_sample, matrix)["fov_in_ct"]
        polish = float(state.details.get("native_level", {}).get("change_mm", 0.0))
        # the estimate about the CBCT's centre (the identity's grid is centred there): the motion the network saw
        params = np.asarray(state.params, dtype=np.float64)
        max_t, max_r = float(np.abs(params[:3]).max()), float(np.abs(params[3:]).max())
        reasons = []
        if not signals["confidence"] >= LEAD_CONFIDENCE:
            reasons.append("confidence")
        if not overlap >= LEAD_MIN_OVERLAP:
            reasons.append("overlap")
        if polish > LEAD_POLISH_MAX_MM:
            reasons.append("polish")
        if max_t > LEAD_RANGE_MM or max_r > LEAD_RANGE_DEG:
            reasons.append("range")
        if LEAD_CHOICE_FALLBACK and (state.details.get("fine_stage_choice") or {}).get("kept") == "regression":
            reasons.append("choice")
        state.details["lead_check"] = {
            "confidence": round(float(signals["confidence"]), 4), "local_gain": round(signals["local_gain"], 5),
            "tissue_on_air": round(signals["tissue_on_air"], 4),
            "tissue_on_air_deep": round(signals["tissue_on_air_deep"], 4), "overlap": round(overlap, 4),
            "polish_mm": round(polish, 3), "max_translation_mm": round(max_t, 2), "max_rotation_deg": round(max_r, 2),
            "reasons": reasons}
        state.timings["lead_check"] = time.perf_counter() - t
        return signals

    def _fallback(self, state: RegistrationState) -> None:
        """The thorough path's remaining stages from the network's run: the global search (with ``global_init``)
        and the network from its candidates, the choice by image match (:meth:`_choose_start`), the last level
        again where a candidate won (with its own swapped-input estimate beside it), and the full confidence. Where the
        identity's run stays the start, the swapped-input estimate made beside its last level serves."""
        t = time.perf_counter()
        polished = state.params.copy()
        searching: Background | None = self._start_search(state)
        if searching is not None:
            self._choose_start(state, searching)
        if state.details.get("start", "identity") == "identity":
            # the identity's run, already polished: its swapped-input estimate is computed by the confidence
            state.params, state.net_params = polished, polished.copy()
            state.details["swap_estimate"] = "after the check"
        else:
            self._last_level(state)  # another start won: its swapped-input estimate starts beside its last level
        self._assess(state)
        state.timings["fallback"] = time.perf_counter() - t
