"""Tests of monai_rigidreg.losses.RigidRegistrationLoss and its terms (tiny volumes, real numbers)."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch
from monai.losses import GlobalMutualInformationLoss, SSIMLoss

from monai_rigidreg.core.geometry import Grid, grid_points, target_registration_error
from monai_rigidreg.losses import (
    LossTerms,
    RigidRegistrationLoss,
    grid_gradient_penalty,
    masked_mutual_information,
    masked_ssim,
    supervised_point_distance,
)
from monai_rigidreg.networks import RigidTransformer

GRID = Grid.centered((24, 24, 24), (4.0, 4.0, 4.0), (10.0, -5.0, 3.0))
IMAGE_TERMS = ["ssim", "ncc", "mi", "grad_image"]


def _smooth(seed: int = 0, size: tuple[int, int, int] = (24, 24, 24), sigma: float = 2.0) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    img = sitk.SmoothingRecursiveGaussian(sitk.GetImageFromArray(rng.normal(size=size)), sigma)
    a = sitk.GetArrayFromImage(img)
    return torch.as_tensor((a - a.min()) / (a.max() - a.min()), dtype=torch.float32)[None, None]


def _fov_mask(size: int = 24, radius: float = 8.0) -> torch.Tensor:
    """A cylindrical CBCT-like field of view (axis along z), ``[1, 1, x, y, z]``."""
    i = torch.arange(size, dtype=torch.float32) - (size - 1) / 2
    r2 = i.view(-1, 1, 1) ** 2 + i.view(1, -1, 1) ** 2
    return (r2 <= radius**2).float().expand(size, size, size)[None, None].contiguous()


def _term(name: str, warped: torch.Tensor, fixed: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """Unweighted value of one image term through the public loss (lower is better)."""
    weights = {"w_ssim": 0.0, "w_ncc": 0.0, "w_mi": 0.0, "w_grad": 0.0, "w_reg": 0.0}
    key = {"ssim": "w_ssim", "ncc": "w_ncc", "mi": "w_mi", "grad_image": "w_grad"}[name]
    weights[key] = 1.0
    loss = RigidRegistrationLoss(**weights, grad_term="image")
    terms = loss(warped, fixed, torch.zeros(warped.shape[0], 6), mask=mask, grid=GRID)
    field = "grad" if name == "grad_image" else name
    value = float(getattr(terms, field))
    assert value == pytest.approx(float(terms.total), rel=1e-6, abs=1e-7)
    return value


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("name", IMAGE_TERMS)
def test_image_term_identical_best_shifted_worse(name, masked):
    fixed = _smooth(0)
    mask = _fov_mask() if masked else None
    best = _term(name, fixed, fixed, mask)
    tr = RigidTransformer(GRID, padding_mode="border")
    values = [best]
    for shift in (2.0, 4.0, 8.0):
        shifted = tr(fixed, torch.tensor([[shift, -shift / 2, 0.0, 0.0, 0.0, 0.0]]))
        values.append(_term(name, shifted, fixed, mask))
    tol = 1e-7 if name == "grad_image" else 1e-4  # (intensity/mm)^2 values are small at 4 mm spacing
    assert all(v > best + tol for v in values[1:]), values
    assert values[1] < values[3], values  # a small shift scores better than a large one
    rotated = tr(fixed, torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 10.0]]))
    assert _term(name, rotated, fixed, mask) > best + tol


def test_identical_values():
    fixed = _smooth(0)
    assert _term("ssim", fixed, fixed) == pytest.approx(0.0, abs=1e-5)
    assert _term("ncc", fixed, fixed) == pytest.approx(-1.0, abs=1e-5)
    assert _term("grad_image", fixed, fixed) == 0.0
    mi_self = -_term("mi", fixed, fixed)
    assert mi_self > 0.5 and mi_self > -_term("mi", fixed, _smooth(5))


@pytest.mark.parametrize("name", IMAGE_TERMS)
def test_image_term_ignores_voxels_outside_mask(name):
    fixed, warped = _smooth(0), _smooth(1)
    mask = _fov_mask()
    ref = _term(name, warped, fixed, mask)
    g = torch.Generator().manual_seed(3)
    outside = mask == 0
    w2 = warped.clone()
    w2[outside] = torch.rand(int(outside.sum()), generator=g)
    f2 = fixed.clone()
    f2[outside] = torch.rand(int(outside.sum()), generator=g)
    assert _term(name, w2, f2, mask) == pytest.approx(ref, abs=1e-6)
    unmasked = _term(name, warped, fixed)
    assert abs(_term(name, w2, f2) - unmasked) > 1e-3 * abs(unmasked)  # they do count without the mask
    w3 = warped.clone()
    w3[~outside] = _smooth(7)[~outside]  # inside does count
    assert abs(_term(name, w3, fixed, mask) - ref) > 1e-3 * abs(ref)


def test_masked_terms_reduce_to_monai_for_full_mask():
    x, y = _smooth(0), _smooth(1)
    ones = torch.ones_like(x)
    ref_ssim = 1.0 - SSIMLoss(spatial_dims=3, data_range=1.0, win_size=7, kernel_sigma=1.5)(x, y)
    assert float(masked_ssim(x, y, ones)[0]) == pytest.approx(float(ref_ssim), abs=1e-5)
    gmi = GlobalMutualInformationLoss(num_bins=32)
    assert float(masked_mutual_information(x, y, ones, gmi)[0]) == pytest.approx(float(-gmi(x, y)), abs=1e-5)
    loss = RigidRegistrationLoss()
    a = loss(x, y, torch.zeros(1, 6))
    b = loss(x, y, torch.zeros(1, 6), mask=ones)
    for fa, fb in zip(a, b):
        assert float(fa) == pytest.approx(float(fb), abs=1e-5)


def test_masked_ssim_gradient_equals_monai_for_full_mask():
    """masked_ssim backpropagates through image_ops.separable_filter: the same gradient as MONAI's SSIMLoss."""
    x, y = _smooth(0).requires_grad_(True), _smooth(1)
    ones = torch.ones_like(y)
    (g_ref,) = torch.autograd.grad(SSIMLoss(spatial_dims=3, data_range=1.0, win_size=7, kernel_sigma=1.5)(x, y), x)
    (g,) = torch.autograd.grad(1.0 - masked_ssim(x, y, ones)[0], x)
    torch.testing.assert_close(g, g_ref, atol=1e-7, rtol=1e-3)


