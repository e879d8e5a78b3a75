"""The peer tools' baselines (ANTs, greedy): each tool's transform convention checked on a pair with a known motion,
real registrations, real numbers; the wrong readings of the same output (a flipped sign, swapped axes, the inverse)
shown to miss. The pair itself is checked without the tools (SimpleITK)."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from monai_rigidreg.core.geometry import (
    LPS_TO_RAS,
    Grid,
    matrix_to_params,
    parameter_errors,
    params_to_matrix,
    params_to_sitk,
    ras_to_lps_transform,
)
from monai_rigidreg.registration.classical import moving_footprint, register_sitk
from monai_rigidreg.registration.peers import (
    CONVENTION_TOLERANCE,
    KNOWN_MOTION,
    ants_available,
    check_convention,
    greedy_available,
    known_motion_pair,
    register_ants,
)

NO_ANTS = "antspyx is not installed (the 'bench' extra; kept out of 'test': it pins numpy<2.4 and scipy<1.16)"
NO_GREEDY = "picsl-greedy is not installed (the 'bench' and 'test' extras)"
SWAP_XY = np.array([[0.0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])


def test_ras_to_lps_transform_flips_input_and_output():
    m = np.eye(4)
    m[:3, 3] = (5.0, 6.0, 7.0)
    np.testing.assert_allclose(ras_to_lps_transform(m)[:3, 3], (-5.0, -6.0, 7.0))
    r = params_to_sitk([0, 0, 0, 0, 0, 10.0]).GetMatrix()  # a rotation about z keeps its angle in both frames
    rot = np.eye(4)
    rot[:3, :3] = np.reshape(r, (3, 3))
    np.testing.assert_allclose(ras_to_lps_transform(rot), rot, atol=1e-12)
    rx = np.eye(4)
    rx[:3, :3] = np.reshape(params_to_sitk([0, 0, 0, 10.0, 0, 0]).GetMatrix(), (3, 3))
    np.testing.assert_allclose(matrix_to_params(ras_to_lps_transform(rx))[3], -10.0)  # about x: the sign flips
    np.testing.assert_allclose(ras_to_lps_transform(ras_to_lps_transform(m)), m)
    with pytest.raises(ValueError, match="4x4"):
        ras_to_lps_transform(np.eye(3))


def test_the_check_s_tolerance_is_at_most_half_of_what_any_misreading_of_the_known_motion_misses_by():
    """Every misreading of a right answer (a sign flipped per axis, two axes transposed, the inverse, RAS read as
    LPS) misses the known motion by at least twice the tolerance, so a tool's optimizer noise up to the tolerance
    cannot hide one."""
    fixed, _ = known_motion_pair()
    c = Grid.from_sitk(fixed).center()
    right = params_to_matrix(KNOWN_MOTION, c)
    readings = [np.linalg.inv(right), LPS_TO_RAS @ right @ LPS_TO_RAS, SWAP_XY @ right @ SWAP_XY]
    for a in range(3):
        flip = np.eye(4)
        flip[a, a] = -1.0
        readings.append(flip @ right @ flip)  # one axis reversed
        b = (a + 1) % 3
        swap = np.eye(4)
        swap[[a, b]] = swap[[b, a]]
        readings.append(swap @ right @ swap)
    errors = [parameter_errors(matrix_to_params(m, c), KNOWN_MOTION) for m in readings]
    # each reading on its own: its rotations miss by twice the degrees' tolerance, and its translations by twice the
    # millimetres' (the check fails a tool on either)
    rotation_misses = [float(e[3:].max()) for e in errors]
    translation_misses = [float(e[:3].max()) for e in errors]
    assert min(rotation_misses) >= 2 * CONVENTION_TOLERANCE[1], rotation_misses
    assert min(translation_misses) >= 2 * CONVENTION_TOLERANCE[0], translation_misses


def test_known_motion_pair_is_related_by_the_motion():
    """Without any peer tool: the moving image resampled through the known motion is the fixed image (within the
    CBCT's footprint, up to the interpolation), through the identity it is not; SimpleITK's Mattes MI, the package's
    own baseline, recovers the motion within the tolerance."""
    fixed, moving = known_motion_pair()
    c = Grid.from_sitk(fixed).center()
    ref = sitk.GetArrayFromImage(fixed)
    inside = sitk.GetArrayFromImage(moving_footprint(fixed, moving)) > 0

    def rms(params) -> float:
        out = sitk.GetArrayFromImage(sitk.Resample(moving, fixed, params_to_sitk(params, c), sitk.sitkLinear, np.nan))
        ok = inside & np.isfinite(out)
        return float(np.sqrt(np.mean((out[ok] - ref[ok]) ** 2)))

    assert rms(KNOWN_MOTION) < 0.3 * rms(np.zeros(6))
    res = register_sitk(fixed, moving, initial_params=np.zeros(6))
    err = parameter_errors(res.params, KNOWN_MOTION)
    assert err[:3].max() <= CONVENTION_TOLERANCE[0] and err[3:].max() <= CONVENTION_TOLERANCE[1], err


def _misses(matrix_lps: np.ndarray, center: np.ndarray) -> float:
    """Largest parameter error (mm or degrees) of a reading of a tool's output."""
    return float(parameter_errors(matrix_to_params(matrix_lps, center), KNOWN_MOTION).max())


def _native_reading(tool: str) -> tuple[np.ndarray, np.ndarray]:
    """A peer tool's output on the known-motion pair after its convention check passed: its native 4x4 and the
    rotation centre (mm)."""
    check = check_convention(tool)
    assert check["ok"], check["errors"]
    res = check["result"]
    assert res.extra["native_space"] == {"greedy": "RAS", "ants": "LPS"}[tool]
    return np.asarray(res.extra["native_matrix"]), res.center


@pytest.mark.skipif(not greedy_available(), reason=NO_GREEDY)
def test_greedy_convention_on_a_known_motion():
    """greedy's matrix is RAS, fixed -> moving: F Q F recovers the motion; Q read as LPS, its inverse, or the x and y
    axes swapped miss it by degrees or millimetres."""
    q, c = _native_reading("greedy")
    assert _misses(ras_to_lps_transform(q), c) <= CONVENTION_TOLERANCE[1]
    assert _misses(q, c) > 3.0  # RAS read as LPS: tx, ty, rx, ry flip sign
    assert _misses(np.linalg.inv(ras_to_lps_transform(q)), c) > 3.0  # moving -> fixed
    assert _misses(SWAP_XY @ ras_to_lps_transform(q) @ SWAP_XY, c) > 3.0  # x and y transposed


@pytest.mark.skipif(not ants_available(), reason=NO_ANTS)
def test_ants_convention_on_a_known_motion():
    """ANTs' GenericAffine.mat is LPS, fixed -> moving, read as it is: it recovers the motion; read as RAS, inverted,
    or with x and y swapped, it misses by degrees or millimetres."""
    a, c = _native_reading("ants")
    assert _misses(a, c) <= CONVENTION_TOLERANCE[1] + 1e-6
    assert _misses(LPS_TO_RAS @ a @ LPS_TO_RAS, c) > 3.0  # LPS read as RAS
    assert _misses(np.linalg.inv(a), c) > 3.0  # moving -> fixed
    assert _misses(SWAP_XY @ a @ SWAP_XY, c) > 3.0  # x and y transposed


def test_ants_starts_are_checked_before_anything_runs():
    fixed, moving = known_motion_pair()
    with pytest.raises(ValueError, match="start must be one of"):
        register_ants(fixed, moving, start="centre")


@pytest.mark.skipif(not ants_available(), reason=NO_ANTS)
def test_ants_from_its_own_centre_of_mass_start_reports_the_whole_transform():
    """Started from ANTsPy's default (the centres of mass aligned), the one transform file holds the start too: the
    known motion is recovered, not the motion less the start's translation."""
    check = check_convention("ants", start="mass")
    assert check["ok"], check["errors"]


@pytest.mark.skipif(not greedy_available(), reason=NO_GREEDY)
def test_greedy_leaves_no_output_and_repeats_with_its_seed(capfd):
    """Nothing printed (greedy's optimizer writes to the process's stdout directly), and the same seed gives the same
    answer."""
    from monai_rigidreg.registration.peers import register_greedy

    fixed, moving = known_motion_pair(size=40, spacing=4.8)
    a = register_greedy(fixed, moving, iterations=(50, 20), threads=1)
    b = register_greedy(fixed, moving, iterations=(50, 20), threads=1)
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    np.testing.assert_array_equal(a.params, b.params)
    assert a.stop_condition == "NMI -n 50x20"


def test_missing_tool_is_an_import_error_naming_the_extra(monkeypatch):
    import monai_rigidreg.registration.peers as peers

    monkeypatch.setattr(peers, "_installed", lambda name: False)
    fixed, moving = known_motion_pair(size=8, spacing=24.0)
    for fn, dist in ((peers.register_ants, "antspyx"), (peers.register_greedy, "picsl-greedy")):
        with pytest.raises(ImportError, match=rf"monai-rigidreg\[bench\].*{dist}"):
            fn(fixed, moving)
    assert not peers.peer_available("ants") and not peers.peer_available("greedy")


@pytest.mark.skipif(not greedy_available(), reason=NO_GREEDY)
def test_evaluate_runs_greedy_beside_sitk_on_the_same_cases(tiny_dataset):
    from monai_rigidreg.evaluation.evaluate import evaluate_datalist

    res = evaluate_datalist(tiny_dataset, ["sitk", "greedy"], None, progress=False, max_cases=2)
    by = {(c.case_id, c.method): c for c in res["cases"]}
    assert sorted({m for _, m in by}) == ["greedy", "sitk"] and len(by) == 4
    for case in res["cases"]:
        assert np.isfinite(case.tre_mm) and case.runtime_s > 0
    assert all(c.extra["stop"].startswith("NMI -n") for c in res["cases"] if c.method == "greedy")
    assert "greedy" in res["report"]


def test_evaluate_refuses_a_peer_method_whose_tool_is_missing(tiny_dataset, monkeypatch):
    import monai_rigidreg.evaluation.evaluate as evaluate
    from monai_rigidreg.core.errors import InputError

    monkeypatch.setattr(evaluate, "peer_available", lambda method: False)
    for method, dist in (("ants", "antspyx"), ("greedy", "picsl-greedy")):
        with pytest.raises(InputError, match=rf"{dist}.*monai-rigidreg\[bench\]"):
            evaluate.evaluate_datalist(tiny_dataset, [method], None, progress=False)


def test_register_peer_gives_the_field_of_view_only_where_the_mask_is_asked_for(monkeypatch):
    import monai_rigidreg.registration.peers as peers

    got = []
    for name in ("register_ants", "register_greedy"):
        monkeypatch.setattr(peers, name, lambda f, m, c=None, mask=None, _n=name: got.append((_n, mask)) or _n)
    fixed, moving = known_motion_pair(size=8, spacing=24.0)
    fov = sitk.Image(moving.GetSize(), sitk.sitkUInt8)
    for method, use, expect in (("ants", None, fov), ("greedy", True, fov), ("ants", False, None),
                                ("greedy", False, None)):
        got.clear()
        assert peers.register_peer(method, fixed, moving, moving_mask=fov, use_mask=use) == f"register_{method}"
        assert got == [(f"register_{method}", expect)]
    monkeypatch.setitem(peers.PEER_FOV_MASK, "ants", False)  # the tool's own default decides where use_mask is None
    got.clear()
    peers.register_peer("ants", fixed, moving, moving_mask=fov)
    assert got == [("register_ants", None)]
    with pytest.raises(ValueError, match="unknown peer method"):
        peers.register_peer("elastix", fixed, moving)


def test_evaluate_passes_the_peer_mask_choice_to_the_tool(tiny_dataset, monkeypatch):
    import monai_rigidreg.evaluation.evaluate as evaluate
    import monai_rigidreg.registration.peers as peers
    from monai_rigidreg.registration.classical import ClassicalResult

    masks = []

    def fake_greedy(fixed, moving, center=None, mask=None):
        masks.append(mask is not None)
        return ClassicalResult(np.zeros(6), np.asarray(center), runtime_s=0.0, stop_condition="fake")

    monkeypatch.setattr(peers, "register_greedy", fake_greedy)
    monkeypatch.setattr(evaluate, "peer_available", lambda method: True)
    for choice, expect in ((None, True), (True, True), (False, False)):
        masks.clear()
        evaluate.evaluate_datalist(tiny_dataset, ["greedy"], None, progress=False, max_cases=2, peer_mask=choice)
        assert masks == [expect, expect]
