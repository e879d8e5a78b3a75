"""Global initialisation (large offsets) and the match region (ROI, bone): exact FFT correlation, recovered large
motions with the shipped network, and an ROI that decides which of two differently moving halves is matched."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch
from conftest import synth_ct

from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import (
    Grid,
    matrix_to_sitk,
    params_to_matrix,
    recenter_params,
    target_registration_error,
)
from monai_rigidreg.registration import RigidRegistrar
from monai_rigidreg.registration.confidence import cylindrical_fov_mask
from monai_rigidreg.registration.match_region import match_weight, parse_roi
from monai_rigidreg.registration.region_check import MIN_BLOCKS, block_shifts
from monai_rigidreg.registration.search import (
    DEFAULT_ROTATIONS_DEG,
    global_search,
    masked_ncc_map,
    masked_ncc_maps,
    matrix_distance_mm,
)

ISO = np.array([20.0, -10.0, 15.0])
"""The CBCT isocentre, mm from the CT centre (the origin)."""


@pytest.fixture(scope="module")
def ct() -> sitk.Image:
    """A synthetic-anatomy CT (HU), 96^3 at 3 mm (288 mm) centred on the origin."""
    return synth_ct(Grid.centered((96, 96, 96), (3.0, 3.0, 3.0)), 11)


def _cbct(ct: sitk.Image, matrix: np.ndarray, seed: int = 0) -> sitk.Image:
    """A CBCT-like image, 64^3 at 2 mm centred on the isocentre: ``CBCT(y) = CT(T^-1 y)`` plus noise and a smooth
    shading (the CBCT's contrast is not the CT's)."""
    grid = Grid.centered((64, 64, 64), (2.0, 2.0, 2.0), ISO)
    cb = sitk.Resample(ct, grid.to_sitk(), matrix_to_sitk(np.linalg.inv(matrix)), sitk.sitkLinear, -1000.0)
    arr = sitk.GetArrayFromImage(cb)
    rng = np.random.default_rng(seed)
    z = np.linspace(-1, 1, arr.shape[0])[:, None, None]
    arr = arr + 30.0 * rng.standard_normal(arr.shape) + 40.0 * z
    out = sitk.GetImageFromArray(arr.astype(np.float32))
    out.CopyInformation(cb)
    return out


def _two_halves(ct: sitk.Image, left: list[float], right: list[float], seed: int) -> sitk.Image:
    """A CBCT (as :func:`_cbct`) whose half x < ISO_x moved by ``left`` and half x >= ISO_x by ``right`` (params
    about the isocentre)."""
    cb_left = _cbct(ct, params_to_matrix(left, ISO), seed=seed)
    cb_right = _cbct(ct, params_to_matrix(right, ISO), seed=seed)
    arr = sitk.GetArrayFromImage(cb_left)
    x = np.arange(64) * 2.0 + cb_left.GetOrigin()[0]
    arr[:, :, x >= ISO[0]] = sitk.GetArrayViewFromImage(cb_right)[:, :, x >= ISO[0]]
    cbct = sitk.GetImageFromArray(arr)
    cbct.CopyInformation(cb_left)
    return cbct


def _brute_ncc(volume, template, mask, shift):
    x, y, z = template.shape
    win = volume[shift[0]:shift[0] + x, shift[1]:shift[1] + y, shift[2]:shift[2] + z]
    m = mask > 0
    a, b = win[m].double(), template[m].double()
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / torch.sqrt((a * a).sum() * (b * b).sum()))


def test_batched_ncc_maps_are_each_templates_own_map():
    # the global search's batch: every map as the template gets it alone, a template without mask is -1 everywhere
    g = torch.Generator().manual_seed(5)
    volume = torch.randn(20, 18, 16, generator=g)
    templates = torch.randn(3, 8, 7, 6, generator=g)
    masks = (torch.rand(3, 8, 7, 6, generator=g) > 0.3).float()
    masks[2] = 0.0
    masks[2, 0, 0, :5] = 1.0  # five voxels: fewer than 10
    templates[1] = volume[2:10, 5:12, 7:13]
    maps = masked_ncc_maps(volume, templates, masks)
    assert tuple(maps.shape) == (3, 13, 12, 11)
    for k in range(3):
        assert torch.equal(maps[k], masked_ncc_map(volume, templates[k], masks[k]))
    assert tuple(np.unravel_index(int(maps[1].argmax()), maps[1].shape)) == (2, 5, 7)
    assert bool((maps[2] == -1.0).all())


def test_masked_ncc_map_is_the_ncc_at_every_shift():
    g = torch.Generator().manual_seed(0)
    volume = torch.randn(20, 18, 16, generator=g)
    template = torch.randn(8, 7, 6, generator=g)
    mask = (torch.rand(8, 7, 6, generator=g) > 0.3).float()
    ncc = masked_ncc_map(volume, template, mask, min_overlap=0.0)
    assert tuple(ncc.shape) == (13, 12, 11)
    for shift in [(0, 0, 0), (12, 11, 10), (3, 7, 2), (5, 0, 9)]:
        assert float(ncc[shift]) == pytest.approx(_brute_ncc(volume, template, mask, shift), abs=1e-9)
    # the template cut out of the volume is found where it was cut, with NCC 1
    template = volume[4:12, 9:16, 3:9].clone()
    ncc = masked_ncc_map(volume, template, mask)
    assert tuple(np.unravel_index(int(ncc.argmax()), ncc.shape)) == (4, 9, 3)
    assert float(ncc.max()) == pytest.approx(1.0, abs=1e-9)


def test_global_search_finds_a_large_translation_and_the_rotation_basin(ct):
    grid_pts = Grid.centered((8, 8, 8), (12.0, 12.0, 12.0), ISO)
    pts = np.stack(np.meshgrid(*[np.arange(8.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pts = pts @ grid_pts.index_to_physical()[:3, :3].T + grid_pts.index_to_physical()[:3, 3]
    # a 60 mm table shift: the best candidate is the identity rotation, within half the 8 mm search step (the
    # learned network refines it); at 4 mm the same search is within 1 mm
    truth = params_to_matrix([40.0, -35.0, 27.0, 0.0, 0.0, 0.0], ISO)
    cbct = _cbct(ct, truth)
    cands = global_search(ct, cbct)
    assert cands[0].rotation_deg == (0.0, 0.0, 0.0)
    assert matrix_distance_mm(cands[0].matrix, truth, pts) < 4.0
    fine = global_search(ct, cbct, spacing_mm=4.0, rotations_deg=[(0.0, 0.0, 0.0)])
    assert matrix_distance_mm(fine[0].matrix, truth, pts) < 1.0
    assert [c.score for c in cands] == sorted((c.score for c in cands), reverse=True)
    # with a 40-degree rotation about y, the +25-degree candidate wins and leaves the network a 15-degree residual
    truth = params_to_matrix([-30.0, 25.0, 20.0, 0.0, 40.0, 0.0], ISO)
    cands = global_search(ct, _cbct(ct, truth, seed=1))
    assert cands[0].rotation_deg == (0.0, 25.0, 0.0)
    assert matrix_distance_mm(cands[0].matrix, truth, pts) < matrix_distance_mm(np.eye(4), truth, pts) / 2
    # a rotation about all three axes (30, -30, 30 degrees): the three-axis candidate of the same signs wins
    assert len(DEFAULT_ROTATIONS_DEG) == 27 and len(set(DEFAULT_ROTATIONS_DEG)) == 27
    truth = params_to_matrix([20.0, 15.0, -25.0, 30.0, -30.0, 30.0], ISO)
    cands = global_search(ct, _cbct(ct, truth, seed=3))
    assert cands[0].rotation_deg == (25.0, -25.0, 25.0)
    assert matrix_distance_mm(cands[0].matrix, truth, pts) < matrix_distance_mm(np.eye(4), truth, pts) / 3


@pytest.fixture(scope="module")
def registrar():
    return RigidRegistrar.from_bundle(device="cpu")


def _tre(result, truth_about_iso, pts):
    truth = recenter_params(truth_about_iso, ISO, result.center)
    return target_registration_error(result.params, truth, pts, center=result.center)


def _box_points(lo, hi, n=5):
    axes = [np.linspace(a, b, n) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def test_default_registration_recovers_60mm_40deg_and_90deg(ct, registrar):
    # 60 mm and 40 degrees about z: within the learned network's own capture range (trained to 60 mm / 45 degrees)
    truth = [38.0, -36.0, 28.0, 0.0, 0.0, 40.0]  # |t| = 60 mm about the isocentre
    pts = _box_points(ISO - 40, ISO + 40)
    res = registrar(ct, _cbct(ct, params_to_matrix(truth, ISO), seed=2), resample_moving=False, global_init=False)
    assert _tre(res, truth, pts) < 1.0 and not res.flagged
    # 90 degrees about z: beyond it (with the converging last level the identity's run recovers 80 degrees); the
    # default path's check fails and the global search's candidates recover it
    truth = [0.0, 0.0, 0.0, 0.0, 0.0, 90.0]
    cbct = _cbct(ct, params_to_matrix(truth, ISO), seed=2)
    without = registrar(ct, cbct, resample_moving=False, global_init=False)
    assert _tre(without, truth, pts) > 10.0 and without.flagged
    res = registrar(ct, cbct, resample_moving=False)  # the default: global initialisation on
    assert res.details["start"] == "search" and res.details["fallback"]["run"]
    assert res.details["global_search"]["best"]["rotation_deg"][2] == 25.0  # a candidate turned towards +z
    assert _tre(res, truth, pts) < 1.0
    assert not res.flagged
    assert "global_search" in res.timings


def test_the_network_starts_from_several_candidates_when_the_best_score_is_a_decoy(ct, registrar, monkeypatch):
    """``search_starts``: the search's top candidate can be a wrong basin (a near-symmetric head fools the coarse
    score); with one start the registration follows it, with two the network also starts from the second candidate
    and the better image match (the true basin) wins; details say which rank and list every start's match."""
    import monai_rigidreg.registration.search as reg_mod

    truth = [0.0, 0.0, 0.0, 0.0, 0.0, 90.0]  # beyond the network's own range: the search's candidates are needed
    cbct = _cbct(ct, params_to_matrix(truth, ISO), seed=2)
    pts = _box_points(ISO - 40, ISO + 40)
    real = reg_mod.global_search

    def decoy_first(*args, **kwargs):
        cands = real(*args, **kwargs)
        right = cands[0]  # the search's own best (the default registration recovers the truth from it)
        wrong = next(c for c in cands if c.rotation_deg == (25.0, 25.0, -25.0))
        return [wrong, right] + [c for c in cands if c is not right and c is not wrong]

    monkeypatch.setattr(reg_mod, "global_search", decoy_first)
    assert registrar.search_starts == 4  # the bundle's
    one = RigidRegistrar.from_bundle(device="cpu", search_starts=1)
    res1 = one(ct, cbct, resample_moving=False)
    assert _tre(res1, truth, pts) > 10.0 and len(res1.details["global_search"]["search_start_ncc"]) == 1
    two = RigidRegistrar.from_bundle(device="cpu", search_starts=2)
    res2 = two(ct, cbct, resample_moving=False)
    search = res2.details["global_search"]
    assert res2.details["start"] == "search" and search["start_rank"] == 1
    assert search["search_start_ncc"][1] > max(search["search_start_ncc"][0], search["identity_start_ncc"])
    assert _tre(res2, truth, pts) < 1.0 and not res2.flagged
    with pytest.raises(InputError, match="search_starts"):
        RigidRegistrar.from_bundle(device="cpu", search_starts=0)


