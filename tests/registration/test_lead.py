"""The network-led default path (``registration/lead.py``): no search where the network's polished estimate passes
the check, the fallback (search, further starts) where it does not, and what ``details`` records either way."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch
from conftest import KNOWN_MOTION, synth_ct

from monai_rigidreg.core.geometry import (
    Grid,
    matrix_to_sitk,
    params_to_matrix,
    recenter_params,
    target_registration_error,
)
from monai_rigidreg.evaluation.evaluate import body_points
from monai_rigidreg.io.volumes import load_volume
from monai_rigidreg.registration import RigidRegistrar
from monai_rigidreg.registration.last_level import FINE_STAGE_CHOICE_MM
from monai_rigidreg.registration.lead import (
    LEAD_CONFIDENCE,
    LEAD_MIN_OVERLAP,
    LEAD_POLISH_MAX_MM,
    LEAD_RANGE_DEG,
    LEAD_RANGE_MM,
)

ISO = np.array([20.0, -10.0, 15.0])
"""The CBCT isocentre of the large-motion pair, mm from the CT centre (the origin)."""


@pytest.fixture(scope="module")
def registrar() -> RigidRegistrar:
    return RigidRegistrar.from_bundle(device="cpu")


def test_an_easy_pair_takes_the_network_led_path_without_search_or_twin(fast_pair, registrar):
    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    res = registrar(fixed, moving, resample_moving=False)
    assert res.details["path"] == "network-led"
    assert res.details["fallback"] == {"run": False, "reasons": []}
    check = res.details["lead_check"]
    assert check["confidence"] >= LEAD_CONFIDENCE and check["overlap"] >= LEAD_MIN_OVERLAP
    assert check["polish_mm"] <= LEAD_POLISH_MAX_MM
    # the check's overlap is the overlap report's share of the field of view inside the CT (the estimate it checked
    # is the result's): one sample of the field of view, one measure
    assert check["overlap"] == pytest.approx(res.details["overlap"]["estimate"]["fov_in_ct"], abs=1e-4)
    assert check["max_translation_mm"] <= LEAD_RANGE_MM and check["max_rotation_deg"] <= LEAD_RANGE_DEG
    # neither the search nor the swapped-input estimate ran; the confidence is the calibrated one, from the check's
    # signals (the calibration's features need no twin)
    for stage in ("global_search", "fallback", "second_start", "swap_estimate"):
        assert stage not in res.timings
    assert "global_search" not in res.details and "swap_estimate" not in res.details
    assert np.isnan(res.details["signals"]["swap_tre_mm"]) and "swap_check" not in res.details
    for key in ("local_gain", "edge_ncc", "tissue_on_air"):
        assert res.details["signals"][key] == pytest.approx(check[key] if key != "edge_ncc" else
                                                            res.details["signals"][key], abs=1e-4)
    assert 0.0 <= res.confidence <= 1.0 and not res.flagged and res.details["flag_reasons"] == []
    points = body_points(fixed)
    tre = target_registration_error(res.params, KNOWN_MOTION, points, center=res.center)
    assert tre < 1.0
    # the thorough path on the same pair: the search and the twin ran, and the estimate is the same one (the same
    # network run and last level; the twin agreed and replaced nothing)
    thorough = registrar(fixed, moving, resample_moving=False, thorough=True)
    assert thorough.details["path"] == "thorough" and "fallback" not in thorough.details
    assert "global_search" in thorough.timings and np.isfinite(thorough.details["signals"]["swap_tre_mm"])
    assert target_registration_error(res.params, thorough.params, points, center=res.center) < 0.01
    assert res.confidence == pytest.approx(thorough.confidence, abs=0.02)


def _moved_cbct(ct: sitk.Image, matrix: np.ndarray, seed: int) -> sitk.Image:
    """A CBCT-like image, 64^3 at 2 mm centred on :data:`ISO`: ``CBCT(y) = CT(T^-1 y)`` plus noise and shading."""
    grid = Grid.centered((64, 64, 64), (2.0, 2.0, 2.0), ISO)
    cb = sitk.Resample(ct, grid.to_sitk(), matrix_to_sitk(np.linalg.inv(matrix)), sitk.sitkLinear, -1000.0)
    arr = sitk.GetArrayFromImage(cb)
    rng = np.random.default_rng(seed)
    arr = arr + 30.0 * rng.standard_normal(arr.shape) + 40.0 * np.linspace(-1, 1, arr.shape[0])[:, None, None]
    out = sitk.GetImageFromArray(arr.astype(np.float32))
    out.CopyInformation(cb)
    return out


def test_a_motion_beyond_the_networks_reach_fails_the_check_and_the_fallback_recovers_it(registrar):
    ct = synth_ct(Grid.centered((96, 96, 96), (3.0, 3.0, 3.0)), 11)
    # 90 degrees about z at the isocentre: far beyond the rotations the network was trained on (45 degrees; alone it
    # recovers 60 mm with 40 degrees about z on this CT, and with the converging last level the identity's run
    # reaches 80 degrees), reached from the global search's candidates
    truth = [0.0, 0.0, 0.0, 0.0, 0.0, 90.0]
    cbct = _moved_cbct(ct, params_to_matrix(truth, ISO), seed=2)
    axes = [np.linspace(a, b, 5) for a, b in zip(ISO - 40, ISO + 40)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)

    def tre(res) -> float:
        return target_registration_error(res.params, recenter_params(truth, ISO, res.center), points,
                                         center=res.center)

    # the check alone (lead_fallback off): the network's estimate is wrong and the check says so
    registrar.lead_fallback = False
    try:
        alone = registrar(ct, cbct, resample_moving=False)
    finally:
        registrar.lead_fallback = True
    assert tre(alone) > 10.0
    reasons = alone.details["lead_check"]["reasons"]
    assert reasons and alone.details["fallback"] == {"run": False, "reasons": reasons}
    # the default: the fallback runs for the same reasons, the search's start wins, and the result is right
    res = registrar(ct, cbct, resample_moving=False)
    assert res.details["path"] == "network-led"
    assert res.details["fallback"] == {"run": True, "reasons": reasons}
    assert res.details["start"] == "search" and "global_search" in res.details
    assert res.timings["fallback"] > 0 and "global_search" in res.timings
    assert np.isfinite(res.details["signals"]["swap_tre_mm"])  # the full confidence, with the twin
    assert tre(res) < 1.0 and not res.flagged


def test_a_fallback_that_finds_no_better_start_keeps_the_polished_estimate(fast_pair, registrar, monkeypatch):
    """With the trained range set below any motion, the easy pair fails the check on ``range`` alone: the search
    runs and agrees with the network, the twin (made after the check, the fallback's) agrees too, and the estimate is
    the polished one the check saw."""
    import monai_rigidreg.registration.lead as lead_mod

    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    plain = registrar(fixed, moving, resample_moving=False)
    monkeypatch.setattr(lead_mod, "LEAD_RANGE_MM", 0.0)
    res = registrar(fixed, moving, resample_moving=False)
    assert res.details["fallback"] == {"run": True, "reasons": ["range"]}
    assert res.details["start"] == "identity"
    assert "global_search" in res.details and res.details["swap_estimate"] == "after the check"
    np.testing.assert_allclose(res.params, plain.params, atol=1e-9)
    assert np.isfinite(res.details["signals"]["swap_tre_mm"]) and res.details["signals"]["swap_tre_mm"] < 3.0
    assert not res.flagged


def test_register_thorough_takes_the_thorough_path_from_python_and_the_command_line(fast_pair, registrar, tmp_path):
    import json

    from monai_rigidreg import register
    from monai_rigidreg.cli import main

    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    res = register(fixed, moving, model=registrar, resample_moving=False, thorough=True)
    assert res.details["path"] == "thorough" and "lead_check" not in res.details
    out = tmp_path / "out"
    assert main(["register", "--fixed", str(fast_pair["fixed"]), "--moving", str(fast_pair["moving"]),
                 "--output-dir", str(out), "--no-qc", "--thorough", "--device", "cpu"]) == 0
    details = json.loads((out / "result.json").read_text())["details"]
    assert details["path"] == "thorough" and "global_search" in details
    default = tmp_path / "default"
    assert main(["register", "--fixed", str(fast_pair["fixed"]), "--moving", str(fast_pair["moving"]),
                 "--output-dir", str(default), "--no-qc", "--device", "cpu"]) == 0
    details = json.loads((default / "result.json").read_text())["details"]
    assert details["path"] == "network-led" and details["fallback"]["run"] is False


OFFSET_DEG = 90.0
"""How far the tests of the fine-stage choice turn an estimate about z (degrees): beyond the last level's reach on
the fast pair, which pulls a 40-70 mm translation or a 60-degree turn about y back to the right pose."""


def _offset(params: torch.Tensor, sign: float = 1.0) -> torch.Tensor:
    """``params`` (``[B, 6]``, mm/deg) turned by ``sign`` * :data:`OFFSET_DEG` more about z."""
    out = params.clone()
    out[:, 5] += sign * OFFSET_DEG
    return out


def test_where_the_fine_stage_carries_a_right_estimate_away_the_regressions_goes_on(fast_pair, registrar,
                                                                                       monkeypatch):
    # the fine stage made to end 90 degrees about z from the regression's estimate, about 70 mm over the network
    # grid's points (the large abdomen's failure: 24-62 mm)
    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    monkeypatch.setattr(registrar, "lead_fallback", False)  # the choice itself, not the fallback's rescue
    stage = registrar.network.fine_stage
    monkeypatch.setattr(stage, "forward", lambda m, f, start, w=None: (
        _offset(start), torch.zeros(start.shape[0], dtype=torch.bool)))
    points = body_points(fixed)
    monkeypatch.setattr(registrar, "fine_stage_choice_mm", None)
    without = registrar(fixed, moving, resample_moving=False)
    assert "fine_stage_choice" not in without.details
    assert target_registration_error(without.params, KNOWN_MOTION, points, center=without.center) > 10.0
    monkeypatch.setattr(registrar, "fine_stage_choice_mm", FINE_STAGE_CHOICE_MM)
    res = registrar(fixed, moving, resample_moving=False)
    choice = res.details["fine_stage_choice"]
    assert choice["move_mm"] > 50.0
    assert choice["kept"] == "regression" and choice["regression_ncc"] > choice["fine_stage_ncc"]
    assert choice["end_distance_mm"] > 10.0 and "fine_stage_choice" in res.timings
    assert target_registration_error(res.params, KNOWN_MOTION, points, center=res.center) < 1.0
    # the kept pose's last level is the one recorded: it polished the regression's estimate (a few tenths of a mm)
    assert res.details["native_level"]["change_mm"] < LEAD_POLISH_MAX_MM and not res.flagged
    # the network's own final estimate was overruled: the check fails on "choice", and with the fallback on the
    # search and the swapped-input estimate judge the kept pose (here they keep it)
    assert res.details["lead_check"]["reasons"] == ["choice"]
    monkeypatch.setattr(registrar, "lead_fallback", True)
    led = registrar(fixed, moving, resample_moving=False)
    assert led.details["fallback"] == {"run": True, "reasons": ["choice"]} and "global_search" in led.timings
    assert target_registration_error(led.params, KNOWN_MOTION, points, center=led.center) < 1.0
    monkeypatch.setattr(registrar, "lead_fallback", False)
    # the run that goes on carries the regression's estimate (what the fallback's choice between starts compares),
    # and on the thorough path the swapped-input estimate started beside the last level is computed again
    seen = []
    runner_up = registrar._runner_up_within_ct

    def spy(state, refined):
        seen.append((state.run.residual.copy(), state.run.regression.copy()))
        return runner_up(state, refined)

    monkeypatch.setattr(registrar, "_runner_up_within_ct", spy)
    thorough = registrar(fixed, moving, resample_moving=False, thorough=True)
    assert thorough.details["fine_stage_choice"]["kept"] == "regression"
    np.testing.assert_allclose(seen[-1][0], seen[-1][1], atol=1e-12)
    assert thorough.details["swap_estimate"] == "after the last level"
    assert target_registration_error(thorough.params, KNOWN_MOTION, points, center=thorough.center) < 1.0


def test_where_the_fine_stage_corrects_a_wrong_regression_its_estimate_goes_on(fast_pair, registrar, monkeypatch):
    # the mirror: the fine stage receives a regression estimate 90 degrees off (a pre-hook registered before the
    # choice's own, which sees what it returns) but works from the right one, so its end pose is right and the
    # regression's is not
    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    monkeypatch.setattr(registrar, "lead_fallback", False)
    stage = registrar.network.fine_stage
    forward = stage.forward
    handle = stage.register_forward_pre_hook(lambda module, args: (args[0], args[1], _offset(args[2]), *args[3:]))
    try:
        monkeypatch.setattr(stage, "forward", lambda m, f, start, w=None: forward(m, f, _offset(start, -1.0), w))
        res = registrar(fixed, moving, resample_moving=False)
    finally:
        handle.remove()
    choice = res.details["fine_stage_choice"]
    assert choice["move_mm"] > 50.0
    assert choice["kept"] == "fine stage" and choice["fine_stage_ncc"] > choice["regression_ncc"]
    assert "choice" not in res.details["lead_check"]["reasons"]  # the network's final estimate stands
    assert target_registration_error(res.params, KNOWN_MOTION, body_points(fixed), center=res.center) < 1.0


def test_an_easy_pair_records_the_fine_stages_move_and_runs_no_choice(fast_pair, registrar, monkeypatch):
    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    res = registrar(fixed, moving, resample_moving=False)
    choice = res.details["fine_stage_choice"]
    assert set(choice) == {"move_mm"} and 0.0 <= choice["move_mm"] <= FINE_STAGE_CHOICE_MM
    assert "fine_stage_choice" not in res.timings
    monkeypatch.setattr(registrar, "fine_stage_choice_mm", None)
    off = registrar(fixed, moving, resample_moving=False)
    np.testing.assert_allclose(res.params, off.params, atol=1e-9)
    # the learned network alone has no fine stage to choose against
    alone = registrar(fixed, moving, resample_moving=False, fine_stage=False)
    assert "fine_stage_choice" not in alone.details


def test_the_regression_estimate_caught_before_the_fine_stage_is_its_coarse_output(fast_pair, registrar):
    from monai_rigidreg.registration.network_run import _regression_estimates

    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    _, fixed_t, moving_t = registrar._start_tensors(fixed, moving, np.eye(4))
    fixed_in = torch.cat([fixed_t, registrar._context(fixed, registrar.network_grid(fixed, moving), None)], 0)
    net = registrar.network
    with torch.no_grad():
        stages = net.forward_stages(moving_t[None], fixed_in[None])
        with _regression_estimates(net, 1, 1) as caught:
            params = net.forward_pair(moving_t[None], fixed_in[None])
    assert len(caught) == 1
    np.testing.assert_allclose(caught[0], stages["coarse"].double().numpy(), atol=1e-6)
    np.testing.assert_allclose(params.numpy(), stages["params"].numpy(), atol=1e-6)
    with _regression_estimates(net, 2, 1) as cascade:  # a cascade runs the fine stage once per step
        assert cascade is None
    # nothing stays hooked
    assert not net.fine_stage._forward_pre_hooks


def test_each_starts_regression_estimate_is_in_the_frame_of_its_total(fast_pair, registrar, monkeypatch):
    # a batch of three starts (the global search's candidates): the fine stage made to return the regression's
    # estimate unchanged, then moved by a known translation per case (5 mm times the case's index along x)
    from monai_rigidreg.registration.search import matrix_distance_mm

    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    center = Grid.from_sitk(moving).center()
    starts = [params_to_matrix(p, center) for p in
              ([0.0, 0.0, 0.0, 0.0, 0.0, 0.0], [30.0, -6.0, 4.0, 0.0, 20.0, 0.0], [-8.0, 25.0, 9.0, -20.0, 0.0, 15.0])]
    stage = registrar.network.fine_stage
    monkeypatch.setattr(stage, "forward", lambda m, f, start, w=None: (
        start.clone(), torch.ones(start.shape[0], dtype=torch.bool)))
    runs = registrar._runs_from(fixed, moving, starts, None, [], {})
    for run in runs:
        np.testing.assert_allclose(run.regression_total, run.total, atol=1e-9)
        np.testing.assert_allclose(run.regression, run.residual, atol=1e-9)

    def moved(m, f, start, w=None):
        out = start.clone()
        out[:, 0] += 5.0 * torch.arange(start.shape[0], dtype=start.dtype)
        return out, torch.zeros(start.shape[0], dtype=torch.bool)

    monkeypatch.setattr(stage, "forward", moved)
    runs = registrar._runs_from(fixed, moving, starts, None, [], {})
    for k, run in enumerate(runs):
        # the start's rotation turns the residual's translation but keeps its length
        assert matrix_distance_mm(run.total, run.regression_total, np.asarray(body_points(fixed))[:200]) == \
            pytest.approx(5.0 * k, abs=1e-6)
        np.testing.assert_allclose(run.total, run.start @ params_to_matrix(run.residual, run.grid.center()),
                                   atol=1e-9)
