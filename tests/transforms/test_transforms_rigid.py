"""Tests of RandRigid6DoF / RandRigid6DoFd / Rigid6DoF (monai_rigidreg.transforms.rigid)."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch
from monai.data import DataLoader, Dataset, MetaTensor, list_data_collate
from monai.transforms import Compose

from monai_rigidreg.core.geometry import (
    Grid,
    compose_matrices,
    grid_points,
    params_to_matrix,
    params_to_sitk,
    rotation_matrix,
    target_registration_error,
    transform_points,
)
from monai_rigidreg.transforms import RandRigid6DoF, RandRigid6DoFd, Rigid6DoF, apply_rigid_motion

torch.set_num_threads(1)

# oblique, anisotropic grid with a non-zero origin (ITK terms)
OBLIQUE = Grid(
    (48, 32, 28), (1.0, 1.5, 2.0), (12.0, -30.0, 7.0), tuple(rotation_matrix(*np.deg2rad([10.0, -20.0, 30.0])).ravel())
)
MARKER_OFFSETS = np.array([[6.0, 6.0, 6.0], [6.0, -6.0, -6.0], [-6.0, 6.0, -6.0], [-6.0, -6.0, 6.0]])
SIGMA_MM = 2.0


def physical_points(grid: Grid) -> np.ndarray:
    idx = np.stack(np.meshgrid(*[np.arange(s) for s in grid.size], indexing="ij"), -1).reshape(-1, 3)
    return transform_points(grid.index_to_physical(), idx.astype(np.float64))


def blob_volume(grid: Grid, points: np.ndarray, dtype: torch.dtype = torch.float32, space: str = "RAS") -> MetaTensor:
    """MetaTensor [1, x, y, z] with Gaussian markers at physical ``points`` (background -1000, peaks +1000)."""
    phys = physical_points(grid)
    vol = np.zeros(len(phys))
    for p in np.atleast_2d(points):
        vol += np.exp(-np.sum((phys - p) ** 2, 1) / (2 * SIGMA_MM**2))
    vol = (-1000.0 + 2000.0 * vol).reshape(grid.size)
    meta = {"space": space} if space == "LPS" else {}
    return MetaTensor(torch.as_tensor(vol, dtype=dtype)[None], affine=torch.as_tensor(grid.affine(space)), meta=meta)


def smooth_volume(grid: Grid) -> MetaTensor:
    """MetaTensor [1, x, y, z] with a smooth texture (HU-like, +-500)."""
    phys = physical_points(grid) - grid.center()
    vol = 500.0 * np.sin(phys[:, 0] / 6.0) * np.cos(phys[:, 1] / 8.0) + 300.0 * np.sin(phys[:, 2] / 7.0 + 0.5)
    return MetaTensor(torch.as_tensor(vol.reshape(grid.size), dtype=torch.float32)[None], affine=grid.affine("RAS"))


def centroid(img: torch.Tensor, grid: Grid, near: np.ndarray, radius: float = 6.0) -> np.ndarray:
    """Intensity-weighted centroid (LPS mm) of the marker closest to ``near``."""
    phys = physical_points(grid)
    w = np.asarray(img[0].detach().cpu().double()).ravel() + 1000.0
    w = np.where(np.linalg.norm(phys - near, axis=1) < radius, np.clip(w, 0, None), 0.0)
    w = np.where(w > 0.1 * w.max(), w, 0.0)
    return (phys * w[:, None]).sum(0) / w.sum()


def to_sitk(img: torch.Tensor) -> sitk.Image:
    arr = np.asarray(img[0].detach().cpu().double())
    out = sitk.GetImageFromArray(arr.transpose(2, 1, 0))
    return Grid.from_metatensor(img).apply_to(out)


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares rigid 4x4 mapping src points to dst points (test-side estimator)."""
    cs, cd = src.mean(0), dst.mean(0)
    u, _, vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, cd - r @ cs
    return m