def test_roi_decides_which_of_two_differently_moving_halves_is_matched(ct, registrar, monkeypatch):
    # the half x < ISO_x moved by one motion, the half x >= ISO_x by another (6 mm and 3 degrees apart)
    left, right = [4.0, -3.0, 2.0, 0.0, 0.0, 2.0], [-2.0, 3.0, -3.0, 2.0, 0.0, -1.0]
    cbct = _two_halves(ct, left, right, seed=3)
    # the ROI boxes stay 10 mm clear of the cut (the halves' CT regions differ by the motions, a few mm)
    box_left = (ISO[0] - 54, ISO[1] - 40, ISO[2] - 40, ISO[0] - 10, ISO[1] + 40, ISO[2] + 40)
    box_right = (ISO[0] + 10, ISO[1] - 40, ISO[2] - 40, ISO[0] + 54, ISO[1] + 40, ISO[2] + 40)
    # with the last level on, the region stays out of the pose search: the network runs and the image matches that
    # choose between starts (and the swapped twin) see the whole view; the last level gets the region
    import monai_rigidreg.registration.registrar as reg_mod

    seen: dict[str, list] = {"region": [], "run_weights": [], "match_regions": [], "native_region": []}
    real_weight, real_run, real_match, real_native = (reg_mod.match_weight, registrar._run_from,
                                                      registrar._image_match, registrar._native)

    def spy_weight(*a, **k):
        w = real_weight(*a, **k)
        seen["region"].append(w)
        return w

    def spy_run(fixed, moving, start, steps, weights, *a, **k):
        seen["run_weights"].append(list(weights))
        return real_run(fixed, moving, start, steps, weights, *a, **k)

    def spy_match(*a, region=None, **k):
        seen["match_regions"].append(a[4] if len(a) > 4 else region)
        return real_match(*a, region=region, **k) if len(a) <= 4 else real_match(*a, **k)

    def spy_native(*a, region=False, **k):
        seen["native_region"].append((region, a[4] if len(a) > 4 else k.get("weights")))
        return real_native(*a, region=region, **k)

    monkeypatch.setattr(reg_mod, "match_weight", spy_weight)
    monkeypatch.setattr(registrar, "_run_from", spy_run)
    monkeypatch.setattr(registrar, "_image_match", spy_match)
    monkeypatch.setattr(registrar, "_native", spy_native)
    res_l = registrar(ct, cbct, resample_moving=False, roi=box_left)
    monkeypatch.undo()
    region_img = seen["region"][0]
    assert region_img is not None and seen["run_weights"]
    assert all(all(w is not region_img for w in ws) for ws in seen["run_weights"])
    # the choice between starts sees the whole view; a swap check (if any) is scored inside the region, where the
    # final estimate was fitted
    assert res_l.details["global_search"]["search_start_ncc"] and "swap_check" in res_l.details  # both happen here
    assert seen["match_regions"][0] is None and seen["match_regions"][-1] is region_img
    assert seen["native_region"] and all(flag and any(w is region_img for w in ws)
                                         for flag, ws in seen["native_region"])
    res_r = registrar(ct, cbct, resample_moving=False, roi=box_right)
    pts_l, pts_r = _box_points(box_left[:3], box_left[3:]), _box_points(box_right[:3], box_right[3:])
    assert _tre(res_l, left, pts_l) < 0.75
    assert _tre(res_r, right, pts_r) < 0.75
    # each is matched to its own half, not to the other one
    assert _tre(res_l, right, pts_l) > 3.0
    assert _tre(res_r, left, pts_r) > 3.0
    assert res_l.details["match_region"] == {"roi": list(box_left), "match": "soft", "applied_to": "last level"}
    # the region check: the left box's structures sit where the CBCT shows them; the same estimate leaves the right
    # box's structures several mm off (what the check reports, and flags above 3 mm, for a region matched wrongly).
    # The 44 mm wide boxes reach the 128 mm CBCT's edge: only 3-4 blocks have their search window in view, fewer
    # than MIN_BLOCKS, so the registrar's own check abstains here (NaN) and the blocks are asked directly
    fov = cylindrical_fov_mask(cbct)
    for res, box in ((res_l, box_left), (res_r, box_right)):
        sig = res.details["signals"]
        assert 3 <= sig["region_blocks"] < MIN_BLOCKS and np.isnan(sig["region_shift_mm"]), sig
        mine = block_shifts(ct, cbct, res.matrix, match_weight(ct, box), fov)
        assert mine.count == sig["region_blocks"] and np.linalg.norm(mine.median_shift(min_blocks=3)) < 1.0
    other = block_shifts(ct, cbct, res_l.matrix, match_weight(ct, box_right), fov)
    assert other.count >= 3 and np.linalg.norm(other.median_shift(min_blocks=3)) > 3.0
    # with the last level off the region weights the network instead and still picks the half
    no_last = RigidRegistrar.from_bundle(device="cpu", native_level=False)
    res_n = no_last(ct, cbct, resample_moving=False, roi=box_left)
    assert res_n.details["match_region"]["applied_to"] == "network"
    assert _tre(res_n, left, pts_l) < 1.5 and _tre(res_n, right, pts_l) > 3.0


