"""The torch warp (geometry.normalized_theta + torch affine_grid/grid_sample) against SimpleITK.Resample and MONAI's
AffineTransform."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch
from conftest import oblique_direction, smooth_random_image

from monai_rigidreg.core.geometry import Grid, params_to_matrix, params_to_sitk
from monai_rigidreg.core.warp import affine_grid, warp_points, warp_volume, warp_volume_many, warp_volume_params
from monai_rigidreg.io import metatensor_to_sitk, sitk_to_metatensor


@pytest.fixture(scope="module")
def moving_image():
    return smooth_random_image((24, 28, 20), (1.0, 1.5, 2.0), (-10.0, 5.0, 3.0), oblique_direction(10, -5, 20))


FIXED = Grid((26, 22, 18), (1.2, 1.3, 1.7), (-12.0, 2.0, 0.0), oblique_direction(-5, 8, 3))


def test_warp_on_every_device_and_dtype(moving_image, device_dtype):
    """The same warp on CPU/CUDA in float32/float64: dtype and device kept, values those of the CPU float64 warp."""
    device, dtype = device_dtype
    params = [2, -3, 1.5, 5, -4, 7]
    matrix = torch.tensor(params_to_matrix(params, FIXED.center()))[None]
    vol = torch.from_numpy(sitk.GetArrayFromImage(moving_image).transpose(2, 1, 0).copy())[None, None]
    ref = warp_volume(vol.double(), matrix, FIXED, Grid.from_sitk(moving_image))
    out = warp_volume(vol.to(device, dtype), matrix.to(device), FIXED, Grid.from_sitk(moving_image))
    assert out.dtype == dtype and out.device.type == device.type
    torch.testing.assert_close(out.cpu().double(), ref, atol=1e-4 * float(ref.abs().max()), rtol=0)


@pytest.mark.parametrize("params", [[0, 0, 0, 0, 0, 0], [2, -3, 1.5, 5, -4, 7], [-4, 1, 2, -12, 3, -9]])
@pytest.mark.parametrize("array_order", ["xyz", "zyx"])
def test_warp_matches_sitk_resample(moving_image, params, array_order):
    center = FIXED.center()
    ref = sitk.GetArrayFromImage(sitk.Resample(moving_image, FIXED.to_sitk(), params_to_sitk(params, center),
                                               sitk.sitkLinear, 0.0))
    arr = sitk.GetArrayFromImage(moving_image)
    t = torch.from_numpy(np.ascontiguousarray(arr.transpose(2, 1, 0) if array_order == "xyz" else arr))[None, None]
    out = warp_volume(t, torch.tensor(params_to_matrix(params, center))[None], FIXED, Grid.from_sitk(moving_image),
                      array_order=array_order)[0, 0].numpy()
    if array_order == "xyz":
        out = out.transpose(2, 1, 0)
    assert out.shape == ref.shape
    assert np.abs(out - ref).mean() < 0.01 * (ref.max() - ref.min())
    # where the sample point falls inside the moving voxel block (continuous index in [0, size - 1]) both are
    # plain trilinear interpolation and must agree to float precision; outside it ITK extrapolates half a voxel
    tfm = params_to_sitk(params, center)
    fixed_img = FIXED.to_sitk()
    inside = np.zeros(ref.shape, bool)
    for z, y, x in np.ndindex(*ref.shape):
        q = moving_image.TransformPhysicalPointToContinuousIndex(
            tfm.TransformPoint(fixed_img.TransformIndexToPhysicalPoint((x, y, z))))
        inside[z, y, x] = all(0 <= q[i] <= moving_image.GetSize()[i] - 1 for i in range(3))
    assert inside.sum() > 1000
    np.testing.assert_allclose(out[inside], ref[inside], atol=1e-4 * (ref.max() - ref.min()))


def test_warp_params_identity_is_exact_and_metatensor_roundtrip(moving_image):
    mt = sitk_to_metatensor(moving_image)
    grid = Grid.from_metatensor(mt)
    out = warp_volume_params(mt.as_tensor()[None], torch.zeros(1, 6), grid)
    torch.testing.assert_close(out[0], mt.as_tensor(), atol=1e-5, rtol=0)
    back = metatensor_to_sitk(mt)
    assert back.GetSize() == moving_image.GetSize()
    np.testing.assert_allclose(back.GetDirection(), moving_image.GetDirection(), atol=1e-12)
    np.testing.assert_allclose(back.GetOrigin(), moving_image.GetOrigin(), atol=1e-12)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(back), sitk.GetArrayFromImage(moving_image))


def test_warp_rejects_bad_shapes(moving_image):
    grid = Grid.from_sitk(moving_image)
    with pytest.raises(ValueError, match="does not match its grid"):
        warp_volume(torch.zeros(1, 1, 5, 5, 5), torch.eye(4)[None], grid, grid)
    with pytest.raises(ValueError, match=r"\[B, C, D, H, W\]"):
        warp_volume(torch.zeros(5, 5, 5), torch.eye(4)[None], grid, grid)


@pytest.mark.parametrize("mode", ["bilinear", "nearest"])
@pytest.mark.parametrize("padding_mode", ["zeros", "border", "reflection"])
def test_warp_is_monai_affine_transform(moving_image, mode, padding_mode):
    """warp_volume samples as MONAI's AffineTransform (normalized theta, align_corners) did before it was called
    directly: batch of two different transforms, a different output size; to float rounding, as its sampling points
    are :func:`affine_grid`'s per-axis sums rather than torch's matrix product (a 1e-3 voxel shift fails it)."""
    from monai.networks.layers import AffineTransform

    from monai_rigidreg.core.geometry import normalized_theta

    moving_grid = Grid.from_sitk(moving_image)
    vol = torch.from_numpy(sitk.GetArrayFromImage(moving_image).transpose(2, 1, 0).copy())[None, None]
    vol = torch.cat([vol, -2.0 * vol]).float()
    matrix = torch.tensor(np.stack([params_to_matrix([2, -3, 1.5, 5, -4, 7], FIXED.center()),
                                    params_to_matrix([-9, 4, 0, -2, 11, 3], FIXED.center())]))
    got = warp_volume(vol, matrix, FIXED, moving_grid, mode=mode, padding_mode=padding_mode)
    theta = normalized_theta(matrix, FIXED, moving_grid, "xyz").float()
    ref = AffineTransform(normalized=True, mode=mode, padding_mode=padding_mode, align_corners=True,
                          reverse_indexing=False)(vol, theta, spatial_size=FIXED.size)
    assert got.shape == (2, 1, *FIXED.size)
    scale = float(vol.abs().max())
    torch.testing.assert_close(got, ref, atol=2e-6 * scale, rtol=0)
    shifted = matrix.clone()
    shifted[:, 0, 3] += 1e-3 * moving_grid.spacing[0]
    assert not torch.allclose(warp_volume(vol, shifted, FIXED, moving_grid, mode="bilinear"),
                              AffineTransform(normalized=True, align_corners=True, reverse_indexing=False)(
                                  vol, theta, spatial_size=FIXED.size), atol=2e-6 * scale, rtol=0)
    with pytest.raises(ValueError, match="mode"):
        warp_volume(vol, matrix, FIXED, moving_grid, mode="bicubic")


@pytest.mark.parametrize("mode", ["bilinear", "nearest"])
def test_one_volume_under_many_transforms_is_each_warp(moving_image, mode):
    """warp_volume_many: the K transforms' outputs are those of warp_volume one by one, in order (oblique grids)."""
    vol = torch.from_numpy(sitk.GetArrayFromImage(moving_image)).permute(2, 1, 0)[None, None]  # a transposed view
    vol = torch.cat([vol, 2.0 * vol + 1.0], 1)  # two channels
    mats = torch.tensor(np.stack([params_to_matrix(p, FIXED.center()) for p in
                                  ([0, 0, 0, 0, 0, 0], [2, -3, 1.5, 5, -4, 7], [-4, 1, 0, 0, 12, -3])]))
    out = warp_volume_many(vol, mats, FIXED, Grid.from_sitk(moving_image), mode=mode)
    assert tuple(out.shape) == (3, 2, *FIXED.size)
    for k in range(3):
        torch.testing.assert_close(out[k], warp_volume(vol, mats[k:k + 1], FIXED, Grid.from_sitk(moving_image),
                                                        mode=mode)[0], rtol=0, atol=1e-5)
    assert not torch.allclose(out[0], out[1])