class TestRigidConvention:
    @pytest.mark.parametrize(("space", "seed"), [("RAS", 0), ("RAS", 1), ("LPS", 2), ("RAS", 3)])
    def test_marker_goes_to_euler3d_point(self, space, seed):
        """A marker at p appears at params_to_sitk(params, center).TransformPoint(p) (oblique, anisotropic)."""
        p = OBLIQUE.center() + np.array([3.0, -4.0, 5.0])
        img = blob_volume(OBLIQUE, p[None], space=space)
        t = RandRigid6DoF(translate_range=5.0, rotate_range=30.0)
        t.set_random_state(seed)
        out = t(img)
        assert np.any(np.abs(t.last_params) > 1.0)
        np.testing.assert_allclose(t.last_center, OBLIQUE.center(), atol=1e-9)
        expected = np.array(params_to_sitk(t.last_params, t.last_center).TransformPoint(tuple(p)))
        found = centroid(out, OBLIQUE, expected)
        assert np.linalg.norm(found - expected) < 0.5 * min(OBLIQUE.spacing)
        # the grid does not move
        torch.testing.assert_close(out.affine, img.affine)
        assert out.shape == img.shape

    def test_explicit_center_and_fixed_motion(self):
        p = OBLIQUE.center() + np.array([-2.0, 3.0, 1.0])
        c = OBLIQUE.center() + np.array([10.0, -5.0, 3.0])
        params = [2.0, -3.0, 1.5, 8.0, -6.0, 12.0]
        out = Rigid6DoF(params, center=c)(blob_volume(OBLIQUE, p[None]))
        expected = np.array(params_to_sitk(params, c).TransformPoint(tuple(p)))
        assert np.linalg.norm(centroid(out, OBLIQUE, expected) - expected) < 0.5

    def test_apply_rigid_motion_moves_a_marker_to_its_motion_point(self):
        """The functional form: a marker at p appears at M(p) (out(y) = img(M^-1(y))), not at M^-1(p)."""
        p = OBLIQUE.center() + np.array([4.0, -3.0, 2.0])
        m = params_to_matrix([3.0, -2.0, 4.0, 10.0, -8.0, 15.0], OBLIQUE.center() + np.array([5.0, 4.0, -3.0]))
        img = blob_volume(OBLIQUE, p[None]).as_tensor()
        out = apply_rigid_motion(img, m, OBLIQUE)
        expected, wrong = transform_points(m, p)[0], transform_points(np.linalg.inv(m), p)[0]
        found = centroid(out, OBLIQUE, expected)
        assert np.linalg.norm(found - expected) < 0.5 * min(OBLIQUE.spacing)
        assert np.linalg.norm(expected - wrong) > 8.0  # the two readings are far apart
        assert float(out.max()) > 500.0  # the marker is there, not padding
        assert out.shape == img.shape


class TestRigidRegistrationPair:
    def setup_method(self):
        self.points = OBLIQUE.center() + MARKER_OFFSETS
        self.fixed = blob_volume(OBLIQUE, self.points)

    def test_pair_registers_back_with_sitk(self):
        t = RandRigid6DoFd(keys="moving", translate_range=5.0, rotate_range=20.0, center_key="fixed")
        t.set_random_state(7)
        item = t({"fixed": self.fixed, "moving": self.fixed.clone()})
        rec = item["rigid_params"]
        params, center = rec["params"].double().numpy(), rec["center"].double().numpy()
        tfm = params_to_sitk(params, center)
        # markers in the moving image sit at T(p); a rigid fit of them is T (TRE < 0.5 voxel)
        found = np.stack([centroid(item["moving"], OBLIQUE, m) for m in transform_points(rec["matrix"], self.points)])
        tre = target_registration_error(kabsch(self.points, found), tfm, grid_points(OBLIQUE, step=3))
        assert tre < 0.5 * min(OBLIQUE.spacing)
        # sitk.Resample(moving, fixed, T) reproduces the fixed image
        back = sitk.Resample(to_sitk(item["moving"]), to_sitk(self.fixed), tfm, sitk.sitkLinear, -1000.0)
        back_t = torch.as_tensor(sitk.GetArrayFromImage(back).transpose(2, 1, 0))[None]
        for p in self.points:
            assert np.linalg.norm(centroid(back_t, OBLIQUE, p) - p) < 0.5 * min(OBLIQUE.spacing)
        err = (back_t - self.fixed.as_tensor().double()).abs()[0, 8:-8, 6:-6, 6:-6].mean()
        assert float(err) < 20.0  # HU, on a +-1000 HU marker image
        np.testing.assert_allclose(rec["matrix"].double().numpy(), params_to_matrix(params, center), atol=1e-4)

    def test_composition_with_prior_ground_truth(self):
        c = OBLIQUE.center()
        p0 = np.array([3.0, -2.0, 4.0, 5.0, -8.0, 10.0])
        t0 = params_to_matrix(p0, c)
        moving0 = Rigid6DoF(matrix=t0)(self.fixed)
        item = {"fixed": self.fixed, "moving": moving0, "params": p0.tolist(), "matrix": t0, "center": c.tolist()}
        t = RandRigid6DoFd(keys="moving", translate_range=4.0, rotate_range=15.0, center_key="fixed")
        t.set_random_state(3)
        out = t(item)
        rec = out["rigid_params"]
        total = compose_matrices(t.last_matrix, t0)  # M o T0: apply T0, then M
        np.testing.assert_allclose(rec["matrix"].double().numpy(), total, atol=1e-4)
        np.testing.assert_allclose(rec["center"].double().numpy(), c, atol=1e-4)
        np.testing.assert_allclose(params_to_matrix(rec["params"].double().numpy(), c), total, atol=1e-4)
        # simulator keys updated, same container types
        assert isinstance(out["params"], list)
        np.testing.assert_allclose(out["params"], rec["params"].double().numpy(), atol=1e-4)
        np.testing.assert_allclose(out["matrix"], total, atol=1e-9)
        # markers sit where the total transform says
        for p in self.points:
            expected = transform_points(total, p)[0]
            assert np.linalg.norm(centroid(out["moving"], OBLIQUE, expected) - expected) < 0.5
        # composing again through the output key (already in the dict) keeps accumulating
        again = t(out)
        total2 = compose_matrices(t.last_matrix, total)
        np.testing.assert_allclose(again["rigid_params"]["matrix"].double().numpy(), total2, atol=1e-4)