def test_region_check_uses_the_roi_box_also_with_a_bone_match(ct, registrar, monkeypatch):
    """With --roi and --match bone the last level is weighted by the bone inside the box, but the region check's blocks
    tile the box itself (the bone's own bounding box would shrink and thin them out); the check reports a small
    residual on a right registration."""
    import monai_rigidreg.registration.confidence as reg_mod
    from monai_rigidreg.registration.region_check import region_bounds

    motion = [6.0, -4.0, 3.0, 2.0, -3.0, 4.0]
    cbct = _cbct(ct, params_to_matrix(motion, ISO), seed=7)
    box = (ISO[0] - 35, ISO[1] - 35, ISO[2] - 35, ISO[0] + 35, ISO[1] + 35, ISO[2] + 35)
    seen = []
    real = reg_mod.block_shifts

    def spy(fixed, moving, matrix, region, *a, **k):
        seen.append(region)
        return real(fixed, moving, matrix, region, *a, **k)

    monkeypatch.setattr(reg_mod, "block_shifts", spy)
    res = registrar(ct, cbct, resample_moving=False, roi=box, match="bone")
    assert len(seen) == 1
    # copies (GetArrayFromImage): a view of a temporary image would outlive its memory
    region = sitk.GetArrayFromImage(seen[0]) > 0.5
    in_box = sitk.GetArrayFromImage(match_weight(ct, box)) > 0.5
    bone = sitk.GetArrayFromImage(match_weight(ct, box, "bone")) > 0.5
    assert np.array_equal(region, in_box) and bone.sum() < 0.9 * in_box.sum()  # the box, not the bone in it
    assert np.allclose(np.concatenate(region_bounds(seen[0])), np.concatenate(region_bounds(match_weight(ct, box))))
    assert _tre(res, motion, _box_points(box[:3], box[3:])) < 1.0
    sig = res.details["signals"]
    assert sig["region_blocks"] >= 1 and not sig.get("region_shift_mm", 0.0) > 1.0, sig