def test_mi_float32_under_autocast():
    x, y = _smooth(0), _smooth(1)
    loss = RigidRegistrationLoss(0.0, 0.0, 1.0, 0.0, 0.0)
    ref = loss.mi_term(x, y)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        val = loss.mi_term(x.bfloat16(), y.bfloat16())
        val_masked = loss.mi_term(x.bfloat16(), y.bfloat16(), _fov_mask())
    assert val.dtype == torch.float32 and val_masked.dtype == torch.float32
    assert torch.isfinite(val_masked)
    assert float(val) == pytest.approx(float(ref), abs=2e-2)  # only the bf16 rounding of the inputs differs


def test_grid_gradient_term():
    """||R - I||_F^2 = 4 (1 - cos theta): 0 for translations, independent of the centre, grows with the angle."""
    loss = RigidRegistrationLoss(0.0, 0.0, 0.0, 1.0, 0.0)
    x = _smooth(0)
    params = torch.tensor([[0, 0, 0, 0, 0, 0], [5, -3, 2, 0, 0, 0], [0, 0, 0, 10, 0, 0], [0, 0, 0, 20, 0, 0.0]])
    vals = [float(loss(x, x, p[None], grid=GRID).grad) for p in params]
    assert vals[0] == 0.0 and vals[1] == pytest.approx(0.0, abs=1e-10)
    assert vals[2] == pytest.approx(4 * (1 - np.cos(np.deg2rad(10))), rel=1e-4)
    assert vals[3] > vals[2]
    # equals the mean squared finite-difference gradient of the sampling grid's displacement field
    from monai_rigidreg.core.geometry import params_to_matrix

    m = params_to_matrix([1, 2, 3, 4, -5, 6], GRID.center())
    pts = grid_points(GRID, step=1).reshape(24, 24, 24, 3)
    disp = pts @ m[:3, :3].T + m[:3, 3] - pts
    fd = sum(((np.diff(disp, axis=a) / 4.0) ** 2).sum(-1).mean() for a in range(3))
    pen = grid_gradient_penalty(torch.as_tensor(m)[None])
    assert float(pen[0]) == pytest.approx(fd, rel=1e-9)