class TestRandRigid6DoF:
    def setup_method(self):
        self.img = blob_volume(Grid((24, 24, 24), (2.0, 2.0, 2.0), (-23.0, -23.0, -23.0)), np.array([[4.0, 2.0, -3.0]]))

    @pytest.mark.parametrize(
        "kwargs", [{"prob": 0.0}, {"axis_prob": 0.0}, {"translate_range": 0.0, "rotate_range": 0.0}]
    )
    def test_identity(self, kwargs):
        t = RandRigid6DoF(**kwargs)
        t.set_random_state(0)
        out = t(self.img)
        np.testing.assert_array_equal(t.last_params, np.zeros(6))
        torch.testing.assert_close(out.as_tensor(), self.img.as_tensor(), atol=1e-3, rtol=0)
        td = RandRigid6DoFd(keys="moving", **kwargs)
        d = td({"moving": self.img})
        torch.testing.assert_close(d["moving"].as_tensor(), self.img.as_tensor(), atol=1e-3, rtol=0)
        torch.testing.assert_close(d["rigid_params"]["matrix"], torch.eye(4))

    def test_reproducible_with_seed(self):
        outs = []
        for _ in range(2):
            t = RandRigid6DoF(translate_range=10.0, rotate_range=20.0)
            t.set_random_state(123)
            outs.append((t(self.img), t.last_params))
            outs.append((t(self.img), t.last_params))
        torch.testing.assert_close(outs[0][0], outs[2][0])
        np.testing.assert_array_equal(outs[1][1], outs[3][1])
        assert not np.allclose(outs[0][1], outs[1][1])
        pipe = [Compose([RandRigid6DoFd(keys="moving")]).set_random_state(5) for _ in range(2)]
        recs = [p({"moving": self.img})["rigid_params"]["params"] for p in pipe]
        torch.testing.assert_close(recs[0], recs[1])

    def test_ranges_step_and_axis_prob(self):
        t = RandRigid6DoF(translate_range=((-10.0, -5.0), 15.0, 0.0), rotate_range=30.0, step=(5.0, 5.0), axis_prob=0.5)
        t.set_random_state(0)
        draws = []
        for _ in range(200):
            t.randomize()
            draws.append(t._params.copy())
        draws = np.array(draws)
        np.testing.assert_allclose(draws / 5.0, np.round(draws / 5.0), atol=1e-9)  # a 5 mm / 5 degree grid
        assert np.all(draws[:, 0] <= 0) and np.all(draws[:, 0] >= -10) and np.all(draws[:, 2] == 0)
        assert np.all(np.abs(draws[:, 3:]) <= 30.0)
        n_active = (draws != 0).sum(1)
        assert np.any(n_active == 1) and np.any(n_active >= 3)  # single- and multi-axis perturbations
        with pytest.raises(ValueError):
            RandRigid6DoF(axis_prob=1.5)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.int16])
    def test_dtype_kept(self, dtype):
        img = self.img.to(dtype)
        t = RandRigid6DoF(
            translate_range=5.0, rotate_range=10.0, mode="nearest" if dtype == torch.int16 else "bilinear"
        )
        t.set_random_state(1)
        out = t(img)
        assert out.dtype == dtype
        assert isinstance(out, MetaTensor)
        assert float(out.min()) >= -1000.0  # padded with the image minimum, not 0

    def test_plain_tensor_and_numpy(self):
        t = RandRigid6DoF(translate_range=5.0, rotate_range=10.0)
        t.set_random_state(1)
        out = t(self.img.as_tensor().numpy())
        assert tuple(out.shape) == tuple(self.img.shape)

    @pytest.mark.parametrize("kind", ["array", "dict"])
    def test_inverse_round_trip(self, kind):
        img = smooth_volume(Grid((24, 24, 24), (2.0, 2.0, 2.0), (-23.0, -23.0, -23.0)))
        if kind == "array":
            t = RandRigid6DoF(translate_range=6.0, rotate_range=15.0)
            t.set_random_state(4)
            moved = t(img)
            back = t.inverse(moved)
        else:
            t = RandRigid6DoFd(keys="moving", translate_range=6.0, rotate_range=15.0)
            t.set_random_state(4)
            moved = t({"moving": img})["moving"]
            back = t.inverse({"moving": moved})["moving"]
        assert float((moved - img).abs()[0, 6:-6, 6:-6, 6:-6].mean()) > 100.0
        interior = (back - img).abs()[0, 6:-6, 6:-6, 6:-6].mean()
        assert float(interior) < 10.0  # HU: two trilinear interpolations of a +-800 HU texture
        assert len(back.applied_operations) == 0
        torch.testing.assert_close(back.affine, img.affine)

    def test_inverse_when_not_applied(self):
        t = RandRigid6DoF(prob=0.0)
        out = t(self.img)
        assert len(out.applied_operations) == 1
        back = t.inverse(out)
        torch.testing.assert_close(back.as_tensor(), self.img.as_tensor())

    def test_dict_several_keys_same_draw(self):
        mask = (self.img > 0).to(torch.uint8)
        t = RandRigid6DoFd(keys=("moving", "moving_copy"), mask_keys="moving_mask", translate_range=6.0)
        t.set_random_state(2)
        d = t({"moving": self.img, "moving_copy": self.img.clone(), "moving_mask": mask, "fixed": self.img})
        torch.testing.assert_close(d["moving"], d["moving_copy"])
        assert d["fixed"] is self.img
        assert d["moving_mask"].dtype == torch.uint8
        assert set(np.unique(d["moving_mask"].numpy())) == {0, 1}
        # the mask follows the same motion: it overlaps the moved marker
        inside = d["moving"][d["moving_mask"].bool()]
        assert float(inside.mean()) > 0.0
        assert float(((d["moving"] > 0).float() - d["moving_mask"].float()).abs().mean()) < 0.01

    def test_collate(self):
        t = RandRigid6DoFd(keys="moving")
        t.set_random_state(0)
        batch = list_data_collate([t({"moving": self.img}) for _ in range(3)])
        rec = batch["rigid_params"]
        assert tuple(rec["params"].shape) == (3, 6)
        assert tuple(rec["matrix"].shape) == (3, 4, 4)
        assert tuple(rec["center"].shape) == (3, 3)

    def test_distinct_across_dataloader_workers(self):
        small = MetaTensor(torch.zeros(1, 8, 8, 8), affine=torch.eye(4))
        ds = Dataset([{"moving": small} for _ in range(6)], transform=RandRigid6DoFd(keys="moving"))
        loader = DataLoader(ds, batch_size=1, num_workers=2)
        params = torch.cat([b["rigid_params"]["params"] for b in loader])
        assert len(torch.unique(params, dim=0)) == 6

    @pytest.mark.cuda
    @pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
    def test_cuda(self):
        img = self.img.to("cuda")
        t = RandRigid6DoFd(keys="moving")
        t.set_random_state(0)
        out = t({"moving": img})["moving"]
        assert out.device.type == "cuda"
        t_cpu = RandRigid6DoFd(keys="moving")
        t_cpu.set_random_state(0)
        ref = t_cpu({"moving": self.img})["moving"]
        torch.testing.assert_close(out.cpu().as_tensor(), ref.as_tensor(), atol=1e-2, rtol=0)
