"""Tests of the network-grid preprocessing (monai_rigidreg.transforms.grid)."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch
from monai.data import MetaTensor
from monai.transforms import GaussianSmooth

from monai_rigidreg.core.geometry import Grid, rotation_matrix, transform_points
from monai_rigidreg.core.image_ops import gaussian_smooth
from monai_rigidreg.transforms import (
    NormalizeHU,
    NormalizeHUd,
    RandRigid6DoFd,
    ResampleToNetworkGrid,
    ResampleToNetworkGridd,
    network_grid,
)

torch.set_num_threads(1)

OBLIQUE = Grid(
    (30, 24, 20), (1.0, 1.5, 2.0), (12.0, -30.0, 7.0), tuple(rotation_matrix(*np.deg2rad([15.0, -10.0, 35.0])).ravel())
)


def physical_points(grid: Grid) -> np.ndarray:
    idx = np.stack(np.meshgrid(*[np.arange(s) for s in grid.size], indexing="ij"), -1).reshape(-1, 3)
    return transform_points(grid.index_to_physical(), idx.astype(np.float64))


def marker_volume(grid: Grid, p: np.ndarray, space: str = "RAS", sigma: float = 2.5) -> MetaTensor:
    phys = physical_points(grid)
    vol = -1000.0 + 2000.0 * np.exp(-np.sum((phys - p) ** 2, 1) / (2 * sigma**2))
    meta = {"space": space} if space == "LPS" else {}
    return MetaTensor(
        torch.as_tensor(vol.reshape(grid.size), dtype=torch.float32)[None],
        affine=torch.as_tensor(grid.affine(space)),
        meta=meta,
    )


def centroid(img: MetaTensor) -> np.ndarray:
    grid = Grid.from_metatensor(img)
    w = np.asarray(img[0].double()).ravel() + 1000.0
    w = np.where(w > 0.1 * w.max(), w, 0.0)
    return (physical_points(grid) * w[:, None]).sum(0) / w.sum()


class TestNetworkGrid:
    @pytest.mark.parametrize(
        ("space", "size", "spacing"), [("RAS", 16, 2.0), ("LPS", (20, 16, 18), (1.5, 2.0, 2.5)), ("RAS", 24, 1.0)]
    )
    def test_marker_lands_at_same_physical_point(self, space, size, spacing):
        p = OBLIQUE.center() + np.array([3.0, -2.0, 4.0])
        img = marker_volume(OBLIQUE, p, space=space)
        out = ResampleToNetworkGrid(size=size, spacing=spacing)(img)
        grid = Grid.from_metatensor(out)
        expected_grid = network_grid(OBLIQUE, size, spacing)
        assert grid.size == expected_grid.size
        np.testing.assert_allclose(grid.index_to_physical(), expected_grid.index_to_physical(), atol=1e-6)
        np.testing.assert_allclose(grid.direction_matrix, np.eye(3), atol=1e-9)  # axis-aligned
        np.testing.assert_allclose(grid.center(), OBLIQUE.center(), atol=1e-6)
        if space == "LPS":
            assert out.meta["space"] == "LPS"
        assert np.linalg.norm(centroid(out) - p) < 0.5 * min(grid.spacing)
        assert out.dtype == img.dtype

    def test_dict_one_grid_centred_on_fixed(self):
        fixed = marker_volume(OBLIQUE, OBLIQUE.center())
        other = Grid((20, 20, 20), (3.0, 3.0, 3.0), (-120.0, -10.0, 0.0))
        q = other.center() + np.array([2.0, 3.0, -1.0])
        moving = marker_volume(other, q)
        t = ResampleToNetworkGridd(keys=("moving", "fixed"), size=24, spacing=2.5, ref_key="fixed", grid_key="grid")
        d = t({"moving": moving, "fixed": fixed})
        gm, gf = Grid.from_metatensor(d["moving"]), Grid.from_metatensor(d["fixed"])
        assert gm == gf or np.allclose(gm.index_to_physical(), gf.index_to_physical())
        np.testing.assert_allclose(gf.center(), OBLIQUE.center(), atol=1e-6)
        np.testing.assert_allclose(d["grid"].numpy(), gf.affine("RAS"), atol=1e-9)
        # the moving marker, far from the fixed centre, is outside: padding value everywhere
        assert float(d["moving"].max()) == pytest.approx(-1000.0, abs=1e-3)
        # with an explicit centre at the moving marker, it lands there
        t2 = ResampleToNetworkGridd(keys=("moving",), size=40, spacing=2.0, center=q, padding_value=-1024.0)
        out = t2({"moving": moving})["moving"]
        assert np.linalg.norm(centroid(out) - q) < 1.0
        assert float(out.min()) == pytest.approx(-1024.0, abs=1e-3)  # padding outside the moving image

    def test_network_grid_helper_inputs(self):
        img = marker_volume(OBLIQUE, OBLIQUE.center())
        sitk_img = OBLIQUE.to_sitk()
        g1, g2, g3 = (network_grid(x, 32, 3.0) for x in (OBLIQUE, img, sitk_img))
        assert g1.size == (32, 32, 32) and g1.spacing == (3.0, 3.0, 3.0)
        for g in (g2, g3):
            np.testing.assert_allclose(g.origin, g1.origin, atol=1e-6)
        np.testing.assert_allclose(network_grid(OBLIQUE, 8, 1.0, center=(1.0, 2.0, 3.0)).center(), [1, 2, 3])
        assert isinstance(sitk_img, sitk.Image)

    def test_inverse_round_trip(self):
        grid = Grid((24, 24, 24), (2.0, 2.0, 2.0), (-23.0, -23.0, -23.0))
        phys = physical_points(grid)
        vol = 400.0 * np.sin(phys[:, 0] / 8.0) * np.cos(phys[:, 1] / 9.0)
        img = MetaTensor(torch.as_tensor(vol.reshape(grid.size), dtype=torch.float32)[None], affine=grid.affine("RAS"))
        t = ResampleToNetworkGridd(keys="image", ref_key="image", size=40, spacing=1.5)
        out = t({"image": img})
        assert out["image"].shape == (1, 40, 40, 40)
        back = t.inverse(out)["image"]
        assert back.shape == img.shape
        torch.testing.assert_close(back.affine, img.affine)
        assert float((back - img).abs()[0, 4:-4, 4:-4, 4:-4].mean()) < 5.0

    def test_after_rigid_pair_ground_truth_still_valid(self):
        """Resampling both images onto the network grid does not change the physical ground truth."""
        p = OBLIQUE.center() + np.array([2.0, 1.0, -2.0])
        fixed = marker_volume(OBLIQUE, p)
        item = RandRigid6DoFd(keys="moving", translate_range=4.0, rotate_range=10.0, center_key="fixed")(
            {"fixed": fixed, "moving": fixed.clone()}
        )
        out = ResampleToNetworkGridd(size=32, spacing=1.5)(item)
        expected = transform_points(item["rigid_params"]["matrix"].double().numpy(), p)[0]
        assert np.linalg.norm(centroid(out["moving"]) - expected) < 0.75
        assert np.linalg.norm(centroid(out["fixed"]) - p) < 0.75


def test_normalize_hu():
    x = torch.tensor([[[[-2000.0, -1000.0, 500.0, 2000.0, 3000.0]]]])
    expected = torch.tensor([[[[0.0, 0.0, 0.5, 1.0, 1.0]]]])
    torch.testing.assert_close(NormalizeHU()(x), expected)
    torch.testing.assert_close(NormalizeHUd(keys="moving")({"moving": x})["moving"], expected)


def test_antialias_suppresses_aliased_noise_and_keeps_smooth_content():
    """A 1 mm noise volume sampled onto a 4 mm grid: the pre-filter cuts the aliased noise by > 2x, and leaves a
    smooth ramp (no fine detail to alias) unchanged in the interior."""
    from monai.data import MetaTensor

    from monai_rigidreg.transforms.grid import antialias_for_grid

    fine = Grid.centered((64, 64, 64), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    gen = torch.Generator().manual_seed(0)
    noise = MetaTensor(torch.randn(1, 64, 64, 64, generator=gen) * 100.0, affine=torch.as_tensor(fine.affine("RAS")))
    coarse = dict(size=14, spacing=4.0)
    with_aa = ResampleToNetworkGrid(**coarse, antialias=True)(noise)
    without = ResampleToNetworkGrid(**coarse, antialias=False)(noise)
    assert float(without[0, 2:-2, 2:-2, 2:-2].std()) > 2.0 * float(with_aa[0, 2:-2, 2:-2, 2:-2].std())
    # a linear ramp is invariant under the (symmetric, normalized) Gaussian in the interior
    x = torch.arange(64, dtype=torch.float32).reshape(64, 1, 1).expand(64, 64, 64)[None].clone()
    out = antialias_for_grid(x, fine, Grid.centered((14, 14, 14), (4.0,) * 3, (0.0, 0.0, 0.0)))
    torch.testing.assert_close(out[:, 10:-10, 10:-10, 10:-10], x[:, 10:-10, 10:-10, 10:-10], atol=1e-2, rtol=0)
    # nothing to do when the input is not finer than the grid
    assert antialias_for_grid(x, Grid.centered((64,) * 3, (4.0,) * 3, (0, 0, 0)), fine) is x


def test_antialias_crops_to_the_grid_without_changing_values():
    """Only the part of a large fine image that the network grid covers is filtered: same values as filtering and
    sampling the whole image, on an oblique input and an off-centre grid."""
    from monai.data import MetaTensor

    from monai_rigidreg.transforms.grid import antialias_for_grid, crop_to_grid
    from monai_rigidreg.transforms.utils import resample_physical

    fine = Grid((72, 64, 60), (1.0, 1.2, 1.5), (-40.0, -35.0, -42.0),
                tuple(rotation_matrix(*np.deg2rad([5.0, -8.0, 12.0])).ravel()))
    gen = torch.Generator().manual_seed(1)
    vol = torch.randn(1, *fine.size, generator=gen) * 100.0
    out_grid = Grid.centered((8, 8, 8), (4.0,) * 3, (6.0, -4.0, 3.0))  # 32 mm cube inside a ~70 mm volume
    crop, sub = crop_to_grid(vol, fine, out_grid, margin=7)
    assert crop.numel() < 0.5 * vol.numel()
    img = MetaTensor(vol, affine=torch.as_tensor(fine.affine("RAS")))
    got = ResampleToNetworkGrid(size=8, spacing=4.0, antialias=True, padding_value=0.0)(img, grid=out_grid)
    ref = resample_physical(antialias_for_grid(vol, fine, out_grid), np.eye(4), out_grid, fine, "bilinear", "zeros",
                            0.0)
    torch.testing.assert_close(torch.as_tensor(got), torch.as_tensor(ref), atol=1e-3, rtol=1e-4)


@pytest.mark.parametrize("sigmas", [(0.5, 0.5, 0.5), (1.3, 0.4, 2.2), (0.0, 0.8, 0.3)])
def test_gaussian_smooth_equals_monai_gaussian_smooth(sigmas):
    """The shifted-sum separable filter reproduces MONAI's ``GaussianSmooth`` (kernel, truncation, zero padding),
    on several channels and a non-contiguous (transposed) view; a zero sigma leaves that axis alone."""
    gen = torch.Generator().manual_seed(2)
    vol = (torch.randn(2, 14, 17, 11, generator=gen) * 100.0).permute(0, 3, 2, 1)  # [2, 11, 17, 14], a view
    got = gaussian_smooth(vol, sigmas)
    if min(sigmas) > 0:
        ref = torch.as_tensor(GaussianSmooth(sigma=list(sigmas))(vol.contiguous()))
    else:  # MONAI needs positive sigmas: smooth the other axes one at a time
        ref = vol.contiguous()
        for axis, s in enumerate(sigmas):
            if s > 0:
                one = [1e-6] * 3
                one[axis] = s
                ref = torch.as_tensor(GaussianSmooth(sigma=one)(ref))
    torch.testing.assert_close(got, ref, atol=1e-4, rtol=1e-5)
