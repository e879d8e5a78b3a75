"""Tests of the weight-free Gauss-Newton stage (monai_rigidreg.networks.gauss_newton) and of the two-stage network."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import monai_rigidreg.networks.gauss_newton as gauss_newton_module
from monai_rigidreg.core.geometry import Grid, matrix_to_params_torch, params_to_matrix_torch, rotation_matrix
from monai_rigidreg.core.image_ops import erode
from monai_rigidreg.core.warp import warp_volume
from monai_rigidreg.engine import RegistrationCriterion
from monai_rigidreg.losses import RigidRegistrationLoss
from monai_rigidreg.networks import DualEncoderRigidNet, GaussNewtonStage, TwoStageRigidNet
from monai_rigidreg.networks.gauss_newton import fixed_jacobian, gauss_newton_align, parameter_flow, polynomial_basis
from monai_rigidreg.registration.last_level import support_reach

TINY = {"channels": (4, 8, 8), "strides": (2, 2, 2), "pool_size": 2, "hidden": (16,)}


def _blobs(size: tuple[int, int, int], seed: int = 0, n: int = 8, spread: float = 0.6, sharp: float = 1.0
           ) -> torch.Tensor:
    """Smooth random volume ``[1, 1, *size]`` (sum of anisotropic Gaussians centred within ``+-spread`` of the
    normalized extent, widths divided by ``sqrt(sharp)``), float64."""
    g = torch.Generator().manual_seed(seed)
    axes = [torch.linspace(-1, 1, s, dtype=torch.float64) for s in size]
    x, y, z = torch.meshgrid(*axes, indexing="ij")
    vol = torch.zeros(size, dtype=torch.float64)
    for _ in range(n):
        c = (torch.rand(3, generator=g, dtype=torch.float64) * 2 - 1) * spread
        w = (torch.rand(3, generator=g, dtype=torch.float64) * 8 + 4) * sharp
        vol += torch.exp(-(w[0] * (x - c[0]) ** 2 + w[1] * (y - c[1]) ** 2 + w[2] * (z - c[2]) ** 2))
    return vol[None, None]


def _moving_for(fixed: torch.Tensor, params: torch.Tensor, grid: Grid) -> torch.Tensor:
    """A moving volume with ``moving(T(x)) = fixed(x)`` for ``T`` of ``params``: ``fixed`` warped by ``T^-1``."""
    t = params_to_matrix_torch(params, grid.center())
    return warp_volume(fixed, torch.linalg.inv(t), grid, grid, padding_mode="border")


def test_jacobian_matches_finite_differences_of_warp_on_oblique_grid():
    # oblique, anisotropic grid off the origin: the chain rule must agree with warping by perturbed transforms
    direction = rotation_matrix(*np.deg2rad([10.0, 20.0, -15.0])).ravel()
    grid = Grid((20, 24, 18), (2.0, 1.5, 3.0), (5.0, -3.0, 10.0), tuple(direction))
    fixed = _blobs(grid.size, seed=3)
    jac = fixed_jacobian(fixed, grid)[0]  # [6, 1, x, y, z]
    h = 1e-3
    eye = torch.eye(6, dtype=torch.float64)
    mats = params_to_matrix_torch(torch.cat([eye * h, -eye * h]), grid.center())
    warped = warp_volume(fixed.repeat(12, 1, 1, 1, 1), mats, grid, grid, padding_mode="border")
    ref = (warped[:6] - warped[6:]) / (2 * h)
    inner = (slice(None), slice(None), slice(3, -3), slice(3, -3), slice(3, -3))
    assert ref[inner].abs().max() > 0.05
    assert (jac - ref)[inner].abs().max() < 1e-3 * ref[inner].abs().max()


def test_jacobian_is_the_gradient_times_the_parameter_flow():
    # the ramp form of fixed_jacobian equals the chain rule through the [6, 3, N] flow it no longer builds
    direction = rotation_matrix(*np.deg2rad([-25.0, 5.0, 40.0])).ravel()
    grid = Grid((14, 11, 9), (1.2, 2.5, 1.7), (-30.0, 12.0, 80.0), tuple(direction))
    fixed = torch.rand(2, 3, *grid.size, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    g_idx = torch.gradient(fixed, dim=(2, 3, 4))
    inv_t = np.linalg.inv(grid.index_to_physical()[:3, :3]).T
    g_phys = [sum(float(inv_t[a, i]) * g_idx[i] for i in range(3)) for a in range(3)]
    flow = parameter_flow(grid)
    ref = torch.stack([sum(g_phys[a] * flow[k, a] for a in range(3)) for k in range(6)], 1)
    jac = fixed_jacobian(fixed, grid)
    assert jac.shape == (2, 6, 3, *grid.size)
    torch.testing.assert_close(jac, ref, rtol=1e-9, atol=1e-9)


def test_parameter_flow_translation_and_rotation_units():
    grid = Grid.centered((5, 5, 5), (2.0, 2.0, 2.0), (10.0, 0.0, 0.0))
    flow = parameter_flow(grid)
    # translations: unit displacement along their own axis everywhere
    for k in range(3):
        expected = torch.zeros(3, *grid.size, dtype=torch.float64)
        expected[k] = 1.0
        assert torch.allclose(flow[k], expected, atol=1e-9)
    # rotation about z at a point 4 mm along +x from the centre: pi/180 * 4 mm along +y per degree
    np.testing.assert_allclose(flow[5, :, 4, 2, 2].numpy(), [0.0, 4 * np.pi / 180, 0.0], atol=1e-7)


@pytest.mark.parametrize("params", [[4.0, -3.0, 2.0, 3.0, -4.0, 5.0], [8.0, 0.0, 0.0, 0.0, 0.0, 8.0]])
def test_gauss_newton_recovers_known_motion(params, device_dtype):
    device, dtype = device_dtype
    grid = Grid.centered((32, 32, 32), (3.0, 3.0, 3.0), (0.0, 0.0, 0.0))
    fixed = _blobs(grid.size, seed=1)
    p = torch.tensor([params], dtype=torch.float64)
    moving = _moving_for(fixed, p, grid).to(device, dtype)
    fixed = fixed.to(device, dtype)
    total = torch.eye(4, dtype=torch.float64, device=device)[None]
    for level_iters in (10, 10):
        total = gauss_newton_align(moving, fixed, grid, total, iterations=level_iters)
    assert total.dtype == torch.float64 and total.device.type == device.type
    est = matrix_to_params_torch(total, grid.center())[0].cpu()
    np.testing.assert_allclose(est[:3].numpy(), params[:3], atol=0.2)
    np.testing.assert_allclose(est[3:].numpy(), params[3:], atol=0.2)


def test_polynomial_basis_terms():
    grid = Grid.centered((5, 6, 7), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    assert [polynomial_basis(grid, d).shape[0] for d in range(4)] == [1, 4, 10, 20]
    b = polynomial_basis(grid, 2, torch.float64)
    assert torch.all(b[0] == 1.0) and b[1:].abs().max() == 1.0
    x = torch.linspace(-1, 1, 5, dtype=torch.float64)
    torch.testing.assert_close(b[1][:, 0, 0], x)  # the x term varies along the first index axis
    # a quadratic field is in the span: least squares reproduces it exactly
    field = (0.3 * b[1] ** 2 - 0.2 * b[2] * b[3] + 0.1 * b[3]).flatten()
    coef = torch.linalg.lstsq(b.flatten(1).t(), field[:, None]).solution
    torch.testing.assert_close(b.flatten(1).t() @ coef[:, 0], field, atol=1e-10, rtol=0)


def test_gauss_newton_bias_terms_remove_the_pull_of_a_smooth_intensity_bias():
    """A moving image with cupping-like shading (a quadratic bias, here up to 30 % of the contrast): without bias
    terms the pose is pulled off; with ``bias_degree=2`` it is recovered; with no bias both agree."""
    grid = Grid.centered((32, 32, 32), (3.0, 3.0, 3.0), (0.0, 0.0, 0.0))
    fixed = _blobs(grid.size, seed=4, n=10)
    p = torch.tensor([[3.0, -2.0, 2.0, 2.0, -3.0, 3.0]], dtype=torch.float64)
    clean = _moving_for(fixed, p, grid)
    b = polynomial_basis(grid, 2, torch.float64)
    shading = 0.3 * (b[1] ** 2 + b[2] ** 2) - 0.15 * b[1] + 0.1 * b[3]
    init = torch.eye(4, dtype=torch.float64)[None]
    err = lambda m: (matrix_to_params_torch(m, grid.center()) - p).abs().max().item()  # noqa: E731
    biased = clean + shading[None, None]
    plain = gauss_newton_align(biased, fixed, grid, init, iterations=30)
    with_bias = gauss_newton_align(biased, fixed, grid, init, iterations=30, bias_degree=2)
    assert err(with_bias) < 0.2
    assert err(plain) > 3 * err(with_bias)
    # without shading the bias terms cost no accuracy
    assert err(gauss_newton_align(clean, fixed, grid, init, iterations=30, bias_degree=2)) < 0.2


@pytest.mark.parametrize("jacobian", ["moving", "symmetric"])
def test_gauss_newton_jacobian_variants_agree_on_equal_appearance(jacobian):
    """Images of equal appearance: gradients from the warped moving image (forward compositional) or the mean of
    both (symmetric) reach the known motion as the default (fixed image gradients) does."""
    grid = Grid.centered((32, 32, 32), (3.0, 3.0, 3.0), (0.0, 0.0, 0.0))
    fixed = _blobs(grid.size, seed=1)
    p = torch.tensor([[4.0, -3.0, 2.0, 3.0, -4.0, 5.0]], dtype=torch.float64)
    moving = _moving_for(fixed, p, grid)
    init = torch.eye(4, dtype=torch.float64)[None]
    est = gauss_newton_align(moving, fixed, grid, init, iterations=20, jacobian=jacobian)
    np.testing.assert_allclose(matrix_to_params_torch(est, grid.center())[0].numpy(), p[0].numpy(), atol=0.2)
    with pytest.raises(ValueError, match="jacobian"):
        gauss_newton_align(moving, fixed, grid, init, jacobian="mixed")


def test_gauss_newton_support_excludes_truncated_region():
    # moving truncated to a central box (zeros outside): with the support mask the motion is still found
    grid = Grid.centered((32, 32, 32), (3.0, 3.0, 3.0), (0.0, 0.0, 0.0))
    fixed = _blobs(grid.size, seed=2, n=14)
    p = torch.tensor([[5.0, -4.0, 3.0, 0.0, 0.0, 4.0]], dtype=torch.float64)
    moving = _moving_for(fixed, p, grid)
    support = torch.zeros_like(moving)
    support[..., 8:24, 8:24, 8:24] = 1.0
    moving = moving * support
    init = torch.eye(4, dtype=torch.float64)[None]
    with_support = gauss_newton_align(moving, fixed, grid, init, iterations=30, moving_support=support)
    without = gauss_newton_align(moving, fixed, grid, init, iterations=30)
    err = lambda m: (matrix_to_params_torch(m, grid.center()) - p).abs().max().item()  # noqa: E731
    assert err(with_support) < 0.3
    assert err(without) > 3 * err(with_support)


def test_gauss_newton_trust_region_and_empty_overlap():
    grid = Grid.centered((16, 16, 16), (4.0, 4.0, 4.0), (0.0, 0.0, 0.0))
    fixed = _blobs(grid.size, seed=7)
    moving = _moving_for(fixed, torch.tensor([[4.0, 0, 0, 0, 0, 0]], dtype=torch.float64), grid)
    init = torch.eye(4, dtype=torch.float64)[None]

    def step(limit):
        out = gauss_newton_align(moving, fixed, grid, init, iterations=1, max_step=limit)
        return matrix_to_params_torch(out, grid.center())[0]

    free, clamped = step((100.0, 100.0)), step((1.0, 100.0))
    assert free[0] > 2.0  # the solved step heads for the true +4 mm
    # the trust region (here 1 mm) scales the whole step down, keeping its direction
    np.testing.assert_allclose(clamped[0].item(), 1.0, atol=1e-3)
    assert (clamped.abs() <= free.abs() + 1e-6).all()
    np.testing.assert_allclose((clamped[3:] / clamped[0]).numpy(), (free[3:] / free[0]).numpy(), atol=1e-3)
    # (almost) no moving data: the estimate stays where it started instead of jumping
    support = torch.zeros_like(moving)
    support[..., 7:9, 7:9, 7:9] = 1.0
    out = gauss_newton_align(moving * support, fixed, grid, init, iterations=5, moving_support=support)
    assert torch.equal(out, init)


def test_gauss_newton_is_differentiable():
    grid = Grid.centered((16, 16, 16), (4.0, 4.0, 4.0), (0.0, 0.0, 0.0))
    fixed = _blobs(grid.size, seed=4).float().requires_grad_(True)
    moving = _moving_for(fixed.detach().double(), torch.tensor([[3.0, 0, 0, 0, 0, 2.0]], dtype=torch.float64),
                         grid).float().requires_grad_(True)
    out = gauss_newton_align(moving, fixed, grid, torch.eye(4, dtype=torch.float64)[None], iterations=2)
    out[:, :3, 3].sum().backward()
    assert moving.grad is not None and moving.grad.abs().sum() > 0
    assert fixed.grad is not None and fixed.grad.abs().sum() > 0


def test_untrained_network_with_alignment_stage_registers_and_trains():
    # the fine stage has no trainable weights: an untrained network (identity regression) already aligns
    # compact blobs (background at the grid edges): the local-contrast features see no border-padding artefacts
    grid = Grid.centered((32, 32, 32), (4.0, 4.0, 4.0), (0.0, 0.0, 0.0))
    fixed = _blobs(grid.size, seed=5, n=12, spread=0.4, sharp=3.0)
    p = torch.tensor([[5.0, -3.0, 2.0, 2.0, -3.0, 4.0]], dtype=torch.float64)
    moving = _moving_for(fixed, p, grid)
    net = TwoStageRigidNet(DualEncoderRigidNet(**TINY), GaussNewtonStage(grid.spacing, iterations=(5, 5, 5)))
    with torch.no_grad():
        stages = net.forward_stages(moving.float(), fixed.float())
    assert torch.allclose(stages["coarse"], torch.zeros(1, 6))  # zero-initialised head: identity start
    np.testing.assert_allclose(stages["params"][0].numpy(), p[0].numpy(), atol=0.2)
    assert torch.equal(net(torch.cat([moving, fixed], 1).float()), stages["params"])  # bundle form: the final one
    # one training step through the criterion, given the stage estimates as the prediction: the coarse term is
    # logged and every stage receives gradients
    crit = RegistrationCriterion((32, 32, 32), grid.spacing, RigidRegistrationLoss(w_ssim=0, w_ncc=0, w_mi=0,
                                 w_sup=1.0), w_coarse=0.5)
    pred = net(torch.cat([moving, fixed], 1).float(), stages=True)
    loss = crit(pred, {"moving": moving.float(), "fixed": fixed.float(), "params": p.float()})
    loss.backward()
    assert crit.last_terms["coarse"] > 5.0  # identity start: the regression is several mm off
    assert net.regression.head.weight.grad.abs().sum() > 0
    # the fine stage alone, and without levels: the start comes back unchanged
    start = torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]])
    out, from_start = GaussNewtonStage(grid.spacing, iterations=(0, 0, 0))(moving.float(), fixed.float(), start)
    torch.testing.assert_close(out, start, atol=1e-5, rtol=0)
    assert from_start.tolist() == [True]
    with pytest.raises(ValueError, match="differ in length"):
        GaussNewtonStage(grid.spacing, iterations=(1, 2), levels=(4, 2, 1))


def test_regression_alone_is_the_switched_off_two_stage_net():
    """``fine_stage_enabled=False`` (the bundle's ``fine_stage: false``) returns the regression's own estimate."""
    grid = Grid.centered((32, 32, 32), (4.0, 4.0, 4.0), (0.0, 0.0, 0.0))
    fixed = _blobs(grid.size, seed=5, n=12, spread=0.4, sharp=3.0).float()
    moving = _moving_for(fixed.double(), torch.tensor([[5.0, -3.0, 2.0, 2.0, -3.0, 4.0]], dtype=torch.float64),
                         grid).float()
    torch.manual_seed(0)
    reg = DualEncoderRigidNet(**TINY)
    torch.nn.init.normal_(reg.head.weight, std=0.05)  # a regression that does not say "identity"
    both = TwoStageRigidNet(reg, GaussNewtonStage(grid.spacing, iterations=(5, 5, 5))).eval()
    alone = TwoStageRigidNet(reg, GaussNewtonStage(grid.spacing), fine_stage_enabled=False).eval()
    with torch.no_grad():
        coarse = reg.forward_pair(moving, fixed)
        assert torch.equal(alone.forward_pair(moving, fixed), coarse)
        assert not torch.allclose(both.forward_pair(moving, fixed), coarse, atol=0.1)


def test_two_stage_net_loads_flat_regression_checkpoints():
    """Bundle 0.2.x checkpoints hold the regression's keys without the ``regression.`` prefix."""
    torch.manual_seed(1)
    src = DualEncoderRigidNet(**TINY)
    net = TwoStageRigidNet(DualEncoderRigidNet(**TINY), GaussNewtonStage((4.0, 4.0, 4.0)))
    net.load_state_dict(src.state_dict())  # flat keys
    for key, value in src.state_dict().items():
        assert torch.equal(net.state_dict()[f"regression.{key}"], value)
    again = TwoStageRigidNet(DualEncoderRigidNet(**TINY), GaussNewtonStage((4.0, 4.0, 4.0)))
    again.load_state_dict(net.state_dict())  # prefixed keys (what training saves now)
    assert all(torch.equal(v, again.state_dict()[k]) for k, v in net.state_dict().items())
    with pytest.raises(RuntimeError, match="Missing key"):
        net.load_state_dict({k: v for k, v in src.state_dict().items() if not k.startswith("head")})


def test_network_jacobian_per_level_and_its_length_check():
    """``jacobian`` per pyramid level: symmetric steps on the last level end where the default does on a clean
    pair, near the known motion; a list of the wrong length is refused."""
    grid = Grid.centered((32, 32, 32), (3.0, 3.0, 3.0), (0.0, 0.0, 0.0))
    fixed = _blobs(grid.size, seed=1).float()
    p = torch.tensor([[4.0, -3.0, 2.0, 3.0, -4.0, 5.0]])
    moving = _moving_for(fixed.double(), p.double(), grid).float()
    kw = dict(iterations=(10, 10), levels=(2, 1), support_threshold=-1.0)
    ests = []
    for jac in ("fixed", ("fixed", "symmetric")):
        net = TwoStageRigidNet(DualEncoderRigidNet(**TINY), GaussNewtonStage(grid.spacing, **kw, jacobian=jac)).eval()
        with torch.no_grad():
            ests.append(net.forward_pair(moving, fixed)[0].numpy())
        np.testing.assert_allclose(ests[-1], p[0].numpy(), atol=1.0)  # the fixed features' own precision here
    np.testing.assert_allclose(ests[1], ests[0], atol=0.3)
    with pytest.raises(ValueError, match="one entry per level"):
        GaussNewtonStage(grid.spacing, **kw, jacobian=("fixed", "fixed", "symmetric"))
    with pytest.raises(ValueError, match="jacobian must be one of"):
        GaussNewtonStage(grid.spacing, **kw, jacobian="sideways")


def test_scripting_the_two_stage_net_fails_loudly_with_the_way_out():
    """``torch.jit.script`` (``ckpt_export`` without ``--use_trace``) refuses with what to do; the regression alone
    scripts (the traced export of the whole network is tests/test_bundle.py's)."""
    net = TwoStageRigidNet(DualEncoderRigidNet(**TINY), GaussNewtonStage((4.0, 4.0, 4.0))).eval()
    with pytest.raises(RuntimeError, match="Export it by tracing"):
        torch.jit.script(net)
    scripted = torch.jit.script(net.regression)
    x = torch.rand(1, 2, 16, 16, 16)
    torch.testing.assert_close(scripted(x), net.regression(x))


def _low_contrast_pair(gain: float = 0.35):
    """A moving image whose contrast is ``gain`` times the fixed image's (as a blurred, noisy CBCT's features are):
    the fixed-image Jacobian over-estimates the curvature and every plain step covers about ``gain`` of the error."""
    grid = Grid.centered((32, 32, 32), (3.0, 3.0, 3.0), (0.0, 0.0, 0.0))
    fixed = _blobs(grid.size, seed=2)
    p = torch.tensor([[3.0, -2.0, 2.5, 2.0, -3.0, 2.5]], dtype=torch.float64)
    moving = gain * _moving_for(fixed, p, grid)
    return grid, fixed, moving, p


def test_secant_steps_reach_the_same_fixed_point_in_fewer_steps():
    grid, fixed, moving, p = _low_contrast_pair()
    init = torch.eye(4, dtype=torch.float64)[None]
    params = lambda m: matrix_to_params_torch(m, grid.center())  # noqa: E731
    # plain steps contract by about 1 - gain per step; after 80 they sit at the least-squares fixed point (which
    # the contrast mismatch moves a little off the known motion)
    converged = params(gauss_newton_align(moving, fixed, grid, init, iterations=80))
    assert (converged - p).abs().max() < 0.5
    dist = lambda m: (params(m) - converged).abs().max().item()  # noqa: E731
    assert dist(gauss_newton_align(moving, fixed, grid, init, iterations=4)) > 0.3
    # secant-scaled steps: at that fixed point in 4 steps
    assert dist(gauss_newton_align(moving, fixed, grid, init, iterations=4, secant=True)) < 0.05
    # equal contrast: the secant gain stays near 1 and costs nothing
    grid, fixed, moving, p = _low_contrast_pair(gain=1.0)
    assert (params(gauss_newton_align(moving, fixed, grid, init, iterations=6, secant=True)) - p).abs().max() < 0.1


def test_tolerance_stops_once_the_steps_are_small(monkeypatch):
    import monai_rigidreg.networks.gauss_newton as gn

    grid, fixed, moving, p = _low_contrast_pair(gain=1.0)
    init = torch.eye(4, dtype=torch.float64)[None]
    calls = []
    real_warp = gn.warp_volume
    monkeypatch.setattr(gn, "warp_volume", lambda *a, **k: calls.append(1) or real_warp(*a, **k))
    full = gauss_newton_align(moving, fixed, grid, init, iterations=40)
    assert len(calls) == 40
    calls.clear()
    early = gauss_newton_align(moving, fixed, grid, init, iterations=40, tolerance=(0.01, 0.01))
    assert 2 <= len(calls) < 20  # stopped long before 40 steps
    diff = (matrix_to_params_torch(early, grid.center()) - matrix_to_params_torch(full, grid.center())).abs()
    assert diff.max().item() < 0.02


def test_stage_applies_tolerance_and_secant_at_inference_only():
    grid, fixed, moving, p = _low_contrast_pair()
    start = torch.zeros(1, 6, dtype=torch.float64)
    plain = GaussNewtonStage((3.0, 3.0, 3.0), iterations=(3,), levels=(1,), highpass_weight=0.0)
    fast = GaussNewtonStage((3.0, 3.0, 3.0), iterations=(3,), levels=(1,), highpass_weight=0.0, secant=True,
                            tolerance=(0.01, 0.01))
    assert "secant=True" in repr(fast)
    with torch.no_grad():
        a, _ = plain(moving, fixed, start)
        b, _ = fast(moving, fixed, start)
    assert (b - p).abs().max() < 0.7 * (a - p).abs().max()  # secant steps got closer in the same 3 steps
    with torch.enable_grad():  # training: the same plain steps, whatever the settings
        c, _ = fast(moving.clone().requires_grad_(True), fixed, start)
    torch.testing.assert_close(c.detach(), a)
    for bad in [(0.0, 0.01), (0.01,), (0.01, 0.01, 0.01)]:
        with pytest.raises(ValueError, match="tolerance"):
            GaussNewtonStage((3.0, 3.0, 3.0), tolerance=bad)


def test_jacobian_at_some_voxels_is_the_dense_one_there():
    direction = rotation_matrix(*np.deg2rad([-25.0, 5.0, 40.0])).ravel()
    grid = Grid((14, 11, 9), (1.2, 2.5, 1.7), (-30.0, 12.0, 80.0), tuple(direction))
    fixed = torch.rand(1, 2, *grid.size, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    index = torch.tensor([0, 5, 99, 500, 1385])  # first and last voxel included
    dense = fixed_jacobian(fixed, grid).flatten(3)[..., index]
    at = fixed_jacobian(fixed, grid, index)
    assert at.shape == (1, 6, 2, 5)
    torch.testing.assert_close(at, dense, rtol=1e-12, atol=1e-12)


def _truncated_pair(params):
    """A blob volume, its moving twin under ``params`` truncated to a cylinder-like box (the CBCT's field of view),
    that field of view, the support eroded from it by 3 voxels, and a weight that is zero on one side."""
    grid = Grid.centered((36, 34, 30), (2.0, 2.0, 2.0), (5.0, -3.0, 2.0))
    fixed = _blobs(grid.size, seed=4, n=16, sharp=2.0).float()
    moving = _moving_for(fixed.double(), torch.tensor([params], dtype=torch.float64), grid).float()
    fov = torch.zeros_like(moving)
    fov[..., 4:32, 5:30, 3:27] = 1.0
    moving = moving * fov
    radius = [3, 3, 3]
    weight = torch.ones_like(fixed)
    weight[..., :8] = 0.0
    weight[..., 8:12] = 0.5
    return grid, fixed, moving, fov, erode(fov, radius), radius, weight


def test_gauss_newton_over_the_candidate_voxels_takes_the_dense_steps(monkeypatch):
    # the last level's candidates (support_reach: the field of view where the weight is positive): the same estimate
    # as over the whole grid, computed at about half the voxels; beyond reach_mm the remaining steps use the whole grid
    params = [1.2, -0.8, 0.6, 0.8, -0.5, 0.7]
    grid, fixed, moving, fov, support, radius, weight = _truncated_pair(params)
    init = torch.eye(4, dtype=torch.float64)[None]
    kwargs = dict(iterations=4, weight=weight, moving_support=support, bias_degree=1)
    dense = gauss_newton_align(moving, fixed, grid, init, **kwargs)
    err = (matrix_to_params_torch(dense, grid.center())[0] - torch.tensor(params, dtype=torch.float64)).abs().max()
    assert err < 0.3  # from 1.2 mm / 0.8 degrees (the truncated blobs' own fixed point is 0.2 degrees off)
    cand, reach = support_reach(fov, radius, grid.spacing, weight)
    assert reach == 7.0  # (3 + 1/2) voxels of 2 mm
    assert 0.3 < cand.float().mean() < 0.8
    calls = {"points": 0, "volume": 0}
    for name, function in (("points", "sample_normalized"), ("volume", "warp_volume")):
        real = getattr(gauss_newton_module, function)

        def counted(*a, _real=real, _name=name, **k):
            calls[_name] += 1
            return _real(*a, **k)
        monkeypatch.setattr(gauss_newton_module, function, counted)
    subset = gauss_newton_align(moving, fixed, grid, init, candidates=cand, reach_mm=reach, **kwargs)
    assert calls == {"points": 4, "volume": 0}
    torch.testing.assert_close(subset, dense, atol=1e-5, rtol=0)
    # a reach of 1e-9 mm: the first step over the candidates, the estimate then leaves the reach and the whole grid
    # takes over
    calls.update(points=0, volume=0)
    fallback = gauss_newton_align(moving, fixed, grid, init, candidates=cand, reach_mm=1e-9, **kwargs)
    assert calls == {"points": 1, "volume": 3}
    torch.testing.assert_close(fallback, dense, atol=1e-5, rtol=0)
    # the candidates are what the steps use: missing voxels that carry weight change the estimate
    half = cand.clone()
    half[..., 18:] = False
    partial = gauss_newton_align(moving, fixed, grid, init, candidates=half, reach_mm=reach, **kwargs)
    assert (partial - dense).abs().max() > 1e-3
    with pytest.raises(ValueError, match="one case"):
        gauss_newton_align(moving.repeat(2, 1, 1, 1, 1), fixed.repeat(2, 1, 1, 1, 1), grid, init.repeat(2, 1, 1),
                           candidates=cand)
    with pytest.raises(ValueError, match="jacobian"):
        gauss_newton_align(moving, fixed, grid, init, candidates=cand, jacobian="symmetric")


def test_alignment_features_default_channels_are_the_intensity_and_its_local_contrast():
    from monai_rigidreg.core.image_ops import local_mean
    from monai_rigidreg.networks.alignment_features import alignment_features

    grid = Grid.centered((24, 24, 24), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    vol = _blobs(grid.size, seed=2, n=12, sharp=4.0)
    feats = alignment_features(vol, grid.spacing, highpass_sigma_mm=8.0, highpass_weight=3.0)
    mask = (vol > 1e-3).to(vol.dtype)
    expected = 3.0 * (vol - local_mean(vol, mask, [4.0] * 3)) * mask
    assert feats.shape == (1, 2, *grid.size)
    torch.testing.assert_close(feats[:, :1], vol)
    torch.testing.assert_close(feats[:, 1:], expected)
    assert alignment_features(vol, grid.spacing, intensity_weight=0.0).shape == (1, 1, *grid.size)


def test_normalised_local_contrast_ignores_the_contrast_gain():
    """Normalised by its own strength, the local contrast of twice the contrast is the same map (the plain one
    doubles), and its strength is :data:`CONTRAST_NORM_SCALE` wherever there is contrast."""
    from monai_rigidreg.core.image_ops import local_mean
    from monai_rigidreg.networks.alignment_features import CONTRAST_NORM_SCALE, alignment_features

    grid = Grid.centered((32, 32, 32), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    vol = 0.2 + 0.5 * _blobs(grid.size, seed=3, n=40, sharp=8.0, spread=0.8)  # all of it holds data
    kw = {"highpass_sigma_mm": 8.0, "highpass_weight": 1.0, "intensity_weight": 0.0}
    plain = [alignment_features(v, grid.spacing, **kw) for v in (vol, 0.2 + 2 * (vol - 0.2))]
    norm = [alignment_features(v, grid.spacing, contrast_norm_sigma_mm=12.0, **kw)
            for v in (vol, 0.2 + 2 * (vol - 0.2))]
    torch.testing.assert_close(plain[1], 2 * plain[0])
    inner = (slice(None), slice(None)) + (slice(6, -6),) * 3  # away from the grid's edges
    strong = local_mean(plain[0] ** 2, torch.ones_like(vol), [6.0] * 3)[inner] > 4e-4  # contrast above the floor
    assert (norm[1] - norm[0])[inner][strong].abs().max() < 0.1 * CONTRAST_NORM_SCALE
    rms = local_mean(norm[0] ** 2, torch.ones_like(vol), [6.0] * 3)[inner][strong].sqrt()
    assert rms.median() == pytest.approx(CONTRAST_NORM_SCALE, rel=0.25)


def test_normalised_local_contrast_is_pulled_less_by_a_contrast_gain_across_the_image():
    """A moving image whose contrast rises by 40 % from one side to the other (scatter shading of a large body):
    Gauss-Newton on the normalised local contrast ends nearer the truth than on the plain features, and both
    recover a clean pair."""
    from monai_rigidreg.networks.alignment_features import alignment_features

    grid = Grid.centered((40, 40, 40), (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))
    fixed = _blobs(grid.size, seed=4, n=60, sharp=20.0, spread=0.8)
    p = torch.tensor([[3.0, -2.0, 2.0, 2.0, -3.0, 3.0]], dtype=torch.float64)
    clean = _moving_for(fixed, p, grid)
    shaded = clean * (1.0 + 0.4 * polynomial_basis(grid, 1, torch.float64)[2])[None, None]
    init = torch.eye(4, dtype=torch.float64)[None]

    def error(moving: torch.Tensor, **kw) -> float:
        f = [alignment_features(v, grid.spacing, highpass_sigma_mm=16.0, **kw) for v in (moving, fixed)]
        m = gauss_newton_align(f[0], f[1], grid, init, iterations=30)
        return (matrix_to_params_torch(m, grid.center()) - p).abs().max().item()

    norm = {"contrast_norm_sigma_mm": 12.0, "intensity_weight": 0.0}
    assert error(clean) < 0.03 and error(clean, **norm) < 0.03
    assert error(shaded, **norm) < 0.8 * error(shaded)