def test_supervised_term():
    grid = GRID
    loss = RigidRegistrationLoss(0.0, 0.0, 0.0, 0.0, 0.0, w_sup=1.0)
    x = _smooth(0)
    p_true = torch.tensor([[3.0, -2.0, 5.0, 4.0, -3.0, 6.0]])
    # identical parameters: exactly 0 with a finite (zero) gradient
    p = p_true.clone().requires_grad_(True)
    terms = loss(x, x, p, p_true, grid=grid)
    assert float(terms.sup.detach()) == 0.0
    terms.total.backward()
    assert torch.isfinite(p.grad).all() and float(p.grad.abs().max()) == 0.0
    # pure translation difference: the TRE is |dt| at every point
    dt = torch.tensor([[3.0, 4.0, 12.0, 0.0, 0.0, 0.0]])
    assert float(loss(x, x, p_true + dt, p_true, grid=grid).sup) == pytest.approx(13.0, rel=1e-6)
    # general case: equals geometry.target_registration_error on every 4th voxel
    p_pred = torch.tensor([[1.0, 2.0, -3.0, -5.0, 7.0, 2.0]])
    ref = target_registration_error(p_pred[0].numpy(), p_true[0].numpy(), grid_points(grid, 4), center=grid.center())
    assert float(loss(x, x, p_pred, p_true, grid=grid).sup) == pytest.approx(ref, rel=1e-5)
    # a mask restricts the points; the gradient flows to the prediction
    mask = torch.zeros(1, 1, 24, 24, 24)
    mask[:, :, :12] = 1.0
    pts = grid_points(grid, 4)
    inside = pts[:, 0] < grid.center()[0]
    ref_m = target_registration_error(p_pred[0].numpy(), p_true[0].numpy(), pts[inside], center=grid.center())
    q = p_pred.clone().requires_grad_(True)
    val = loss(x, x, q, p_true, mask=mask, grid=grid).sup
    assert float(val.detach()) == pytest.approx(ref_m, rel=1e-5)
    val.backward()
    assert float(q.grad.abs().sum()) > 0
    # batch: per-item mean then batch mean
    both = supervised_point_distance(
        torch.cat([p_true + dt, p_true]), torch.cat([p_true, p_true]), torch.as_tensor(pts), grid.center()
    )
    assert np.allclose(both.numpy(), [13.0, 0.0], atol=1e-5)


def test_total_and_weights():
    fixed, warped = _smooth(0), _smooth(1)
    p_pred = torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]])
    p_true = torch.zeros(1, 6)
    loss = RigidRegistrationLoss(w_ssim=1.0, w_ncc=0.1, w_mi=0.1, w_grad=0.1, w_reg=1e-4, w_sup=0.5)
    t = loss(warped, fixed, p_pred, p_true, grid=GRID)
    assert isinstance(t, LossTerms)
    expected = t.ssim + 0.1 * t.ncc + 0.1 * t.mi + 0.1 * t.grad + 1e-4 * t.reg + 0.5 * t.sup
    assert float(t.total) == pytest.approx(float(expected), rel=1e-6)
    assert float(t.reg) == pytest.approx(91.0)
    assert set(t.as_dict()) == {"total", "ssim", "ncc", "mi", "grad", "reg", "sup"}
    assert all(float(v) != 0.0 for v in t)
    with pytest.raises(ValueError):
        RigidRegistrationLoss(w_sup=1.0)(warped, fixed, p_pred)  # needs params_true and grid
    with pytest.raises(ValueError):
        RigidRegistrationLoss(grad_term="other")


def test_end_to_end_gradient_through_transformer(device_dtype):
    """The image terms back-propagate through the rigid transformer to the six parameters, on every device and
    dtype, with the same gradient as on the CPU in float64."""
    device, dtype = device_dtype

    def grad_of(dev: torch.device, dt: torch.dtype) -> torch.Tensor:
        fixed = _smooth(0).to(dev, dt)
        tr = RigidTransformer(GRID)
        moving = tr(fixed, torch.tensor([[-4.0, 0, 0, 0, 0, 0]], dtype=dt, device=dev))  # moving(T(x)) ~ fixed, tx=+4
        p = torch.zeros(1, 6, dtype=dt, device=dev, requires_grad=True)
        RigidRegistrationLoss()(tr(moving, p), fixed, p, grid=GRID).total.backward()
        return p.grad.detach().cpu().double()

    g = grad_of(device, dtype)
    assert torch.isfinite(g).all()
    assert float(g[0, 0]) < 0  # increasing tx towards the truth (+4 mm) lowers the loss
    ref = grad_of(torch.device("cpu"), torch.float64)
    # float32: MI histograms and SSIM sums round differently (about 1 % of the largest component)
    tol = 1e-6 if dtype == torch.float64 else 3e-2
    torch.testing.assert_close(g, ref, atol=tol * float(ref.abs().max()), rtol=0)
