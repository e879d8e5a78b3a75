"""Tests of RandCBCTDegradation / RandCBCTDegradationd (monai_rigidreg.transforms.cbct)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from monai.data import MetaTensor, list_data_collate

from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.transforms import CBCT_RECORD_KEYS, RandCBCTDegradation, RandCBCTDegradationd, RandRigid6DoFd

torch.set_num_threads(1)

EFFECTS = ("blur", "downsample", "scatter", "cupping", "streak", "ring", "noise", "hu", "fov")


def only(effect: str | None, **kwargs) -> RandCBCTDegradation:
    """A degradation with only ``effect`` switched on (probability 1)."""
    probs = {f"{e}_prob": 1.0 if e == effect else 0.0 for e in EFFECTS}
    probs.update(kwargs)
    return RandCBCTDegradation(**probs)


def water_phantom(size=(32, 32, 24), spacing=(2.0, 2.0, 2.5), radius=24.0, dtype=torch.float32) -> MetaTensor:
    """Water cylinder (0 HU, radius mm) about the volume z axis in air (-1000 HU), with a bone rod (1000 HU)."""
    grid = Grid(size, spacing, (10.0, -20.0, 5.0))
    u = (np.arange(size[0]) - (size[0] - 1) / 2) * spacing[0]
    v = (np.arange(size[1]) - (size[1] - 1) / 2) * spacing[1]
    r = np.sqrt(u[:, None] ** 2 + v[None, :] ** 2)
    sl = np.where(r < radius, 0.0, -1000.0)
    sl[(np.abs(u[:, None] - 10.0) < 4.0) & (np.abs(v[None, :]) < 4.0)] = 1000.0
    vol = np.repeat(sl[:, :, None], size[2], axis=2)
    return MetaTensor(torch.as_tensor(vol, dtype=dtype)[None], affine=torch.as_tensor(grid.affine("RAS")))


def radius_map(img: MetaTensor) -> np.ndarray:
    size, spacing = img.shape[1:], Grid.from_metatensor(img).spacing
    u = (np.arange(size[0]) - (size[0] - 1) / 2) * spacing[0]
    v = (np.arange(size[1]) - (size[1] - 1) / 2) * spacing[1]
    return np.sqrt(u[:, None] ** 2 + v[None, :] ** 2)


class TestCBCTDegradation:
    def setup_method(self):
        self.img = water_phantom()

    @pytest.mark.parametrize("kwargs", [{"prob": 0.0}, {f"{e}_prob": 0.0 for e in EFFECTS}])
    def test_identity(self, kwargs):
        t = RandCBCTDegradation(**kwargs)
        t.set_random_state(0)
        out = t(self.img)
        torch.testing.assert_close(out.as_tensor(), self.img.as_tensor())
        assert not any(t.last_record[e] for e in ("blur", "noise", "fov", "hu"))

    @pytest.mark.parametrize("level", [10.0, 40.0])
    def test_noise_level(self, level):
        t = only("noise", noise_std=level, noise_correlation=0.0, noise_floor=0.2)
        t.set_random_state(0)
        diff = (t(self.img) - self.img)[0].numpy()
        water = (radius_map(self.img) < 18.0) & (self.img[0, :, :, 0].numpy() == 0.0)
        air = radius_map(self.img) > 30.0
        sd_water = diff[water].std()
        assert abs(sd_water - level * np.sqrt(1.2)) < 0.1 * level
        assert diff[air].std() < sd_water  # variance follows intensity
        assert t.last_record["noise_std"] == level

    def test_noise_grows_with_level(self):
        sds = []
        for level in (5.0, 20.0, 60.0):
            t = only("noise", noise_std=level)
            t.set_random_state(1)
            sds.append(float((t(self.img) - self.img).std()))
        assert sds[0] < sds[1] < sds[2]

    def test_fov_truncation(self):
        t = only("fov", fov_radius=20.0, fov_edge=1.0, background=-1000.0)
        t.set_random_state(0)
        out = t(self.img)[0].numpy()
        r = radius_map(self.img)
        np.testing.assert_allclose(out[r > 28.0], -1000.0, atol=1.0)
        np.testing.assert_allclose(out[r < 12.0], self.img[0].numpy()[r < 12.0], atol=1.0)
        assert np.all(out[(r > 20.0) & (r < 24.0)] < -400.0)  # water beyond the FOV radius is gone

    def test_fov_truncation_with_anisotropic_in_plane_spacing(self):
        """The FOV cylinder is round in mm: x's coordinates come from x's spacing, y's from y's (1.5 mm and 3 mm
        voxels; x and y swapped, the cut would be an ellipse, 30 mm wide along x and 15 mm along y)."""
        img = water_phantom(size=(32, 32, 6), spacing=(1.5, 3.0, 2.5), radius=100.0)
        t = only("fov", fov_radius=20.0, fov_edge=0.5, background=-1000.0)
        t.set_random_state(0)
        out = t(img)[0].numpy()
        r = radius_map(img)
        assert r[:, 16].max() < 24.0 < 46.0 < r[16, :].max()  # half-widths: 23.3 mm along x, 46.5 mm along y
        np.testing.assert_allclose(out[r > 24.0], -1000.0, atol=1.0)
        np.testing.assert_allclose(out[r < 16.0], img[0].numpy()[r < 16.0], atol=1.0)
        assert np.all(out[r < 16.0] > -100.0)  # water and bone kept inside the radius

    def test_fov_half_length(self):
        t = only("fov", fov_radius=500.0, fov_edge=1.0, fov_half_length=10.0)
        out = t(self.img)[0].numpy()
        np.testing.assert_allclose(out[:, :, :3], -1000.0, atol=1.0)  # z far from the centre
        np.testing.assert_allclose(out[:, :, 11:13], self.img[0].numpy()[:, :, 11:13], atol=1.0)

    def test_fov_half_length_range_is_drawn_and_recorded(self):
        t = only("fov", fov_radius=500.0, fov_edge=1.0, fov_half_length=(14.0, 24.0))
        t.set_random_state(3)
        out = t(self.img)[0].numpy()
        h = t.last_record["fov_half_length"]
        assert 14.0 <= h <= 24.0
        cz = (np.arange(out.shape[2]) - (out.shape[2] - 1) / 2.0) * 2.5  # mm from the volume centre along z
        np.testing.assert_allclose(out[:, :, np.abs(cz) > h + 10.0], -1000.0, atol=1.0)
        inner = np.abs(cz) < h - 10.0
        np.testing.assert_allclose(out[:, :, inner], self.img[0].numpy()[:, :, inner], atol=1.0)
        assert only("fov", fov_radius=500.0).last_record["fov_half_length"] == 0.0  # no axial truncation

    def test_cupping_lowers_centre(self):
        img = water_phantom(radius=100.0)  # water everywhere in the slice
        t = only("cupping", cupping_depth=0.1)
        out = t(img)[0].numpy()
        r = radius_map(img)
        centre, edge = out[r < 6.0].mean(), out[(r > 26.0) & (r < 30.0)].mean()
        assert centre < edge - 30.0
        assert abs(centre - (-100.0)) < 15.0  # depth 0.1 of water at the axis
        air_img = water_phantom(radius=0.0)
        air = only("cupping", cupping_depth=0.1)(air_img)[0].numpy()
        np.testing.assert_allclose(air[air_img[0].numpy() == -1000.0], -1000.0, atol=1e-3)  # air stays air

    def test_scatter_smooth_shading(self):
        img = water_phantom(radius=100.0)
        t = only("scatter", scatter_amplitude=0.1)
        t.set_random_state(0)
        ratio = ((t(img) + 1000.0) / (img + 1000.0))[0].numpy()  # multiplicative field on the attenuation
        assert np.abs(ratio - 1.0).max() > 0.05 and np.abs(ratio - 1.0).max() <= 0.1 + 1e-5
        assert max(np.abs(np.diff(ratio, axis=a)).max() for a in range(3)) < 0.03  # low frequency

    def test_rings_about_z_axis(self):
        t = only("ring", ring_count=5, ring_amplitude=30.0)
        t.set_random_state(0)
        diff = (t(self.img) - self.img)[0].numpy()
        assert np.abs(diff).max() > 10.0
        np.testing.assert_allclose(diff, np.repeat(diff[:, :, :1], diff.shape[2], axis=2), atol=1e-3)
        # rotationally symmetric: the diff at (u, v) equals the diff at (-u, -v)
        np.testing.assert_allclose(diff[:, :, 0], diff[::-1, ::-1, 0], atol=1e-2)

    def test_streaks(self):
        t = only("streak", streak_count=3, streak_amplitude=60.0)
        t.set_random_state(0)
        diff = (t(self.img) - self.img)[0].numpy()
        assert np.abs(diff).max() > 30.0
        assert (np.abs(diff) > 5.0).mean() < 0.5  # thin lines, not a global change

    def test_hu_miscalibration(self):
        t = only("hu", hu_scale=1.1, hu_offset=20.0, hu_gamma=1.0)
        out = t(self.img)[0].numpy()
        src = self.img[0].numpy()
        np.testing.assert_allclose(out, 1.1 * src + 20.0, atol=1e-2)
        t = only("hu", hu_scale=1.0, hu_offset=0.0, hu_gamma=1.1)
        out = t(self.img)[0].numpy()
        np.testing.assert_allclose(out[src == 0.0], 0.0, atol=1e-3)  # water fixed
        assert np.all(out[src == 1000.0] > 1000.0)  # mild non-linearity on bone

    @pytest.mark.parametrize("sigma", [0.5, 2.0])
    def test_blur_and_downsample(self, sigma):
        rng = np.random.default_rng(0)
        img = MetaTensor(torch.as_tensor(rng.normal(0, 100, (1, 24, 24, 24)), dtype=torch.float32), affine=torch.eye(4))
        out = only("blur", blur_sigma=sigma)(img)
        assert float(out.std()) < 100.0 * (0.9 if sigma == 0.5 else 0.3)
        down = only("downsample", downsample_factor=2.0)(img)
        assert down.shape == img.shape and float(down.std()) < 60.0

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_geometry_and_dtype_kept(self, dtype):
        img = water_phantom(dtype=dtype)
        gt = {"params": torch.tensor([1.0, 2, 3, 4, 5, 6]), "matrix": torch.eye(4), "center": torch.zeros(3)}
        item = {"moving": img, "fixed": img.clone(), "rigid_params": gt, "params": [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]}
        t = RandCBCTDegradationd(keys="moving", streak_prob=1.0, ring_prob=1.0, fov_prob=1.0, downsample_prob=1.0)
        t.set_random_state(0)
        out = t(item)
        assert out["moving"].shape == img.shape and out["moving"].dtype == dtype
        torch.testing.assert_close(out["moving"].affine, img.affine)
        assert len(out["moving"].applied_operations) == len(img.applied_operations)
        assert out["rigid_params"] is gt and out["params"] == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
        torch.testing.assert_close(out["fixed"], img)
        assert float((out["moving"] - img).abs().mean()) > 5.0
        assert set(out["cbct_degradation"]) == set(CBCT_RECORD_KEYS)

    def test_seeded_reproducibility_and_record(self):
        outs, recs = [], []
        for _ in range(2):
            t = RandCBCTDegradationd(keys="moving", streak_prob=1.0, ring_prob=1.0, fov_prob=1.0)
            t.set_random_state(42)
            d = t({"moving": self.img})
            outs.append(d["moving"])
            recs.append(d["cbct_degradation"])
        torch.testing.assert_close(outs[0], outs[1])
        assert recs[0] == recs[1]
        # the record alone reproduces the output
        again = RandCBCTDegradation().apply(self.img, recs[0])
        torch.testing.assert_close(again, outs[0])
        d2 = t({"moving": self.img})
        assert d2["cbct_degradation"]["seed"] != recs[0]["seed"]

    def test_collate_record(self):
        t = RandCBCTDegradationd(keys="moving")
        t.set_random_state(0)
        batch = list_data_collate([t({"moving": self.img}) for _ in range(3)])
        rec = batch["cbct_degradation"]
        assert rec["noise_std"].shape == (3,) and rec["fov"].dtype == torch.bool

    def test_after_rigid_ground_truth_untouched(self):
        item = RandRigid6DoFd(keys="moving")({"moving": self.img, "fixed": self.img})
        before = {k: v.clone() for k, v in item["rigid_params"].items()}
        out = RandCBCTDegradationd(keys="moving")(item)
        for k, v in before.items():
            torch.testing.assert_close(out["rigid_params"][k], v)

    @pytest.mark.cuda
    @pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
    def test_cuda(self):
        t = RandCBCTDegradation(streak_prob=1.0, ring_prob=1.0, fov_prob=1.0, downsample_prob=1.0)
        t.set_random_state(0)
        out = t(self.img.to("cuda"))
        assert out.device.type == "cuda" and out.shape == self.img.shape
