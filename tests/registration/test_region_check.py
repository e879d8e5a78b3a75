"""The region check (block matching inside the match region after an estimate): the residual shift it reports is the
one left in the CT frame (a rotated estimate, a sub-voxel shift), flat blocks and blocks outside the CBCT's field of
view abstain, and the confidence score flags a region left beyond the limit."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from monai_rigidreg.core.geometry import params_to_matrix
from monai_rigidreg.registration.confidence import confidence_score
from monai_rigidreg.registration.region_check import MIN_BLOCKS, REGION_SHIFT_LIMIT_MM, block_shifts, region_bounds


@pytest.fixture(scope="module")
def ct() -> sitk.Image:
    """Smooth random structure (about 150 HU standard deviation), 64^3 at 2 mm centred on the origin."""
    rng = np.random.default_rng(0)
    img = sitk.GetImageFromArray(rng.normal(size=(64, 64, 64)).astype(np.float32))
    img.SetSpacing((2.0, 2.0, 2.0))
    img.SetOrigin((-63.0, -63.0, -63.0))
    return sitk.SmoothingRecursiveGaussian(img, 3.0) * 2000.0


def _moving(ct: sitk.Image, fixed_to_moving: np.ndarray) -> sitk.Image:
    """The CBCT of a CT whose point ``x`` appears at ``fixed_to_moving(x)``: ``CBCT(y) = CT(M^-1 y)``."""
    inv = np.linalg.inv(fixed_to_moving)
    tf = sitk.AffineTransform(3)
    tf.SetMatrix(inv[:3, :3].ravel().tolist())
    tf.SetTranslation(inv[:3, 3].tolist())
    return sitk.Resample(ct, ct, tf, sitk.sitkLinear, -1000.0)


def _box(ct: sitk.Image, lo: int = 12, hi: int = 52) -> sitk.Image:
    region = sitk.Image(ct.GetSize(), sitk.sitkUInt8)
    region.CopyInformation(ct)
    region[lo:hi, lo:hi, lo:hi] = 1
    return region


def _translation(d) -> np.ndarray:
    t = np.eye(4)
    t[:3, 3] = d
    return t


@pytest.mark.parametrize("d0", [(1.0, -2.5, 3.2), (1.0, 0.0, 0.0), (0.0, 0.0, 0.0)])
def test_block_shifts_report_the_shift_left_in_the_ct_frame(ct, d0):
    # a rotated estimate: the truth is estimate o translate(d0), so the shift to report is d0 itself (in the CT frame),
    # not its rotated image; (1, 0, 0) is half a voxel of the 2 mm sampling grid
    estimate = params_to_matrix([5.0, 3.0, -2.0, 15.0, -10.0, 60.0], (0.0, 0.0, 0.0))
    cbct = _moving(ct, estimate @ _translation(d0))
    blocks = block_shifts(ct, cbct, estimate, _box(ct))
    assert blocks.count == 27
    np.testing.assert_allclose(blocks.median_shift(), d0, atol=0.2)
    rotated = estimate[:3, :3] @ np.asarray(d0)
    if np.linalg.norm(d0) > 0:
        assert np.linalg.norm(blocks.median_shift() - rotated) > 0.5  # a frame mix-up would fail the check above
    # the blocks tile the region's box (CT LPS mm: voxels 12..51 at 2 mm from -63)
    lo, hi = region_bounds(_box(ct))
    np.testing.assert_allclose(lo, [-39.0] * 3)
    np.testing.assert_allclose(hi, [39.0] * 3)
    assert np.all(blocks.centers.min(0) > lo) and np.all(blocks.centers.max(0) < hi)


def test_flat_region_abstains(ct):
    flat = sitk.Image(ct.GetSize(), sitk.sitkFloat32) + 40.0
    flat.CopyInformation(ct)
    blocks = block_shifts(flat, _moving(flat, _translation((4.0, 0.0, 0.0))), np.eye(4), _box(ct))
    assert blocks.count == 0
    assert np.all(np.isnan(blocks.median_shift()))


def test_blocks_outside_the_field_of_view_do_not_vote(ct):
    cbct = _moving(ct, _translation((0.0, 2.0, 0.0)))
    fov = sitk.Image(ct.GetSize(), sitk.sitkUInt8)
    fov.CopyInformation(ct)
    fov[:, :, 32:] = 1  # the CBCT sees z >= 1 mm only
    blocks = block_shifts(ct, cbct, np.eye(4), _box(ct), moving_fov=fov)
    assert 0 < blocks.count < 27
    assert np.all(blocks.centers[blocks.used, 2] - 12.0 - 10.0 >= 0.0)  # block and search window inside
    # too few voting blocks: the check abstains
    assert np.all(np.isnan(blocks.median_shift(min_blocks=blocks.count + 1)))
    np.testing.assert_allclose(blocks.median_shift(min_blocks=1), [0.0, 2.0, 0.0], atol=0.2)


def test_confidence_flags_a_region_left_beyond_the_limit():
    ok = dict(local_gain=0.0, swap_tre_mm=0.5, tissue_on_air_share=0.0)
    assert confidence_score(**ok) > 0.9
    assert confidence_score(**ok, region_shift_mm=1.0) > 0.9
    assert confidence_score(**ok, region_shift_mm=REGION_SHIFT_LIMIT_MM - 0.5) > 0.8
    assert confidence_score(**ok, region_shift_mm=REGION_SHIFT_LIMIT_MM + 0.5) < 0.2
    assert confidence_score(**ok, region_shift_mm=float("nan")) == confidence_score(**ok)
    assert MIN_BLOCKS >= 3


@pytest.mark.parametrize("voxels, per_axis", [(12, 1), (15, 1), (20, 2), (24, 3), (36, 3)])
def test_blocks_on_a_small_box_stay_apart(ct, voxels, per_axis):
    # a box of `voxels` voxels per axis (2 mm): at most 3 blocks per axis, no closer than half a block (12 mm), so a
    # small box cannot count one structure several times towards MIN_BLOCKS
    lo = 32 - voxels // 2
    blocks = block_shifts(ct, _moving(ct, np.eye(4)), np.eye(4), _box(ct, lo, lo + voxels))
    assert len(blocks.centers) == per_axis**3
    for a in range(3):
        c = np.unique(np.round(blocks.centers[:, a], 6))
        assert len(c) == per_axis and (per_axis == 1 or np.diff(c).min() >= 12.0 - 2.0)  # snapped to the 2 mm grid
    if per_axis == 1:
        assert np.all(np.isnan(blocks.median_shift()))  # one block: the check abstains


def test_a_block_votes_only_when_half_of_it_is_in_the_region(ct):
    # an L-shaped region: the usual cube without its x > 1 mm, z > 1 mm quarter (same bounding box, same layout);
    # the blocks inside the missing quarter do not vote, those on the other side all do
    region = _box(ct)
    region[32:52, :, 32:52] = 0
    blocks = block_shifts(ct, _moving(ct, np.eye(4)), np.eye(4), region)
    assert len(blocks.centers) == 27
    x, z = blocks.centers[:, 0], blocks.centers[:, 2]
    assert not np.any(blocks.used & (x > 20.0) & (z > 20.0))
    assert np.all(blocks.used[x < -20.0])


def test_fov_mask_is_carried_through_the_estimate(ct):
    # the CBCT frame is the CT frame moved 30 mm along z: its field of view (CBCT frame) covers CBCT z >= 31 mm, i.e.
    # CT z >= 1 mm; a mask read in the CT frame would admit the lower blocks instead
    estimate = _translation((0.0, 0.0, 30.0))
    cbct_grid_img = sitk.Image(ct.GetSize(), sitk.sitkUInt8)
    cbct_grid_img.SetSpacing(ct.GetSpacing())
    cbct_grid_img.SetOrigin((-63.0, -63.0, -33.0))  # the CBCT's grid, shifted with it
    fov = cbct_grid_img
    fov[:, :, 32:] = 1  # CBCT z >= 31 mm
    cbct = sitk.Resample(ct, cbct_grid_img, sitk.TranslationTransform(3, (0.0, 0.0, -30.0)), sitk.sitkLinear, -1000.0)
    blocks = block_shifts(ct, cbct, estimate, _box(ct), moving_fov=fov)
    assert blocks.count > 0
    assert np.all(blocks.centers[blocks.used, 2] - 12.0 - 10.0 >= 0.0)
    np.testing.assert_allclose(blocks.median_shift(min_blocks=1), [0.0, 0.0, 0.0], atol=0.2)
