"""The last level at native resolution: its grid, and a residual of a few mm / degrees removed to a fraction of a mm."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch
from conftest import synth_ct

from monai_rigidreg.core.geometry import Grid, matrix_to_sitk, params_to_matrix, transform_points
from monai_rigidreg.core.image_ops import erode
from monai_rigidreg.core.warp import warp_volume
from monai_rigidreg.registration.confidence import cylindrical_fov_mask
from monai_rigidreg.registration.last_level import native_grid, refine_native, support_reach


def _pair(truth_iso, iso, cb_size=(96, 96, 60), cb_spacing=1.5, seed=21):
    grid = Grid.centered((90, 90, 90), (2.5, 2.5, 2.5))
    ct = synth_ct(grid, seed)
    truth = params_to_matrix(truth_iso, iso)
    cb_grid = Grid.centered(cb_size, (cb_spacing,) * 3, iso)
    cbct = sitk.Resample(ct, cb_grid.to_sitk(), matrix_to_sitk(np.linalg.inv(truth)), sitk.sitkLinear, -1000.0)
    arr = sitk.GetArrayFromImage(cbct) + 25.0 * np.random.default_rng(seed).standard_normal(cb_size[::-1])
    noisy = sitk.GetImageFromArray(arr.astype(np.float32))
    noisy.CopyInformation(cbct)
    return ct, noisy, truth


def _mean_distance(a, b, pts):
    return float(np.linalg.norm(transform_points(a, pts) - transform_points(b, pts), axis=1).mean())


def test_native_grid_covers_the_cbct_at_the_finer_spacing_within_the_voxel_budget():
    iso = np.array([10.0, -20.0, 5.0])
    ct, cbct, truth = _pair([0, 0, 0, 0, 0, 0], iso)
    g = native_grid(ct, cbct, truth)
    assert g.spacing == (1.5, 1.5, 1.5)  # the CBCT's, finer than the CT's 2.5 mm
    assert g.size == (96, 96, 60)  # its extent (144 x 144 x 90 mm)
    np.testing.assert_allclose(g.center(), iso, atol=1e-9)  # T^-1 of the CBCT centre (identity here)
    moved = params_to_matrix([20.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(native_grid(ct, cbct, moved).center(), iso - [20.0, 0.0, 0.0], atol=1e-9)
    small = native_grid(ct, cbct, truth, max_voxels=100_000)
    assert small.spacing[0] > 1.5 and np.prod(small.size) <= 100_000


def test_refine_native_removes_a_residual_of_a_few_mm_and_degrees():
    iso = np.array([10.0, -20.0, 5.0])
    truth_iso = [6.0, -3.0, 4.0, 4.0, -3.0, 5.0]
    ct, cbct, truth = _pair(truth_iso, iso)
    start = truth @ params_to_matrix([1.5, -1.0, 1.2, 1.0, -0.8, 1.2], iso)  # the network's residual error
    box = np.stack(np.meshgrid(*[np.linspace(-50, 50, 5)] * 3, indexing="ij"), -1).reshape(-1, 3) + iso
    before = _mean_distance(start, truth, box)
    refined, grid = refine_native(ct, cbct, start, cylindrical_fov_mask(cbct))
    after = _mean_distance(refined, truth, box)
    assert before > 2.0
    assert after < 0.2, (before, after)
    assert grid.spacing == (1.5, 1.5, 1.5)
    # at the truth it stays there; with the window clipped at air (-1000 HU) the CBCT's noisy air biases the pose
    stay, _ = refine_native(ct, cbct, truth, cylindrical_fov_mask(cbct))
    assert _mean_distance(stay, truth, box) < 0.1
    clipped, _ = refine_native(ct, cbct, truth, cylindrical_fov_mask(cbct), hu_range=(-1000.0, 2000.0))
    assert _mean_distance(clipped, truth, box) > 0.2


def test_a_constant_bias_term_keeps_the_pose_under_a_cbct_hu_offset():
    """A CBCT 300 HU brighter than the CT (a calibration offset, common on real CBCTs), started at the truth: with
    a constant bias term (``native_bias_degree=0``, the fine stage's 2 includes it) the last level stays at the truth
    (0.03 mm, as without an offset); without a bias term the offset pulls the pose (0.10 mm here, growing with the
    offset: 0.05 mm at 150 HU)."""
    iso = np.array([10.0, -20.0, 5.0])
    truth_iso = [6.0, -3.0, 4.0, 4.0, -3.0, 5.0]
    ct, cbct, truth = _pair(truth_iso, iso)
    cbct = sitk.Threshold(cbct + 300.0, -5000.0, 5000.0, 0.0)  # the offset everywhere in the scan
    box = np.stack(np.meshgrid(*[np.linspace(-50, 50, 5)] * 3, indexing="ij"), -1).reshape(-1, 3) + iso
    fov = cylindrical_fov_mask(cbct)
    constant, _ = refine_native(ct, cbct, truth, fov, bias_degree=0)
    none, _ = refine_native(ct, cbct, truth, fov, bias_degree=-1)
    assert _mean_distance(constant, truth, box) < 0.1
    assert _mean_distance(none, truth, box) > 2 * _mean_distance(constant, truth, box)


def test_registrar_passes_its_native_bias_degree_to_the_last_level(monkeypatch):
    """The bundle's degrees reach refine_native: native_bias_degree (0) over the whole field of view,
    native_bias_degree_roi (2) with a match region; a registrar built with other degrees uses them (the region one
    defaults to the whole-FOV one); degrees below -1 are refused."""
    import pytest

    import monai_rigidreg.registration.last_level as ll_mod
    import monai_rigidreg.registration.registrar as reg_mod
    from monai_rigidreg.core.errors import InputError

    seen = []

    def record(*args, **kwargs):
        seen.append(kwargs["bias_degree"])
        raise RuntimeError("stop")

    monkeypatch.setattr(ll_mod, "refine_native", record)
    for (whole, roi), registrar in (
        ((0, 2), reg_mod.RigidRegistrar.from_bundle(device="cpu")),
        ((1, 1), reg_mod.RigidRegistrar.from_bundle(device="cpu", native_bias_degree=1,
                                                    native_bias_degree_roi=None)),
        ((-1, 2), reg_mod.RigidRegistrar.from_bundle(device="cpu", native_bias_degree=-1)),
    ):
        assert (registrar.native_bias_degree, registrar.native_bias_degree_roi) == (whole, roi)
        for region, degree in ((False, whole), (True, roi)):
            with pytest.raises(RuntimeError, match="stop"):
                registrar._native(None, None, np.eye(4), None, [], None, region=region)
            assert seen[-1] == degree
    with pytest.raises(InputError, match="native_bias_degree"):
        reg_mod.RigidRegistrar.from_bundle(device="cpu", native_bias_degree=-2)
    # the local-contrast scale: the bundle's 4 mm, or the fine stage's own (16 mm) when None; <= 0 refused
    sigmas = []

    def record_sigma(*args, **kwargs):
        sigmas.append(kwargs["highpass_sigma_mm"])
        raise RuntimeError("stop")

    monkeypatch.setattr(ll_mod, "refine_native", record_sigma)
    shipped = reg_mod.RigidRegistrar.from_bundle(device="cpu")
    own = reg_mod.RigidRegistrar.from_bundle(device="cpu", native_highpass_sigma_mm=None)
    for registrar in (shipped, own):
        with pytest.raises(RuntimeError, match="stop"):
            registrar._native(None, None, np.eye(4), None, [], None)
    assert sigmas == [4.0, own.network.fine_stage.highpass_sigma_mm] and sigmas[1] == 16.0
    with pytest.raises(InputError, match="native_highpass_sigma_mm"):
        reg_mod.RigidRegistrar.from_bundle(device="cpu", native_highpass_sigma_mm=0.0)
    with pytest.raises(InputError, match="native_bias_degree_roi"):
        reg_mod.RigidRegistrar.from_bundle(device="cpu", native_bias_degree_roi=-3)


@pytest.mark.parametrize("spacing", [(1.875, 1.875, 1.875), (1.0, 1.5, 2.5)])
def test_support_reach_holds_every_voxel_the_moved_support_covers(spacing):
    # every voxel where the support warped by a motion within the reach covers (> 0.999, as the steps count it) is a
    # candidate; motions just past the reach can cover voxels outside (the reach is not loose by much)
    grid = Grid.centered((40, 36, 32), spacing, (0.0, 0.0, 0.0))
    idx = torch.meshgrid(*[torch.arange(n, dtype=torch.float32) - (n - 1) / 2 for n in grid.size], indexing="ij")
    fov = ((idx[0] * spacing[0]) ** 2 + (idx[1] * spacing[1]) ** 2 < 30.0**2).float()[None, None]  # a cylinder
    radius = [max(1, round(8.0 / s)) for s in spacing]
    support = erode(fov, radius)
    cand, reach = support_reach(fov, radius, spacing, None)
    assert cand.dtype == torch.bool and cand.shape == fov.shape
    assert torch.equal(cand, fov > 0)
    assert reach == pytest.approx(min((r + 0.5) * s for r, s in zip(radius, spacing)))
    rng = np.random.default_rng(0)
    corners = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)]) * (np.asarray(grid.size) - 1)
    corners = corners * np.asarray(spacing) + np.asarray(grid.origin)
    outside = 0
    for k in range(40):
        p = rng.uniform(-1, 1, 6) * [1, 1, 1, 0.2, 0.2, 0.2]  # mostly translation: the corners move ~ the inside
        target = reach * (rng.uniform(0.7, 0.999) if k < 30 else rng.uniform(1.3, 2.0))
        for _ in range(8):  # scaled until the farthest corner moves target mm (within 1 %)
            m = params_to_matrix(p)
            moved = np.linalg.norm(transform_points(m, corners) - corners, axis=1).max()
            p = p * target / moved
        m = params_to_matrix(p)
        moved = np.linalg.norm(transform_points(m, corners) - corners, axis=1).max()
        covered = warp_volume(support, torch.as_tensor(m)[None], grid, grid) > 0.999
        if moved < reach:
            assert not (covered & ~cand).any(), (k, moved, reach)
        else:
            outside += int(bool((covered & ~cand).any()))
    assert outside >= 1  # past the reach the guarantee is gone
    weight = torch.ones_like(fov)
    weight[..., :5] = 0.0
    assert not support_reach(fov, radius, spacing, weight)[0][..., :5].any()


def test_refine_native_sums_over_the_field_of_view_only_where_it_leaves_enough_out(monkeypatch):
    # the candidates go to the steps where they are at most CANDIDATE_SHARE_MAX of the grid (a cylinder in its box),
    # not where the field of view fills the grid (the dense steps are cheaper there); the estimate is the same
    import monai_rigidreg.registration.last_level as precision

    iso = np.array([10.0, -20.0, 5.0])
    truth_iso = [2.0, -1.0, 1.5, 1.0, -0.5, 1.0]
    ct, cbct, truth = _pair(truth_iso, iso)
    seen = []
    real = precision.gauss_newton_align

    def spy(*args, **kwargs):
        cand = kwargs.get("candidates")
        seen.append(None if cand is None else float(cand.float().mean()))
        return real(*args, **kwargs)

    monkeypatch.setattr(precision, "gauss_newton_align", spy)
    cylinder = cylindrical_fov_mask(cbct)
    everywhere = sitk.Cast(cbct * 0 + 1, sitk.sitkUInt8)
    refined, _ = refine_native(ct, cbct, np.eye(4), cylinder)
    full, _ = refine_native(ct, cbct, np.eye(4), everywhere)
    assert seen[0] is not None and seen[0] <= precision.CANDIDATE_SHARE_MAX
    assert seen[1] is None
    monkeypatch.setattr(precision, "CANDIDATE_SHARE_MAX", 0.0)  # the same case with the dense steps
    dense, _ = refine_native(ct, cbct, np.eye(4), cylinder)
    assert seen[2] is None
    box = np.stack(np.meshgrid(*[np.linspace(-50, 50, 5)] * 3, indexing="ij"), -1).reshape(-1, 3) + iso
    assert _mean_distance(refined, dense, box) < 1e-4
    assert _mean_distance(refined, truth, box) < 0.3 and _mean_distance(full, truth, box) < 0.5


def test_the_last_level_runs_again_until_a_pass_moves_the_estimate_by_half_a_millimetre():
    """Started 13 mm (mean over the box) from the truth, one pass of four Gauss-Newton steps stops short (6.7 mm
    left when written); the registrar's last level runs again from its own result until a pass moves it by at most
    NATIVE_CONVERGED_MM and ends at the truth, recording the passes and the total move."""
    from monai_rigidreg.registration.last_level import NATIVE_CONVERGED_MM, NATIVE_MAX_PASSES
    from monai_rigidreg.registration.registrar import RigidRegistrar

    registrar = RigidRegistrar.from_bundle(device="cpu")
    iso = np.array([10.0, -20.0, 5.0])
    ct, cbct, truth = _pair([6.0, -3.0, 4.0, 4.0, -3.0, 5.0], iso)
    box = np.stack(np.meshgrid(*[np.linspace(-50, 50, 5)] * 3, indexing="ij"), -1).reshape(-1, 3) + iso
    grid = Grid.centered((64, 64, 64), (2.0,) * 3, iso)
    start = truth @ params_to_matrix([8.0, -6.0, 5.0, 6.0, -4.0, 5.0], iso)
    fov = cylindrical_fov_mask(cbct)
    one, one_detail = registrar._native(ct, cbct, start, fov, [], grid, converge=False)
    assert one_detail["passes"] == 1 and one_detail["last_pass_mm"] == one_detail["change_mm"]
    assert _mean_distance(one, truth, box) > 3.0
    refined, detail = registrar._native(ct, cbct, start, fov, [], grid)
    assert 1 < detail["passes"] <= NATIVE_MAX_PASSES
    assert detail["last_pass_mm"] <= NATIVE_CONVERGED_MM
    assert _mean_distance(refined, truth, box) < 0.2
    # the total move is from the start, not the last pass's
    assert detail["change_mm"] > _mean_distance(start, truth, box) - 2.0
    # at the truth one pass suffices
    _, stay = registrar._native(ct, cbct, truth, fov, [], grid)
    assert stay["passes"] == 1 and stay["last_pass_mm"] < NATIVE_CONVERGED_MM
    # each records whether it needed every pass it was allowed (flagged "unconverged", calibration.verdict), and how
    # precisely the images fix its result (registration.precision): finite, and far below a millimetre at the truth
    assert detail["exhausted"] == (detail["passes"] == NATIVE_MAX_PASSES) and not stay["exhausted"]
    assert not one_detail["exhausted"]  # one pass asked for (the learned network alone's probe): never exhausted
    assert 0.0 < stay["expected_tre_mm"] < 0.5 and stay["weighted_voxels"] > 1000


def test_a_last_level_that_needs_every_pass_says_so(monkeypatch):
    """Allowed two passes from 13 mm away, the last level uses both and records ``exhausted`` (which the verdict flags
    ``unconverged`` whatever the last pass moved: test_calibration.py)."""
    from monai_rigidreg.registration import last_level
    from monai_rigidreg.registration.registrar import RigidRegistrar

    monkeypatch.setattr(last_level, "NATIVE_MAX_PASSES", 2)
    registrar = RigidRegistrar.from_bundle(device="cpu")
    iso = np.array([10.0, -20.0, 5.0])
    ct, cbct, truth = _pair([6.0, -3.0, 4.0, 4.0, -3.0, 5.0], iso)
    grid = Grid.centered((64, 64, 64), (2.0,) * 3, iso)
    start = truth @ params_to_matrix([8.0, -6.0, 5.0, 6.0, -4.0, 5.0], iso)
    _, detail = registrar._native(ct, cbct, start, cylindrical_fov_mask(cbct), [], grid)
    assert detail["passes"] == 2 and detail["exhausted"] is True


def test_final_pass_on_the_normalised_contrast_removes_a_shading_pull(monkeypatch):
    """``native_final_norm_mm`` (off by default): once the last level has converged, one more pass on the local
    contrast normalised over that sigma (no intensity channel). On a CBCT whose contrast rises from 0.3 to 1.7 times
    across its field of view (scatter shading of a large body; 0.14 mm pulled off the truth when written) it ends
    within half that of the truth (0.04 mm); where it
    would move the converged estimate by more than FINAL_NORM_MAX_MM it is not kept; it does not run for the one-pass
    probe, nor by default; a sigma <= 0 is refused."""
    from monai_rigidreg.core.errors import InputError
    from monai_rigidreg.registration import last_level
    from monai_rigidreg.registration.registrar import RigidRegistrar

    iso = np.array([10.0, -20.0, 5.0])
    ct, cbct, truth = _pair([2.0, -1.0, 1.5, 1.0, -0.5, 1.0], iso, seed=5)
    arr = sitk.GetArrayFromImage(cbct)  # [z, y, x]
    x = np.linspace(-1.0, 1.0, arr.shape[2])[None, None, :]
    shaded = sitk.GetImageFromArray(((arr + 1000.0) * (1.0 + 0.7 * x) - 1000.0).astype(np.float32))
    shaded.CopyInformation(cbct)
    fov = cylindrical_fov_mask(cbct)
    grid = Grid.centered((64, 64, 64), (2.0,) * 3, iso)
    box = np.stack(np.meshgrid(*[np.linspace(-40, 40, 5)] * 3, indexing="ij"), -1).reshape(-1, 3) + iso
    default = RigidRegistrar.from_bundle(device="cpu")
    assert default.native_final_norm_mm is None
    plain, plain_detail = default._native(ct, shaded, truth, fov, [], grid)
    assert "final_pass" not in plain_detail
    normed = RigidRegistrar.from_bundle(device="cpu", native_final_norm_mm=12.0)
    final, detail = normed._native(ct, shaded, truth, fov, [], grid)
    assert detail["final_pass"]["kept"] and detail["final_pass"]["contrast_norm_sigma_mm"] == 12.0
    # the precision report (what the calibrated confidence reads) stays the default features'
    assert detail["expected_tre_mm"] == plain_detail["expected_tre_mm"]
    assert _mean_distance(plain, truth, box) > 0.1
    assert _mean_distance(final, truth, box) < 0.5 * _mean_distance(plain, truth, box)
    # the one-pass probe (the learned network alone) never takes it
    _, probe = normed._native(ct, shaded, truth, fov, [], grid, converge=False)
    assert "final_pass" not in probe
    # a move beyond the limit is another optimum, not a correction: the converged estimate stays
    monkeypatch.setattr(last_level, "FINAL_NORM_MAX_MM", 0.0)
    kept_out, out_detail = normed._native(ct, shaded, truth, fov, [], grid)
    assert not out_detail["final_pass"]["kept"] and out_detail["final_pass"]["move_mm"] > 0.0
    np.testing.assert_allclose(kept_out, plain, atol=1e-9)
    with pytest.raises(InputError, match="native_final_norm_mm"):
        RigidRegistrar.from_bundle(device="cpu", native_final_norm_mm=0.0)
