"""What the confidence means: the failure signals mapped to the probability that the registration is right.

The signals (:func:`~monai_rigidreg.registration.confidence.assess_estimate`, the region check, the overlap) are
measured on every registration; a fitted logistic model maps them to the probability that the target registration
error is under 2 mm (:attr:`ConfidenceCalibration.target`). The model is a versioned artefact: a small JSON file
(``configs/confidence_calibration.json`` in the bundle) with the features' names, the fitted coefficients, the
threshold below which a result is flagged, the bundle version and weights it was fitted for, the cases it was fitted
on and the exact command that fitted it (``python -m benchmarks.confidence.bench_confidence_calibration``; rerun it
when new weights ship). The features are functions of the signals only (:data:`FEATURES`), none of the network
that ran, so the same model applies to any registrar; a bundle without the file gets the shipped one.

Where a rule says a result is wrong whatever the model says (:func:`verdict`: inputs not in HU, inputs swapped,
too little overlap, a signal past its hand-set limit), the result is flagged and its confidence is capped below
the flag threshold, so that a flagged result never shows a confidence above it.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["CALIBRATION_FILE", "POLISH_PROBE_LIMIT_MM", "AMBIGUOUS_NCC_GAP", "UNCONVERGED_MM",
           "FEATURES", "FEATURE_SIGNS", "ConfidenceCalibration", "load_calibration", "verdict",
           "UNCALIBRATED_MEANING"]

logger = logging.getLogger(__name__)

CALIBRATION_FILE = "confidence_calibration.json"
"""The calibration's file name in a bundle's ``configs/``."""
POLISH_PROBE_LIMIT_MM = 1.5
"""The learned network alone (``fine_stage=False``) is flagged (``"unpolished"``) where the last level, run from its
estimate as a probe and discarded, would move it by more than this (mm, the mean over the network grid's points,
``details.signals.polish_probe_mm``): where the last level converges its move is about the estimate's error, a little
less where it stops short (on 19 network-alone estimates 2-4 mm off, probe over TRE 0.54-0.96, median 0.86), so a
2 mm error reads about 1.7 mm. At 1.5 mm the 286 re-collected calibration cases' 42 network-alone failures are all
flagged and none of its 10 successes more than before (it was 2.0 mm: two failures, 2.07 and 3.42 mm, passed).
Chosen on those cases (``bench_confidence_calibration --fit``'s "polish probe" lines; ``docs/trust.md``)."""
AMBIGUOUS_NCC_GAP = 0.1
"""A result is flagged ``"ambiguous"`` where its swapped-input estimate (the fallback's and the thorough path's
twin) disagrees with it by more than :data:`~monai_rigidreg.registration.confidence.AMBIGUOUS_TWIN_MM` and the two
match the images (the field of view's NCC, the score that chooses between them) within this of each other
(``details.signals.alternative_ncc_gap``): two distant poses fit about equally well, and the images do not settle
which is right (a short head CT, another patient's anatomy, a deformed pair without the search). Chosen on the
calibration's cases (``docs/trust.md``)."""
UNCONVERGED_MM = 1.0
"""A result is flagged ``"unconverged"`` where the last pass of the last level still moved the estimate by more than
this (mm, the mean over the network grid's points, ``details.signals.last_pass_mm``): the last level runs again until
a pass moves it by at most :data:`~monai_rigidreg.registration.last_level.NATIVE_CONVERGED_MM` (0.5 mm), so this
happens only where its passes ran out (:data:`~monai_rigidreg.registration.last_level.NATIVE_MAX_PASSES`) with the
estimate still travelling: no image optimum was reached. On the 286 calibration cases re-collected with bundle
0.5.0's weights it fired on 33 results: 29 failures, one of them (3.9 mm, a CT covering 31 % of the CBCT, last pass
3.7 mm) flagged by nothing else, and 4 right ones (0.76-0.95 mm), one flagged by nothing else (``docs/trust.md``).
A result whose last level needed all its passes to settle (``details.signals.last_level_exhausted``) is flagged
``"unconverged"`` too: the estimate travelled more than 0.5 mm in each of the first five passes. On the same cases
(collected again after 0.5.0 with the new rule's signals) that adds one failure no other signal caught (a partial
abdomen pair 3.00 mm off) and no false alarm of the default path on ordinary inputs; it flags one more right result
of the default path without its search (0.64 mm)."""
UNCALIBRATED_MEANING = ("an uncalibrated score: the weakest of the failure signals, each mapped through a logistic "
                        "that gives 0.5 at its hand-set limit (not a probability)")


def _finite(value: Any, default: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return default
    return v if math.isfinite(v) else default


def _logit(p: float) -> float:
    p = min(max(p, 1e-4), 1.0 - 1e-4)
    return math.log(p / (1.0 - p))


def _expected_tre(value: Any) -> float:
    """``signals.expected_tre_mm`` for the ``log_expected_tre`` feature, in [0.005, 10] mm: not measured (no last
    level, e.g. the learned network alone): 0.1 mm, about the default path's median; unconstrained (infinite): 10."""
    if value == math.inf:
        return 10.0
    return min(max(_finite(value, 0.1), 0.005), 10.0)


FEATURES: dict[str, Callable[[dict[str, Any]], float]] = {
    # the swapped-input estimate's disagreement (mm, log): an independent estimate's distance; not measured: 3 mm
    "log_swap_tre": lambda s: math.log(max(_finite(s.get("swap_tre_mm"), 3.0), 0.05)),
    # the same where it counts (a twin that matched the images worse does not count, confidence.SWAP_AGREE_MM)
    "log_swap_tre_counted": lambda s: (math.log(max(_finite(s.get("swap_tre_mm"), 3.0), 0.05))
                                       if s.get("swap_counted", True) else math.log(0.05)),
    # edge alignment gained by a small perturbation, in units of its limit (confidence.LOCAL_GAIN_LIMIT); not
    # measurable (too little of the field of view left for the edge test): as bad as it gets
    "local_gain": lambda s: min(_finite(s.get("local_gain"), 0.05) / 0.01, 5.0),
    # share of the CT's tissue put on CBCT air, in units of its limit (confidence.TISSUE_ON_AIR_LIMIT)
    "tissue_on_air": lambda s: min(_finite(s.get("tissue_on_air"), 0.0) / 0.06, 5.0),
    # intensity and edge NCC in the field of view after the estimate
    "ncc_after": lambda s: _finite(s.get("ncc_after"), 0.0),
    "edge_ncc": lambda s: _finite(s.get("edge_ncc"), 0.0),
    # the CBCT's tissue the CT does not cover under the estimate (registration.overlap)
    "overlap_deficit": lambda s: 1.0 - _finite(s.get("overlap"), 1.0),
    # the region check's median residual shift, in units of its limit (region_check.REGION_SHIFT_LIMIT_MM); no ROI: 0
    "region_shift": lambda s: min(_finite(s.get("region_shift_mm"), 0.0) / 3.0, 5.0),
    # how precisely the last level's images fix the pose (registration.precision, log mm)
    "log_expected_tre": lambda s: math.log(_expected_tre(s.get("expected_tre_mm"))),
    # the hand-set rule's score (confidence.confidence_score) as log-odds
    "rule_logit": lambda s: _logit(_finite(s.get("rule_score"), 0.5)),
}
"""The features a calibration may use, each a function of ``details.signals``. A name's meaning never changes: a
new transform gets a new name, so an older calibration file keeps its meaning."""

FEATURE_SIGNS: dict[str, int] = {
    "log_swap_tre": -1, "log_swap_tre_counted": -1, "local_gain": -1, "tissue_on_air": -1, "ncc_after": +1,
    "edge_ncc": +1, "overlap_deficit": -1, "region_shift": -1, "rule_logit": +1, "log_expected_tre": -1,
}
"""The sign each feature's coefficient may take: the confidence never rises as a failure signal gets worse (a larger
disagreement, edge gain, tissue on air, uncovered tissue or region shift; a lower match). The fit
(``bench_confidence_calibration``) drops a feature whose coefficient comes out of sign and refits, and
:class:`ConfidenceCalibration` refuses a model that breaks it."""


@dataclass(frozen=True)
class ConfidenceCalibration:
    """A fitted logistic model of the probability that the registration is right (:attr:`target`) given the
    signals. ``rule_flags``: a signal past its hand-set limit (the rule score below
    :data:`~monai_rigidreg.registration.confidence.CONFIDENCE_THRESHOLD`) flags the result too. ``path``: the file
    it was read from (``None``: built in code)."""

    version: str
    target: str
    features: tuple[str, ...]
    coefficients: tuple[float, ...]
    intercept: float
    flag_below: float
    bundle_version: str = ""
    rule_flags: bool = True
    fitted: dict[str, Any] = field(default_factory=dict)
    path: str | None = None

    def __post_init__(self) -> None:
        unknown = [f for f in self.features if f not in FEATURES]
        if unknown or len(self.features) != len(self.coefficients):
            raise ValueError(f"calibration {self.version}: unknown features {unknown} or a coefficient count that "
                             "does not match the features")
        against = [f for f, c in zip(self.features, self.coefficients) if c * FEATURE_SIGNS[f] < 0]
        if against:
            raise ValueError(f"calibration {self.version}: coefficients of {against} have the wrong sign (the "
                             "confidence would rise as the failure signal gets worse)")

    def probability(self, signals: dict[str, Any]) -> float:
        """The calibrated probability for ``signals`` (``details.signals``), in [0, 1]."""
        z = self.intercept + sum(c * FEATURES[f](signals) for f, c in zip(self.features, self.coefficients))
        return 1.0 / (1.0 + math.exp(-z)) if z > -700 else 0.0

    @property
    def meaning(self) -> str:
        """What the confidence says, in a sentence (``result.json``'s ``confidence_meaning``)."""
        return (f"{self.target}: the estimated probability, calibrated on held-out pairs (calibration {self.version}, "
                f"fitted for bundle {self.bundle_version or 'any'}); flagged below {self.flag_below:.2f}")

    def record(self) -> dict[str, Any]:
        """``details.confidence_calibration``: which calibration, for which bundle, and its flag threshold."""
        return {"version": self.version, "target": self.target, "bundle_version": self.bundle_version,
                "flag_below": self.flag_below, "file": self.path}

    @classmethod
    def from_dict(cls, data: dict[str, Any], path: str | None = None) -> ConfidenceCalibration:
        model = data["model"]
        return cls(version=str(data["version"]), target=str(data["target"]),
                   features=tuple(model["features"]), coefficients=tuple(float(c) for c in model["coefficients"]),
                   intercept=float(model["intercept"]), flag_below=float(data["flag_below"]),
                   bundle_version=str(data.get("bundle_version", "")), rule_flags=bool(data.get("rule_flags", True)),
                   fitted=dict(data.get("fitted", {})), path=path)

    def to_dict(self) -> dict[str, Any]:
        return {"version": self.version, "target": self.target, "bundle_version": self.bundle_version,
                "flag_below": self.flag_below, "rule_flags": self.rule_flags,
                "model": {"kind": "logistic", "features": list(self.features),
                          "coefficients": list(self.coefficients), "intercept": self.intercept},
                "fitted": self.fitted}


def load_calibration(bundle: str | Path | None = None) -> ConfidenceCalibration | None:
    """The calibration of ``bundle`` (its ``configs/``:data:`CALIBRATION_FILE`), else the shipped bundle's; ``None``
    where neither has one (the confidence is then the uncalibrated rule score, :data:`UNCALIBRATED_MEANING`)."""
    from monai_rigidreg.bundle.loader import default_bundle_path

    candidates = [] if bundle is None else [Path(bundle) / "configs" / CALIBRATION_FILE]
    try:
        candidates.append(default_bundle_path() / "configs" / CALIBRATION_FILE)
    except Exception:  # noqa: BLE001 - no shipped bundle (a stripped install): uncalibrated
        pass
    for path in candidates:
        if path.is_file():
            return ConfidenceCalibration.from_dict(json.loads(path.read_text()), path=str(path))
    return None


def verdict(signals: dict[str, Any], calibration: ConfidenceCalibration | None, rule_threshold: float,
            overlap_flag_below: float) -> tuple[float, list[str]]:
    """The confidence and why the result is flagged (empty: not flagged).

    ``signals`` (``details.signals``) hold ``rule_score`` (the hand-set rule,
    :func:`~monai_rigidreg.registration.confidence.confidence_score`), and where they apply ``not_hu``, ``swapped``
    (with ``swap_allowed``) and ``overlap``. Reasons: ``"not_hu"`` and ``"swapped"`` (confidence 0: the signals are
    calibrated on HU, and swapped inputs give the inverse transform), ``"overlap"`` (below ``overlap_flag_below``),
    ``"unpolished"`` (the learned network alone, ``fine_stage=False``, whose estimate the last level would move by
    more than :data:`POLISH_PROBE_LIMIT_MM`: ``polish_probe_mm``), ``"unconverged"`` (the last level's last pass still
    moved the estimate by more than :data:`UNCONVERGED_MM`: ``last_pass_mm``, or it needed all its passes:
    ``last_level_exhausted``), ``"ambiguous"`` (the swapped-input
    estimate lies more than :data:`~monai_rigidreg.registration.confidence.AMBIGUOUS_TWIN_MM` away, or another start's
    more than :data:`~monai_rigidreg.registration.overlap.AMBIGUOUS_DISTANCE_MM`, and the two match the images within
    :data:`AMBIGUOUS_NCC_GAP`: ``alternative_ncc_gap``; not for the network alone), ``"rule"`` (a signal past its
    hand-set limit: the rule score below ``rule_threshold``, where the calibration keeps the rule, ``rule_flags``),
    ``"confidence"`` (the
    calibrated probability below the calibration's ``flag_below``). A flagged result's confidence is capped just
    below the flag threshold.
    """
    rule = float(signals["rule_score"])
    confidence = calibration.probability(signals) if calibration is not None else rule
    threshold = calibration.flag_below if calibration is not None else rule_threshold
    reasons = []
    if signals.get("not_hu"):
        reasons.append("not_hu")
    if signals.get("swapped") and not signals.get("swap_allowed"):
        reasons.append("swapped")
    if _finite(signals.get("overlap"), 1.0) < overlap_flag_below:
        reasons.append("overlap")
    if _finite(signals.get("polish_probe_mm"), 0.0) > POLISH_PROBE_LIMIT_MM:
        reasons.append("unpolished")
    if _finite(signals.get("alternative_ncc_gap"), math.inf) < AMBIGUOUS_NCC_GAP and "polish_probe_mm" not in signals:
        reasons.append("ambiguous")  # (not for the learned network alone: neither estimate is at an image optimum)
    if _finite(signals.get("last_pass_mm"), 0.0) > UNCONVERGED_MM or signals.get("last_level_exhausted") is True:
        reasons.append("unconverged")
    if rule < rule_threshold and (calibration is None or calibration.rule_flags):
        reasons.append("rule")
    if confidence < threshold:
        reasons.append("confidence")
    if "not_hu" in reasons or "swapped" in reasons:
        confidence = 0.0
    elif reasons:
        confidence = min(confidence, max(0.0, threshold - 0.01))
    return float(confidence), reasons