def test_image_match_scores_inside_the_match_region(ct):
    """fov_similarity with a region scores each estimate where the region lies: on a CBCT whose two halves moved
    differently, the left half's motion wins inside a left box and the right half's inside a right box (the rule
    that chooses between starts and the swapped-input estimate follows the user's ROI)."""
    from monai_rigidreg.registration.confidence import cylindrical_fov_mask
    from monai_rigidreg.registration.search import fov_similarity

    left, right = [8.0, -3.0, 2.0, 0.0, 0.0, 4.0], [-4.0, 3.0, -3.0, 3.0, 0.0, -2.0]
    cbct = _two_halves(ct, left, right, seed=5)
    fov = cylindrical_fov_mask(cbct)
    grid = Grid.centered((32, 32, 32), (4.0, 4.0, 4.0), ISO)
    matrices = [params_to_matrix(left, ISO), params_to_matrix(right, ISO)]
    box_left = (ISO[0] - 54, ISO[1] - 40, ISO[2] - 40, ISO[0] - 10, ISO[1] + 40, ISO[2] + 40)
    box_right = (ISO[0] + 10, ISO[1] - 40, ISO[2] - 40, ISO[0] + 54, ISO[1] + 40, ISO[2] + 40)
    hu = (-1000.0, 2000.0)
    s_left = fov_similarity(ct, cbct, fov, matrices, grid, hu, region=match_weight(ct, box_left, "soft"))
    s_right = fov_similarity(ct, cbct, fov, matrices, grid, hu, region=match_weight(ct, box_right, "soft"))
    assert s_left[0] > s_left[1] + 0.05, s_left
    assert s_right[1] > s_right[0] + 0.05, s_right
    whole = fov_similarity(ct, cbct, fov, matrices, grid, hu)
    assert all(w < max(s_left[0], s_right[1]) for w in whole), whole  # the whole view mixes both halves
    # the region rides into the CBCT frame through the estimate's inverse: a 20 mm slab of the CT 90 mm beside the
    # isocentre, under an estimate moving CT points +90 mm along x, lies in the grid's middle; the same slab under the
    # identity lies outside the 128 mm grid (fewer than 10 voxels: NaN)
    shift = params_to_matrix([90.0, 0.0, 0.0, 0.0, 0.0, 0.0], ISO)
    slab = match_weight(ct, (ISO[0] - 100, ISO[1] - 40, ISO[2] - 40, ISO[0] - 80, ISO[1] + 40, ISO[2] + 40), "soft")
    scored, outside = fov_similarity(ct, cbct, fov, [shift, np.eye(4)], grid, hu, region=slab)
    assert np.isfinite(scored) and np.isnan(outside)


