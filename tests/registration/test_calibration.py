"""Issue 35: a confidence that means what it says: the calibrated model, its versioned artefact, the verdict's rules,
what ``result.json`` says it means and how the command prints it."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from monai_rigidreg.registration.calibration import (
    AMBIGUOUS_NCC_GAP,
    CALIBRATION_FILE,
    FEATURES,
    UNCONVERGED_MM,
    ConfidenceCalibration,
    load_calibration,
    verdict,
)


def test_the_shipped_calibration_is_a_versioned_fitted_artefact():
    import monai_rigidreg
    from monai_rigidreg.bundle.loader import default_bundle_path

    path = default_bundle_path() / "configs" / CALIBRATION_FILE
    record = json.loads(path.read_text())
    assert record["target"] == "TRE under 2 mm" and record["bundle_version"] == monai_rigidreg.__version__
    assert "bench_confidence_calibration" in record["fitted"]["command"]
    assert record["fitted"]["held_out"]["protocol"] == "leave one CT out"
    cal = load_calibration()
    assert cal is not None and cal.path == str(path) and all(f in FEATURES for f in cal.features)
    assert 0.0 < cal.flag_below < 1.0
    good = {"local_gain": 0.0, "swap_tre_mm": 0.3, "swap_counted": True, "tissue_on_air": 0.0, "ncc_after": 0.9,
            "edge_ncc": 0.9, "overlap": 1.0, "rule_score": 0.97}
    bad = {**good, "swap_tre_mm": 12.0, "local_gain": 0.03, "tissue_on_air": 0.1, "rule_score": 0.0}
    assert 0.0 <= cal.probability(bad) <= cal.probability(good) <= 1.0  # monotone: worse signals never raise it
    # what a user sees (the verdict with the shipped artefact): the good pair passes, the bad one is flagged; a poor
    # edge match alone lowers the calibrated confidence below the flag
    good_conf, good_reasons = verdict(good, cal, 0.5, 0.2)
    bad_conf, bad_reasons = verdict(bad, cal, 0.5, 0.2)
    assert good_reasons == [] and good_conf > cal.flag_below > bad_conf and bad_reasons
    assert cal.probability({**good, "edge_ncc": 0.0}) < cal.flag_below


def test_the_verdict_rules_and_the_cap_below_the_flag_threshold():
    cal = ConfidenceCalibration("t", "TRE under 2 mm", ("log_swap_tre",), (-2.0,), 2.0, 0.8)
    ok = {"swap_tre_mm": 0.3, "rule_score": 0.97, "overlap": 1.0, "swapped": False}
    conf, reasons = verdict(ok, cal, 0.5, 0.35)
    assert reasons == [] and conf == pytest.approx(1 / (1 + math.exp(-(2.0 - 2.0 * math.log(0.3)))))
    assert verdict({**ok, "not_hu": ["moving (CBCT)"]}, cal, 0.5, 0.35) == (0.0, ["not_hu"])
    assert verdict({**ok, "swapped": True, "swap_allowed": False}, cal, 0.5, 0.35) == (0.0, ["swapped"])
    assert verdict({**ok, "swapped": True, "swap_allowed": True}, cal, 0.5, 0.35)[1] == []
    conf, reasons = verdict({**ok, "overlap": 0.2}, cal, 0.5, 0.35)
    assert reasons == ["overlap"] and conf == pytest.approx(0.79)  # flagged: capped below the threshold
    conf, reasons = verdict({**ok, "rule_score": 0.1}, cal, 0.5, 0.35)
    assert reasons == ["rule"] and conf < 0.8
    assert verdict({**ok, "swap_tre_mm": 20.0}, cal, 0.5, 0.35)[1] == ["confidence"]
    # two distant estimates that match the images about as well: ambiguous; a clear winner is not
    conf, reasons = verdict({**ok, "alternative_ncc_gap": AMBIGUOUS_NCC_GAP / 2}, cal, 0.5, 0.35)
    assert reasons == ["ambiguous"] and conf == pytest.approx(0.79)
    assert verdict({**ok, "alternative_ncc_gap": 2 * AMBIGUOUS_NCC_GAP}, cal, 0.5, 0.35)[1] == []
    # the learned network alone (it carries the polish probe): its twin is no image optimum either, not ambiguity
    assert verdict({**ok, "alternative_ncc_gap": 0.01, "polish_probe_mm": 0.5}, cal, 0.5, 0.35)[1] == []
    assert verdict({**ok, "polish_probe_mm": 2.5}, cal, 0.5, 0.35)[1] == ["unpolished"]
    assert verdict({**ok, "polish_probe_mm": 1.5}, cal, 0.5, 0.35)[1] == []
    # the last level's passes ran out with the estimate still moving: no image optimum reached
    conf, reasons = verdict({**ok, "last_pass_mm": UNCONVERGED_MM + 0.5}, cal, 0.5, 0.35)
    assert reasons == ["unconverged"] and conf == pytest.approx(0.79)
    assert verdict({**ok, "last_pass_mm": UNCONVERGED_MM}, cal, 0.5, 0.35)[1] == []
    # or it settled only on the last pass it was allowed
    assert verdict({**ok, "last_pass_mm": 0.2, "last_level_exhausted": True}, cal, 0.5, 0.35)[1] == ["unconverged"]
    assert verdict({**ok, "last_pass_mm": 0.2, "last_level_exhausted": False}, cal, 0.5, 0.35)[1] == []
    with pytest.raises(ValueError, match="unknown features"):
        ConfidenceCalibration("t", "x", ("no_such_feature",), (1.0,), 0.0, 0.5)


def test_confidence_means_what_result_json_says_and_prints_with_two_digits(fast_pair, tmp_path, capsys):
    from monai_rigidreg.cli import main

    code = main(["register", "--fixed", str(fast_pair["fixed"]), "--moving", str(fast_pair["moving"]),
                 "--output-dir", str(tmp_path / "out"), "--no-qc", "--threads", "1"])
    printed = json.loads(capsys.readouterr().out.split("\noutputs:")[0])
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert code == 0 and 0.0 <= result["confidence"] <= 1.0
    assert result["confidence_meaning"].startswith("TRE under 2 mm: the estimated probability")
    assert result["details"]["confidence_calibration"]["flag_below"] == load_calibration().flag_below
    assert printed["confidence"] == round(result["confidence"], 2)
    assert printed["confidence_meaning"] == result["confidence_meaning"]
    assert result["flagged"] == (result["confidence"] < load_calibration().flag_below) or result["details"][
        "flag_reasons"]


def _signal_grid():
    """Signals from good to bad on each failure signal in turn (the others good), and the extremes a registration
    can report (NaN where a signal was not measurable, infinities, missing keys)."""
    good = {"local_gain": 0.0, "swap_tre_mm": 0.2, "swap_counted": True, "tissue_on_air": 0.0, "ncc_after": 0.95,
            "edge_ncc": 0.9, "overlap": 1.0, "region_shift_mm": 0.0, "rule_score": 0.97, "expected_tre_mm": 0.05}
    worse = {"local_gain": [0.0, 0.002, 0.01, 0.03, 0.2], "swap_tre_mm": [0.05, 0.5, 2.0, 10.0, 200.0],
             "tissue_on_air": [0.0, 0.03, 0.06, 0.2, 1.0], "ncc_after": [1.0, 0.8, 0.5, 0.1, -0.5],
             "edge_ncc": [1.0, 0.8, 0.5, 0.1, -0.5], "overlap": [1.0, 0.8, 0.5, 0.2, 0.0],
             "region_shift_mm": [0.0, 1.0, 3.0, 9.0, 50.0], "rule_score": [1.0, 0.9, 0.5, 0.1, 0.0],
             "expected_tre_mm": [0.001, 0.05, 0.3, 20.0, float("inf")]}
    return good, worse


def test_the_shipped_calibration_is_monotone_and_in_range():
    """Worse on any one failure signal never raises the confidence; every value, odd ones included, lies in [0, 1]."""
    from monai_rigidreg.registration.calibration import FEATURE_SIGNS

    cal = load_calibration()
    assert all(c * FEATURE_SIGNS[f] >= 0 for f, c in zip(cal.features, cal.coefficients))
    good, worse = _signal_grid()
    for key, values in worse.items():
        probs = [cal.probability({**good, key: v}) for v in values]
        assert all(0.0 <= p <= 1.0 for p in probs), (key, probs)
        assert all(b <= a + 1e-12 for a, b in zip(probs, probs[1:])), (key, probs)
    odd = [{}, {"rule_score": 0.5}, {**good, "swap_tre_mm": float("nan"), "local_gain": float("nan")},
           {**good, "swap_tre_mm": float("inf"), "tissue_on_air": float("inf"), "overlap": float("-inf")},
           {**good, "swap_counted": False}, {**good, "edge_ncc": None}, {**good, "expected_tre_mm": float("nan")},
           {**good, "expected_tre_mm": None}, {**good, "expected_tre_mm": float("-inf")}]
    for signals in odd:
        assert 0.0 <= cal.probability(signals) <= 1.0
        conf, _ = verdict({"rule_score": 0.5, **signals}, cal, 0.5, 0.35)
        assert 0.0 <= conf <= 1.0


def test_a_model_against_a_signals_direction_is_refused_and_the_fit_drops_it():
    """The fit keeps every coefficient on its side (collinear signals can flip one): on data where success falls
    with the disagreement and the edge NCC is, by construction, higher on the failures, the edge NCC is dropped."""
    from benchmarks.confidence.bench_confidence_calibration import logistic_fit, monotone_fit

    with pytest.raises(ValueError, match="wrong sign"):
        ConfidenceCalibration("t", "x", ("edge_ncc",), (-1.0,), 0.0, 0.5)
    rng = np.random.default_rng(35)
    swap = np.exp(rng.uniform(np.log(0.05), np.log(30.0), 400))
    ok = rng.random(400) < 1 / (1 + np.exp(-(1.5 - 2.0 * np.log(swap))))
    rows = [{"success": bool(s), "signals": {"swap_tre_mm": float(t), "edge_ncc": 0.9 - 0.3 * bool(s) +
                                             0.05 * rng.normal()}} for t, s in zip(swap, ok)]
    features, coef, _ = monotone_fit(rows, ("log_swap_tre", "edge_ncc"), l2=1.0)
    assert features == ("log_swap_tre",) and coef[0] < 0
    # logistic_fit recovers a known model on plenty of data (the penalty is small against 4000 cases)
    x = rng.normal(size=(4000, 2))
    y = (rng.random(4000) < 1 / (1 + np.exp(-(0.5 + 2.0 * x[:, 0] - 1.0 * x[:, 1])))).astype(float)
    c, b = logistic_fit(x, y, l2=1.0)
    assert np.allclose(c, [2.0, -1.0], atol=0.25) and abs(b - 0.5) < 0.2


def test_the_flag_threshold_keeps_false_alarms_at_the_rate_asked():
    """``choose_threshold`` raises the threshold past each failure while at most 10 % of successes are flagged."""
    from benchmarks.confidence.bench_confidence_calibration import choose_threshold

    p = np.array([0.99] * 18 + [0.6, 0.55] + [0.58, 0.3, 0.1])
    y = np.array([1] * 20 + [0, 0, 0])
    forced = np.zeros(len(p), dtype=bool)
    t = choose_threshold(p, y, forced, 0.1)
    assert t == pytest.approx(0.585)  # past every failure (0.58): the successes at 0.55 flagged, 1 in 20
    assert ((p < t) & (y == 1)).sum() / 20 <= 0.1 and ((p < t) | (y == 1)).all()
    assert choose_threshold(p, y, forced, 0.0) == 0.5  # no false alarm allowed: stays at 0.5
