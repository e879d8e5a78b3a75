"""Issue 35: a confidence that means what it says: the calibrated model, its versioned artefact, the verdict's rules,
what ``result.json`` says it means and how the command prints it."""

from __future__ import annotations

import json
import math

import pytest
from conftest import run_cli

from monai_rigidreg.registration.calibration import (
    CALIBRATION_FILE,
    FEATURES,
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
    assert cal.probability(good) > cal.flag_below > cal.probability(bad)
    assert 0.0 <= cal.probability(bad) <= cal.probability(good) <= 1.0


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
    with pytest.raises(ValueError, match="unknown features"):
        ConfidenceCalibration("t", "x", ("no_such_feature",), (1.0,), 0.0, 0.5)


def test_confidence_means_what_result_json_says_and_prints_with_two_digits(fast_pair, tmp_path, capsys):
    code, _ = run_cli(capsys, ["register", "--fixed", fast_pair["fixed"], "--moving", fast_pair["moving"],
                               "--output-dir", tmp_path / "out", "--no-qc", "--threads", "1"])
    printed = json.loads(capsys.readouterr().out.split("\n  ")[0])
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert code == 0 and 0.0 <= result["confidence"] <= 1.0
    assert result["confidence_meaning"].startswith("TRE under 2 mm: the estimated probability")
    assert result["details"]["confidence_calibration"]["flag_below"] == load_calibration().flag_below
    assert printed["confidence"] == round(result["confidence"], 2)
    assert printed["confidence_meaning"] == result["confidence_meaning"]
    assert result["flagged"] == (result["confidence"] < load_calibration().flag_below) or result["details"][
        "flag_reasons"]