def test_image_match_falls_back_to_the_whole_view_when_the_region_is_out_of_it(ct, registrar):
    """An ROI that the registrar's scoring grid does not see (NaN) is not allowed to decide: both estimates are then
    scored over the whole field of view (NaN would compare as neither better nor worse)."""
    from monai_rigidreg.registration.confidence import cylindrical_fov_mask
    from monai_rigidreg.registration.search import fov_similarity

    cbct = _two_halves(ct, [8.0, -3.0, 2.0, 0.0, 0.0, 4.0], [-4.0, 3.0, -3.0, 3.0, 0.0, -2.0], seed=5)
    fov = cylindrical_fov_mask(cbct)
    far = match_weight(ct, (ISO[0] - 140, ISO[1] - 40, ISO[2] - 40, ISO[0] - 110, ISO[1] + 40, ISO[2] + 40), "soft")
    matrices = [params_to_matrix([8.0, -3.0, 2.0, 0.0, 0.0, 4.0], ISO), np.eye(4)]
    ref_grid = registrar.grid_spec.pooled(2).centered(Grid.from_sitk(cbct).center())
    assert np.all(np.isnan(fov_similarity(ct, cbct, fov, matrices, ref_grid, registrar.hu_range, region=far)))
    scores = registrar._image_match(ct, cbct, fov, matrices, far)
    assert np.all(np.isfinite(scores))
    assert scores == pytest.approx(registrar._image_match(ct, cbct, fov, matrices))


