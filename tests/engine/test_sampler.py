"""The on-the-fly training sampler: its ground truth aligns the images, its CT context sits where the network expects
it, its field of view never shows the source's own edge, and its stream is seeded."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch
from conftest import synth_ct

from monai_rigidreg.core.geometry import Grid, params_to_matrix, params_to_matrix_torch
from monai_rigidreg.core.warp import warp_volume
from monai_rigidreg.engine.sampler import MotionRange, RigidPairSampler, load_sources, sources_from_cts
from monai_rigidreg.networks.context_net import context_from_fixed

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SIZE, SPACING = (32, 32, 32), (4.0, 4.0, 4.0)


@pytest.fixture(scope="module")
def ct_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("sampler") / "ct.nii.gz"
    grid = Grid.centered((64, 64, 48), (3.0, 3.0, 3.0), (10.0, -20.0, 5.0))
    sitk.WriteImage(synth_ct(grid, seed=3, radius_mm=85.0), str(path))
    return path


@pytest.fixture(scope="module")
def ct_sources(ct_file):
    return sources_from_cts([ct_file], network_spacing=SPACING[0], context_spacing=2 * SPACING[0],
                            isocenter_max=40.0)


def _sampler(sources, cls=RigidPairSampler, **kw):
    base = {"network_size": SIZE, "network_spacing": SPACING, "degradation": {"prob": 0.0}, "fov_prob": 0.0,
            "static_couch_prob": 0.0, "moving_couch_removed_prob": 0.0, "fixed_couch_removed_prob": 0.0}
    return cls(sources, **{**base, **kw})


def _ncc(a: torch.Tensor, b: torch.Tensor, m: torch.Tensor) -> float:
    a, b = a[m] - a[m].mean(), b[m] - b[m].mean()
    return float((a * b).sum() / (a.norm() * b.norm() + 1e-9))


@pytest.mark.parametrize(("anatomy_prob", "orientation_prob"), [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)])
def test_ground_truth_aligns_moving_with_fixed(ct_sources, anatomy_prob, orientation_prob):
    """Warping the CBCT by the recorded parameters (fixed -> moving about the grid centre) puts it on the CT; the
    same parameters with the rotation's sign flipped, or with tx and ty swapped, do not. Also where both images show
    the CT stretched by another factor per axis, turned about the isocentre, or both (the truth stays the rigid
    motion between them)."""
    sampler = _sampler(ct_sources, motions=(MotionRange(20.0, 20.0, min_translation=10.0),),
                       anatomy_prob=anatomy_prob, anatomy_scale=(0.8, 1.25), orientation_prob=orientation_prob,
                       orientation_max=30.0)
    rng = np.random.default_rng(0)
    canon = Grid.centered(SIZE, SPACING)
    checked = 0
    for _ in range(12):
        if checked == 3:
            break
        d = sampler.draw(rng)
        p = d["rigid_params"]["params"][None].double()
        if float(p[0, 3:].abs().max()) <= 5.0 or abs(float(p[0, 0] - p[0, 1])) <= 3.0:
            continue  # a draw the checks below cannot tell from its flipped or swapped twin
        checked += 1

        def warped(params, moving=d["moving"]):
            return warp_volume(moving[None], params_to_matrix_torch(params).float(), canon, canon)[0]

        inside = warp_volume(d["moving_fov"][None], params_to_matrix_torch(p).float(), canon, canon)[0] > 0.99
        mask = inside & (d["fixed"] > 0.05)
        right = _ncc(warped(p), d["fixed"], mask)
        flipped = _ncc(warped(p * torch.tensor([[1, 1, 1, -1, -1, -1.0]])), d["fixed"], mask)
        swapped = _ncc(warped(p[:, [1, 0, 2, 3, 4, 5]]), d["fixed"], mask)
        assert right > 0.97
        assert right - max(flipped, swapped) > 0.05
        # the matrix and centre recorded beside the parameters are the same transform
        m = np.asarray(d["rigid_params"]["matrix"])
        assert np.allclose(params_to_matrix(p[0].numpy(), d["rigid_params"]["center"].numpy()), m, atol=1e-4)
    assert checked == 3


def test_context_is_the_ct_on_the_context_grid_of_the_same_centre(ct_sources):
    """Inside the network grid's extent, the context equals the network grid's CT pooled by two (what the network
    falls back to without a context): same centre, twice the spacing."""
    d = _sampler(ct_sources).draw(np.random.default_rng(1))
    pooled = context_from_fixed(d["fixed"][None], 2)[0]
    inner = torch.zeros_like(pooled, dtype=torch.bool)
    inner[:, 9:23, 9:23, 9:23] = True  # away from the border, where the pooled grid is padded
    assert float((pooled - d["context"])[inner].abs().mean()) < 0.01
    shifted = torch.roll(d["context"], 1, dims=1)
    assert float((pooled - shifted)[inner].abs().mean()) > 0.01  # a one-voxel shift is seen


def test_field_of_view_stays_inside_what_the_source_covers(ct_sources):
    """Large motions take part of the grid outside the CT: the field of view (a cylinder about the grid's z axis)
    never reaches there, so no edge of the source moves with the motion."""
    sampler = _sampler(ct_sources, fov_prob=1.0, fov_radius=(200.0, 250.0), fov_half_length=(200.0, 250.0),
                       motions=(MotionRange(60.0, 45.0, min_translation=50.0),))
    rng = np.random.default_rng(2)
    cut = 0
    for _ in range(4):
        d = sampler.draw(rng)
        fov = d["moving_fov"][0] > 0.5
        cut += int((~fov).sum())
        # where the moved CT does not reach, the moving image is padding (air): no such voxel may be in view
        m = d["rigid_params"]["matrix"].numpy()
        grid = Grid.centered(SIZE, SPACING, d["rigid_params"]["center"].numpy())
        src = ct_sources[0].fixed
        ones = torch.ones_like(src.data)
        reach = warp_volume(ones, torch.as_tensor(np.linalg.inv(m))[None].float(), grid, src.grid)[0, 0]
        assert bool((reach[fov] > 0.5).all())
        # a cylinder about z: every axial slice's field of view is a disc (or empty)
        x = (torch.arange(SIZE[0]) - (SIZE[0] - 1) / 2) * SPACING[0]
        r = (x[:, None] ** 2 + x[None, :] ** 2).sqrt()
        for k in range(SIZE[2]):
            sl = fov[:, :, k]
            if sl.any() and not sl.all():
                assert bool(r[sl].max() < r[~sl].min() + 1e-6)
    assert cut > 0  # the motions did take part of the grid outside the CT


def test_stream_is_seeded_per_epoch(ct_sources):
    a = _sampler(ct_sources, seed=5)
    b = _sampler(ct_sources, seed=5)
    first = next(iter(a))["rigid_params"]["params"]
    assert torch.equal(first, next(iter(b))["rigid_params"]["params"])
    b.set_epoch(1)
    assert not torch.equal(first, next(iter(b))["rigid_params"]["params"])


def test_anatomy_stretch_grows_the_body_about_the_isocentre(ct_sources):
    """``anatomy_scale`` (1.25, 1.25): the sample's CT is the source's CT magnified 1.25 times about the isocentre
    (the grid centre): the unstretched sample, magnified by warping, matches it; the unmagnified one and one shrunk
    instead do not. Same stream position for both samplers (a drawn stretch consumes the same numbers)."""
    common = {"motions": (MotionRange(5.0, 5.0),), "anatomy_prob": 1.0}
    big = _sampler(ct_sources, anatomy_scale=(1.25, 1.25), **common).draw(np.random.default_rng(7))
    same = _sampler(ct_sources, anatomy_scale=(1.0, 1.0), **common).draw(np.random.default_rng(7))
    assert torch.equal(big["rigid_params"]["params"], same["rigid_params"]["params"])
    canon = Grid.centered(SIZE, SPACING)

    def zoomed(factor):
        m = torch.eye(4, dtype=torch.float64)
        m[:3, :3] /= factor  # output point x shows the input at x / factor
        return warp_volume(same["fixed"][None], m[None].float(), canon, canon)[0]

    mask = torch.ones_like(big["fixed"], dtype=torch.bool)
    err = {f: float((zoomed(f) - big["fixed"]).abs().mean()) for f in (1.25, 1.0, 0.8)}
    assert err[1.25] < 0.3 * min(err[1.0], err[0.8]), err
    assert _ncc(zoomed(1.25), big["fixed"], mask) > 0.98


def test_anatomy_stretch_moves_the_body_masks_with_the_body(ct_sources):
    """With the couch removed from both images (everything outside the body mask set to air), a stretched body keeps
    all its tissue: the masks are stretched as the images are (else the body's edge, 1.25 times further out, would be
    cut to air); and the fixed image's mask is its own, not the moving image's."""
    common = {"motions": (MotionRange(15.0, 15.0, min_translation=5.0),), "anatomy_prob": 1.0,
              "anatomy_scale": (1.25, 1.25)}
    kept = _sampler(ct_sources, **common).draw(np.random.default_rng(11))
    cut = _sampler(ct_sources, fixed_couch_removed_prob=1.0, moving_couch_removed_prob=1.0,
                   **common).draw(np.random.default_rng(11))
    assert torch.equal(kept["rigid_params"]["params"], cut["rigid_params"]["params"])
    tissue_hu = (-300.0 + 1000.0) / 3000.0  # normalized
    for key in ("fixed", "moving"):
        tissue = kept[key] > tissue_hu
        assert int(tissue.sum()) > 1000
        lost = float((cut[key][tissue] < tissue_hu).float().mean())
        assert lost < 0.005, (key, lost)


class _OrientationSpy(RigidPairSampler):
    """Keeps the anatomy's rotation of the last draw (4x4 about the isocentre, LPS mm)."""

    def _orientation(self, rng, center):
        self.turn = super()._orientation(rng, center)
        self.turn_center = np.asarray(center, dtype=np.float64)
        return self.turn


@pytest.mark.parametrize("anatomy_prob", [0.0, 1.0])
def test_orientation_turns_both_images_about_the_isocentre(ct_sources, anatomy_prob):
    """``orientation_prob`` 1: the sample's CT is the unturned sample's CT turned about the isocentre (the grid centre)
    by the drawn rotation: warping the unturned one by that rotation gives it, by the inverse rotation or about
    another centre it does not. ``orientation_max`` 0 draws the same numbers with no turn, so both samples share the
    motion (and the stretch: with one drawn per axis, the turned sample is the stretched body turned, not the turned
    body stretched along the grid's axes)."""
    common = {"motions": (MotionRange(10.0, 10.0),), "orientation_prob": 1.0, "anatomy_prob": anatomy_prob,
              "anatomy_scale": (0.75, 1.3)}
    turned = _sampler(ct_sources, _OrientationSpy, orientation_max=30.0, **common)
    plain = _sampler(ct_sources, _OrientationSpy, orientation_max=0.0, **common)
    a, b = turned.draw(np.random.default_rng(5), tries=1), plain.draw(np.random.default_rng(5), tries=1)
    assert torch.equal(a["rigid_params"]["params"], b["rigid_params"]["params"])
    assert np.allclose(plain.turn, np.eye(4))
    angles = np.degrees(np.arccos(np.clip((np.trace(turned.turn[:3, :3]) - 1) / 2, -1, 1)))
    assert angles > 10.0  # a turn the checks can see
    assert np.allclose(turned.turn[:3, :3] @ turned.turn_center + turned.turn[:3, 3], turned.turn_center)
    canon = Grid.centered(SIZE, SPACING)
    about_origin = np.eye(4)
    about_origin[:3, :3] = turned.turn[:3, :3]  # the grid centre is the canonical grid's origin

    def warped(m):
        return warp_volume(b["fixed"][None], torch.as_tensor(m)[None].float(), canon, canon)[0]

    mask = warped(about_origin) > 0.05
    right = _ncc(warped(about_origin), a["fixed"], mask)
    inverse = _ncc(warped(np.linalg.inv(about_origin)), a["fixed"], mask)
    shifted = about_origin.copy()
    shifted[:3, 3] = (np.eye(3) - shifted[:3, :3]) @ np.array([60.0, 0.0, 0.0])  # the same turn about another point
    elsewhere = _ncc(warped(shifted), a["fixed"], mask)
    assert right > 0.97
    assert right - max(inverse, elsewhere) > 0.05, (right, inverse, elsewhere)


class _NoTurn(RigidPairSampler):
    """The sampler as it was before the option: no turn, nothing drawn for it."""

    def _orientation(self, rng, center):
        return np.eye(4)


def test_orientation_off_leaves_the_stream_as_it_was(ct_sources):
    """``orientation_prob`` 0 (the default) draws nothing for it: a run resumed with the option off sees the samples
    it saw before the option existed (a sampler without the option), whatever ``orientation_max``, and its generator
    is left where that one leaves it; a probability above 0 draws (the check can tell)."""
    common = {"network_size": SIZE, "network_spacing": SPACING, "degradation": {"prob": 0.0}, "fov_prob": 0.0,
              "motions": (MotionRange(20.0, 20.0),), "anatomy_prob": 0.5}
    old_rng, rng, drawing_rng = (np.random.default_rng(3) for _ in range(3))
    old = _NoTurn(ct_sources, **common).draw(old_rng)
    off = RigidPairSampler(ct_sources, orientation_prob=0.0, orientation_max=40.0, **common).draw(rng)
    for key in ("moving", "fixed", "context", "moving_fov"):
        assert torch.equal(old[key], off[key])
    assert old_rng.random() == rng.random()
    RigidPairSampler(ct_sources, orientation_prob=1e-12, **common).draw(drawing_rng)
    assert drawing_rng.random() != np.random.default_rng(3).random()  # not at the start any more
    old_rng2, drawing_rng2 = np.random.default_rng(3), np.random.default_rng(3)
    _NoTurn(ct_sources, **common).draw(old_rng2)
    RigidPairSampler(ct_sources, orientation_prob=1e-12, **common).draw(drawing_rng2)
    assert old_rng2.random() != drawing_rng2.random()


@pytest.mark.parametrize("kw", [{"orientation_prob": 1.5}, {"orientation_prob": -0.1}, {"orientation_max": -5.0},
                                {"orientation_max": 200.0}])
def test_orientation_options_are_checked(ct_sources, kw):
    with pytest.raises(ValueError, match="orientation"):
        _sampler(ct_sources, **kw)


def test_anatomy_scale_is_checked(ct_sources):
    with pytest.raises(ValueError, match="anatomy_scale"):
        _sampler(ct_sources, anatomy_scale=(1.2, 0.9))


@pytest.mark.parametrize("anatomy_prob", [0.0, 1.0])
def test_sources_from_a_simulated_datalist(tiny_dataset, anatomy_prob):
    """``cbct`` sources from ``monai-rigidreg simulate``: the sample's truth composes the extra motion with the
    recorded one, and the samples align (also with the anatomy stretched in both images)."""
    sources = load_sources(datalists=[tiny_dataset], network_spacing=SPACING[0], context_spacing=8.0,
                           isocenter_max=20.0)
    assert sources and all(s.kind == "cbct" and s.moving is not None for s in sources)
    sampler = _sampler(sources, motions=(MotionRange(5.0, 5.0),), cbct_degradation={"prob": 0.0},
                       anatomy_prob=anatomy_prob, anatomy_scale=(0.8, 1.25))
    d = sampler.draw(np.random.default_rng(3))
    canon = Grid.centered(SIZE, SPACING)
    p = d["rigid_params"]["params"][None].double()
    w = warp_volume(d["moving"][None], params_to_matrix_torch(p).float(), canon, canon)[0]
    inside = warp_volume(d["moving_fov"][None], params_to_matrix_torch(p).float(), canon, canon)[0] > 0.99
    mask = inside & (d["fixed"] > 0.05)
    identity = _ncc(d["moving"], d["fixed"], mask)
    assert _ncc(w, d["fixed"], mask) > max(0.8, identity + 0.05)
