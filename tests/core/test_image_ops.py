"""Tests of the general image operations (monai_rigidreg.core.image_ops)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from monai.networks.layers import GaussianFilter, separable_filtering
from monai.networks.layers.convutils import gaussian_1d

import monai_rigidreg.losses
from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.core.image_ops import (
    SHIFTED_SUM_MAX_TAPS,
    broadcast_mask,
    erode,
    gaussian_kernel_1d,
    gaussian_smooth,
    gradient_magnitude,
    local_mean,
    masked_ncc,
    pyramid,
    separable_filter,
)

try:  # the implementation local_mean replaces, while it exists
    from monai_rigidreg.networks.alignment import _local_mean as _alignment_local_mean
except ImportError:
    _alignment_local_mean = None

torch.set_num_threads(1)
METHODS = ("shifted", "conv", "matrix")


def _reference_local_mean(volume: torch.Tensor, mask: torch.Tensor, sigma_vox: list[float]) -> torch.Tensor:
    """The former ``networks.alignment._local_mean``: normalized convolution with MONAI's ``GaussianFilter``."""
    factor = max(1, min(4, int(min(sigma_vox) // 2)))
    num, den = volume * mask, mask
    if factor > 1:
        num, den = F.avg_pool3d(num, factor, ceil_mode=True), F.avg_pool3d(den, factor, ceil_mode=True)
    blur = GaussianFilter(3, [s / factor for s in sigma_vox])
    mean = blur(num) / blur(den).clamp_min(1e-3)
    if factor > 1:
        mean = F.interpolate(mean, size=volume.shape[2:], mode="trilinear", align_corners=False)
    return mean


def _rand(*shape: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


# -- kernels ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("sigma", [0.1, 0.3, 0.7, 1.5, 2.0, 4.2, 6.35])
@pytest.mark.parametrize("truncated", [1.0, 3.0, 4.0])
@pytest.mark.parametrize("normalize", [False, True])
def test_erf_kernel_is_monai_gaussian_1d(sigma, truncated, normalize):
    ref = gaussian_1d(torch.tensor(sigma), truncated=truncated, approx="erf", normalize=normalize)
    got = gaussian_kernel_1d(sigma, truncated, "erf", normalize)
    assert torch.equal(got, ref)
    # an explicit size with the same number of taps is the same kernel
    torch.testing.assert_close(gaussian_kernel_1d(sigma, approx="erf", normalize=normalize, size=ref.numel()), ref)


def test_kernel_sizes_dtype_and_sampled_values():
    k = gaussian_kernel_1d(2.0, approx="erf", size=9, dtype=torch.float64)
    assert k.shape == (9,) and k.dtype == torch.float64
    assert gaussian_kernel_1d(0.5, size=1).shape == (1,)
    assert float(gaussian_kernel_1d(0.5, size=1, normalize=True)) == 1.0
    # sampled: exp(-x^2 / 2 sigma^2), normalized (MONAI's SSIM window, even sizes at half-integer offsets)
    for size in (6, 7):
        dist = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
        ref = torch.exp(-0.5 * (dist / 1.5) ** 2)
        got = gaussian_kernel_1d(1.5, approx="sampled", normalize=True, size=size, dtype=torch.float64)
        assert torch.equal(got, ref / ref.sum())
    # not normalized: the density at the taps; MONAI's number of taps by default
    got = gaussian_kernel_1d(1.2, approx="sampled")
    ref = gaussian_1d(torch.tensor(1.2), approx="sampled")
    torch.testing.assert_close(got, ref, atol=1e-6, rtol=1e-5)
    assert abs(float(gaussian_kernel_1d(3.0, approx="sampled", truncated=6.0).sum()) - 1.0) < 1e-4
    with pytest.raises(ValueError):
        gaussian_kernel_1d(0.0)
    with pytest.raises(ValueError):
        gaussian_kernel_1d(1.0, size=4)  # erf kernels are centred
    with pytest.raises(ValueError):
        gaussian_kernel_1d(1.0, approx="scalespace")  # type: ignore[arg-type]


# -- separable filter --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("padding", ["zeros", "replicate"])
@pytest.mark.parametrize("method", METHODS)
def test_separable_filter_equals_monai_separable_filtering(padding, method):
    """Both implementations give MONAI's ``separable_filtering`` (correlation, asymmetric kernels included)."""
    x = _rand(2, 3, 9, 11, 13)
    kernels = [_rand(5, seed=1), _rand(3, seed=2), _rand(7, seed=3)]
    ref = separable_filtering(x, kernels, mode=padding)
    torch.testing.assert_close(separable_filter(x, kernels, padding, method), ref, atol=1e-5, rtol=1e-5)
    # any leading axes; the kernels act on the last ones; a non-contiguous view
    flat = x.reshape(6, 9, 11, 13).permute(0, 3, 2, 1)
    got = separable_filter(flat, kernels[::-1], padding, method)
    torch.testing.assert_close(got.permute(0, 3, 2, 1).reshape(ref.shape), ref, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("method", METHODS)
def test_separable_filter_valid_and_skipped_axes(method):
    x = _rand(2, 1, 12, 10, 9, dtype=torch.float64)
    g = [_rand(5, seed=1, dtype=torch.float64), _rand(4, seed=2, dtype=torch.float64), None]
    got = separable_filter(x, g, "valid", method)
    weight = (g[0][:, None] * g[1][None, :])[None, None, :, :, None]
    torch.testing.assert_close(got, F.conv3d(x, weight))
    assert got.shape == (2, 1, 8, 7, 9)
    assert separable_filter(x, [None, None], "zeros", method) is x


def test_separable_filter_auto_switches_at_the_crossover():
    """``auto`` is the shifted sum up to SHIFTED_SUM_MAX_TAPS taps and the convolution beyond (same result)."""
    x = _rand(3, 80, 70)
    for taps in (SHIFTED_SUM_MAX_TAPS, SHIFTED_SUM_MAX_TAPS + 2):
        k = gaussian_kernel_1d(taps / 6.0, approx="sampled", normalize=True, size=taps)
        ref = separable_filtering(x[:, None], [k, k], mode="replicate")[:, 0]
        for method in ("auto", *METHODS):
            torch.testing.assert_close(separable_filter(x, [k, k], "replicate", method), ref, atol=1e-6, rtol=1e-5)


def test_separable_filter_errors():
    x = _rand(1, 8, 8)
    with pytest.raises(ValueError):
        separable_filter(x, [torch.ones(4)], "zeros")  # even kernel needs 'valid'
    with pytest.raises(ValueError):
        separable_filter(x, [torch.ones(9)], "valid")  # longer than the axis
    with pytest.raises(ValueError):
        separable_filter(x, [torch.ones(3)], "reflect")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        separable_filter(x, [torch.ones(3)] * 4)


@pytest.mark.parametrize("padding", ["zeros", "replicate", "valid"])
@pytest.mark.parametrize("method", METHODS)
def test_separable_filter_gradcheck(padding, method):
    x = _rand(2, 5, 6, 7, dtype=torch.float64).requires_grad_(True)
    kernels = [_rand(3, seed=1, dtype=torch.float64), None, _rand(5, seed=2, dtype=torch.float64)]
    assert torch.autograd.gradcheck(lambda t: separable_filter(t, kernels, padding, method), (x,))


# -- the callers' filters ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ("auto", *METHODS))
def test_gaussian_smooth_is_monai_gaussian_filter_on_5d(method):
    x = _rand(2, 2, 15, 12, 10) * 100.0
    sigmas = [1.3, 0.6, 2.4]
    got = gaussian_smooth(x, sigmas, method=method)
    torch.testing.assert_close(got, GaussianFilter(3, sigmas)(x), atol=1e-4, rtol=1e-5)
    assert gaussian_smooth(x, [0.0, 0.0, -1.0]) is x


def test_cbct_blur_kernel_matches_monai_replicate_filter():
    """transforms.cbct: erf kernel truncated at 3 sigma, renormalized, replicate padding."""
    x = _rand(1, 20, 18, 16) * 1000.0
    sig = [1.2, 0.8, 0.5]
    kernels = [gaussian_1d(torch.tensor(s), truncated=3.0, approx="erf", normalize=True) for s in sig]
    ref = separable_filtering(x[None], kernels, mode="replicate")[0]
    got = gaussian_smooth(x, sig, truncated=3.0, padding="replicate", normalize=True)
    torch.testing.assert_close(got, ref, atol=1e-3, rtol=1e-5)


def test_scatter_blur_matches_conv2d_reference():
    """simulation.physics scatter: sampled kernel of radius ceil(3 sigma), normalized, replicate (long kernels)."""
    images = _rand(3, 70, 90) * 1e5
    sig = (12.5, 9.0)
    ref = images[:, None]
    for axis, s in enumerate(sig):
        r = math.ceil(3 * s)
        k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float32) / s) ** 2)
        k = (k / k.sum()).view(1, 1, -1, 1) if axis == 0 else (k / k.sum()).view(1, 1, 1, -1)
        ref = F.conv2d(F.pad(ref, (0, 0, r, r) if axis == 0 else (r, r, 0, 0), mode="replicate"), k)
    kernels = [gaussian_kernel_1d(s, approx="sampled", normalize=True, size=2 * math.ceil(3 * s) + 1) for s in sig]
    for method in METHODS:  # the physics uses "matrix"
        got = separable_filter(images, kernels, padding="replicate", method=method)
        torch.testing.assert_close(got, ref[:, 0], atol=0.05, rtol=1e-5)


@pytest.mark.parametrize("padding", ["zeros", "replicate"])
def test_matrix_method_with_a_kernel_longer_than_the_axis(padding):
    """The detector's scatter kernel can outgrow a short detector axis: the matrix folds every tap that leaves the
    axis into the edge (replicate) or drops it (zeros), as the padded shifted sum does."""
    x = _rand(4, 6, 5)
    kernels = [_rand(17, seed=4), _rand(11, seed=5)]
    ref = separable_filter(x, kernels, padding, "shifted")
    torch.testing.assert_close(separable_filter(x, kernels, padding, "matrix"), ref, atol=1e-5, rtol=1e-5)
    edge = torch.zeros(1, 7)
    edge[0, 0] = 1.0  # replicate: the first sample's value continues to the left, so taps left of it weigh on it
    got = separable_filter(edge, [torch.ones(5) / 5], padding, "matrix")
    want = [3 / 5, 2 / 5, 1 / 5] if padding == "replicate" else [1 / 5, 1 / 5, 1 / 5]
    torch.testing.assert_close(got[0, :3], torch.tensor(want))


@pytest.mark.parametrize("sigma", [[3.0, 3.0, 3.0], [5.0, 4.5, 6.0], [8.0, 8.0, 8.0], [16.0, 12.0, 9.0]])
def test_local_mean_matches_alignment_local_mean(sigma):
    """The normalized convolution of the Gauss-Newton features (pooled by 1, 2 and 4) is unchanged."""
    volume = _rand(2, 1, 40, 36, 32)
    volume[:, :, :6] = 0.0
    mask = (volume > 1e-3).float()
    ref_fn = _alignment_local_mean if _alignment_local_mean is not None else _reference_local_mean
    ref = ref_fn(volume, mask, sigma)
    torch.testing.assert_close(local_mean(volume, mask, sigma), ref, atol=1e-6, rtol=1e-5)
    two = torch.cat([volume, 2 * volume], 1)  # several channels, one mask
    torch.testing.assert_close(local_mean(two, mask, sigma)[:, 1], 2 * ref[:, 0], atol=1e-5, rtol=1e-5)


# -- morphology, gradients, pyramid, NCC -------------------------------------------------------------------------


def test_erode_gradient_magnitude_and_pyramid():
    mask = torch.zeros(1, 1, 12, 12, 12)
    mask[:, :, 2:10, 3:9, 4:8] = 1.0
    eroded = erode(mask, (1, 2, 0))
    assert torch.equal(eroded[0, 0, 3:9, 5:7, 4:8], torch.ones(6, 2, 4)) and eroded.sum() == 6 * 2 * 4
    assert torch.equal(erode(torch.ones(1, 1, 5, 5, 5), (2, 2, 2)), torch.ones(1, 1, 5, 5, 5))  # border kept
    ramp = torch.arange(10.0)[:, None, None].expand(10, 6, 4) * 2.0
    assert torch.allclose(gradient_magnitude(ramp), torch.full_like(ramp, 2.0))
    assert torch.allclose(gradient_magnitude(torch.zeros(4, 4, 4), eps=1e-6), torch.full((4, 4, 4), 1e-3))
    grid = Grid.centered((8, 8, 8), (2.0, 2.0, 2.0), (1.0, -2.0, 3.0))
    vol = _rand(1, 1, 8, 8, 8)
    pooled, g2 = pyramid(vol, grid, 2)
    assert pooled.shape == (1, 1, 4, 4, 4) and tuple(g2.spacing) == (4.0, 4.0, 4.0)
    np.testing.assert_allclose(g2.center(), grid.center())
    assert torch.allclose(pooled[0, 0, 0, 0, 0], vol[0, 0, :2, :2, :2].mean())
    assert pyramid(vol, grid, 1)[0] is vol


def _box_min_reference(x, radius):
    """The box min-filter as max_pool3d of the negated values (voxels outside the volume do not count)."""
    import torch.nn.functional as F

    for axis, r in enumerate(radius):
        if r > 0:
            kernel = [1, 1, 1]
            kernel[axis] = 2 * r + 1
            x = -F.max_pool3d(-x, tuple(kernel), 1, tuple(k // 2 for k in kernel))
    return x


@pytest.mark.parametrize("radius", [(1, 3, 0), (4, 4, 4), (0, 0, 2)])
def test_erode_is_the_box_min_filter(radius):
    """erode's sliding-window minimum equals the box min-filter (max_pool3d of the negated values, border not
    eroded) on non-binary values, several cases and channels, anisotropic radii, float and integer dtypes (an int64
    pad value must not wrap at the border); gradients pass through."""
    x = _rand(2, 3, 9, 11, 13, seed=5).requires_grad_(True)
    out = erode(x, radius)
    assert out.shape == x.shape and torch.equal(out.detach(), _box_min_reference(x.detach(), radius))
    out.sum().backward()
    assert x.grad is not None and float(x.grad.sum()) == pytest.approx(out.numel())
    for dtype in (torch.int64, torch.uint8, torch.float64):
        levels = (x.detach() * 200).to(dtype)
        assert torch.equal(erode(levels, radius), _box_min_reference(levels.double(), radius).to(dtype))


def test_masked_ncc_is_pearson_over_the_mask_and_exported_by_losses():
    assert monai_rigidreg.losses.masked_ncc is masked_ncc
    x, y = _rand(2, 1, 6, 7, 8, seed=1), _rand(2, 1, 6, 7, 8, seed=2)
    y = y + 0.5 * x
    mask = (_rand(2, 1, 6, 7, 8, seed=3) > 0.4).float()
    got = masked_ncc(x, y, mask)
    for b in range(2):
        sel = mask[b, 0] > 0
        ref = np.corrcoef(x[b, 0][sel].double().numpy(), y[b, 0][sel].double().numpy())[0, 1]
        assert float(got[b]) == pytest.approx(ref, abs=1e-5)
    assert torch.allclose(masked_ncc(x, x), torch.ones(2), atol=1e-5)
    assert broadcast_mask(None, x) is None
    assert broadcast_mask(mask * 3.0, x).unique().tolist() == [0.0, 1.0]
    with pytest.raises(ValueError):
        broadcast_mask(mask[:, :, :5], x)