def test_match_weight_box_on_an_oblique_ct_and_bone_mode(ct):
    # an oblique CT: the box is in physical LPS mm, whatever the direction cosines
    rot = params_to_matrix([0, 0, 0, 10.0, -20.0, 30.0])[:3, :3]
    img = sitk.Image(20, 24, 16, sitk.sitkFloat32)
    img.SetSpacing((2.0, 3.0, 4.0))
    img.SetOrigin((-15.0, 7.0, 3.0))
    img.SetDirection(tuple(rot.flatten()))
    img = img - 1000.0
    box = (-10.0, 0.0, 0.0, 20.0, 40.0, 30.0)
    w = match_weight(img, roi=box)
    arr = sitk.GetArrayViewFromImage(w)
    for idx in [(0, 0, 0), (5, 7, 3), (19, 23, 15), (10, 12, 8), (3, 20, 11)]:
        p = np.array(img.TransformIndexToPhysicalPoint(idx))
        inside = bool(np.all(p >= box[:3]) and np.all(p <= box[3:]))
        assert bool(arr[idx[2], idx[1], idx[0]] > 0) == inside
    assert 0 < arr.sum() < arr.size
    # bone match: only bone and its margin, and a region without bone is refused
    bone = match_weight(ct, match="bone")
    ct_arr, b_arr = sitk.GetArrayViewFromImage(ct), sitk.GetArrayViewFromImage(bone)
    assert np.all(b_arr[ct_arr > 250] > 0)
    assert 0 < b_arr.mean() < 0.6
    with pytest.raises(InputError, match="no CT voxel above"):
        match_weight(img, match="bone")
    assert match_weight(ct) is None