def test_warp_points_are_warp_volume_at_those_voxels(device_dtype):
    # oblique, anisotropic grids of unequal sizes per axis: a transposed axis or a flipped grid component in the
    # normalized coordinates would sample elsewhere
    device, dtype = device_dtype
    fixed = Grid((20, 17, 13), (1.5, 2.0, 2.5), (-10.0, 5.0, 3.0), oblique_direction(10.0, -5.0, 20.0))
    m_dir = oblique_direction(-15.0, 10.0, 5.0)
    m_size, m_spacing = (15, 22, 18), (3.0, 2.0, 2.5)
    half_extent = np.reshape(m_dir, (3, 3)) @ ((np.asarray(m_size) - 1) / 2 * np.asarray(m_spacing))
    moving = Grid(m_size, m_spacing, tuple(fixed.center() - half_extent), m_dir)  # same centre as the fixed grid
    vol = torch.rand(2, 3, *moving.size, generator=torch.Generator().manual_seed(1)).to(device, dtype)
    mats = torch.as_tensor(np.stack([params_to_matrix([1, 2, -3, 5, -4, 10], fixed.center()),
                                     params_to_matrix([0, -2, 1, -3, 2, 1], fixed.center())])).to(device)
    full = warp_volume(vol, mats, fixed, moving).flatten(2)  # [2, 3, N]
    index = torch.randperm(full.shape[-1], generator=torch.Generator().manual_seed(2))[:400].to(device)
    points = torch.stack(torch.unravel_index(index, fixed.size), 1).to(dtype)
    sampled = warp_points(vol, mats, points, fixed, moving)
    assert sampled.shape == (2, 3, 400)
    tol = 1e-5 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(sampled, full[:, :, index], atol=tol, rtol=0)
    assert (full[:, :, index] != 0).float().mean() > 0.5  # most points land inside the moving volume
    # a half-voxel shift of the points is the mean of the neighbours along that axis (trilinear)
    ident = torch.eye(4, dtype=torch.float64, device=device)[None].repeat(2, 1, 1)
    half = warp_points(vol, ident, torch.tensor([[3.5, 4.0, 5.0]], dtype=dtype, device=device), moving, moving)
    torch.testing.assert_close(half[:, :, 0], 0.5 * (vol[:, :, 3, 4, 5] + vol[:, :, 4, 4, 5]), atol=tol, rtol=0)
    with pytest.raises(ValueError, match="points"):
        warp_points(vol, mats, points[:, :2], fixed, moving)
    with pytest.raises(ValueError, match="batch"):
        warp_points(vol[:1], mats, points, fixed, moving)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_affine_grid_is_torch_s(dtype):
    """:func:`affine_grid` against ``F.affine_grid(align_corners=True)``: every point (a batch of two, an anisotropic
    size, one-voxel axes at coordinate 0) and the gradient with respect to ``theta``; a transposed axis fails it."""
    import torch.nn.functional as F

    g = torch.Generator().manual_seed(3)
    theta = torch.randn(2, 3, 4, generator=g, dtype=dtype)
    tol = {"atol": 1e-6, "rtol": 1e-6} if dtype == torch.float32 else {"atol": 1e-12, "rtol": 1e-12}
    for size in ((5, 7, 9), (1, 6, 4), (3, 1, 1)):
        got, want = affine_grid(theta, size), F.affine_grid(theta, [2, 1, *size], align_corners=True)
        assert got.shape == want.shape == (2, *size, 3) and got.dtype == dtype
        torch.testing.assert_close(got, want, **tol)
    assert not torch.allclose(affine_grid(theta, (7, 5, 9)).transpose(1, 2), F.affine_grid(
        theta, [2, 1, 5, 7, 9], align_corners=True), atol=1e-3)
    weight = torch.randn(2, 5, 7, 9, 3, generator=g, dtype=dtype)
    leaf = theta.clone().requires_grad_()
    (ours,) = torch.autograd.grad((affine_grid(leaf, (5, 7, 9)) * weight).sum(), leaf)
    (theirs,) = torch.autograd.grad((F.affine_grid(leaf, [2, 1, 5, 7, 9], align_corners=True) * weight).sum(), leaf)
    torch.testing.assert_close(ours, theirs, **{k: 100 * v for k, v in tol.items()})
    with pytest.raises(ValueError, match=r"\[B, 3, 4\]"):
        affine_grid(theta[:, :2], (5, 7, 9))