@pytest.mark.parametrize("bad", ["1,2,3", "a,b,c,d,e,f", [0, 0, 0, 10, 0, 10], [np.nan, 0, 0, 1, 1, 1]])
def test_parse_roi_refuses_bad_boxes(bad):
    with pytest.raises(InputError):
        parse_roi(bad)


def test_parse_roi_orders_corners_and_reads_strings():
    assert parse_roi("10,0,5,-10,20,-5") == (-10.0, 0.0, -5.0, 10.0, 20.0, 5.0)


def test_a_couch_that_did_not_move_is_excluded_by_default(registrar):
    """The patient moved between the scans, the couch (a rigid object of the room) did not: by default the match
    ignores it; kept (``keep_couch=True``) it pulls the estimate towards no motion."""
    from monai_rigidreg.simulation.couch import add_couch, place_couch

    ct = synth_ct(Grid.centered((80, 80, 80), (3.0, 3.0, 3.0)), 5, radius_mm=62.0)
    iso = np.array([0.0, 25.0, 0.0])  # the CBCT's 128 mm cube holds the patient's back and the couch
    truth = [5.0, -4.0, 3.0, 3.0, 0.0, 3.0]
    cb_grid = Grid.centered((64, 64, 64), (2.0, 2.0, 2.0), iso)
    moved = sitk.Resample(ct, cb_grid.to_sitk(), matrix_to_sitk(np.linalg.inv(params_to_matrix(truth, iso))),
                          sitk.sitkLinear, -1000.0)
    couch = place_couch(ct, gap_mm=8.0)
    ct_c, cb_c = add_couch(ct, couch), add_couch(moved, couch)  # the same physical place in both
    changed = np.abs(sitk.GetArrayViewFromImage(cb_c) - sitk.GetArrayViewFromImage(moved)) > 100
    assert changed.sum() > 2000  # the couch top is in the CBCT's cube
    pts = _box_points(iso - 40, iso + [40, 30, 40])
    truth_c = recenter_params(truth, iso, np.zeros(3))
    res = registrar(ct_c, cb_c, resample_moving=False)
    kept = registrar(ct_c, cb_c, resample_moving=False, keep_couch=True)
    tre = target_registration_error(res.params, truth_c, pts, center=res.center)
    tre_kept = target_registration_error(kept.params, truth_c, pts, center=kept.center)
    assert res.details["couch_excluded"] and not kept.details["couch_excluded"]
    assert tre < 0.75
    assert tre_kept > tre + 0.5
    # the same planning CT again (the next fraction): its body mask comes from the registrar's cache, and the
    # estimate is the same; a CT that differs in one voxel is a new CT
    assert res.details["body_mask"] in ("computed", "cached") and "body_mask" not in kept.details
    again = registrar(ct_c, cb_c, resample_moving=False)
    assert again.details["body_mask"] == "cached"
    np.testing.assert_allclose(again.params, res.params, atol=1e-9)
    other = sitk.Image(ct_c)
    other[0, 0, 0] = other[0, 0, 0] + 1.0
    assert registrar(other, cb_c, resample_moving=False).details["body_mask"] == "computed"
