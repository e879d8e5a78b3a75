"""Tests of monai_rigidreg.networks: DualEncoderRigidNet, RigidTransformer, cascade_register, smoke training."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from monai_rigidreg.core.geometry import Grid, matrix_to_params, params_to_matrix, params_to_sitk
from monai_rigidreg.core.warp import warp_volume
from monai_rigidreg.losses import RigidRegistrationLoss
from monai_rigidreg.networks import (
    FUSIONS,
    CascadeRegistration,
    DualEncoderRigidNet,
    RigidTransformer,
    cascade_register,
)
from monai_rigidreg.simulation.toy import phantom_pair_batch, random_params

TINY = {"channels": (4, 8, 8), "strides": (2, 2, 2), "pool_size": 2, "hidden": (16,)}


def _randomize_head(net: DualEncoderRigidNet, scale: float = 1.0, seed: int = 0) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        net.head.weight.copy_(torch.randn(net.head.weight.shape, generator=g) * scale)
        net.head.bias.copy_(torch.randn(net.head.bias.shape, generator=g) * scale)


def _to_sitk(vol: np.ndarray, grid: Grid) -> sitk.Image:
    """``[x, y, z]`` array on ``grid`` -> SimpleITK image."""
    return grid.apply_to(sitk.GetImageFromArray(np.ascontiguousarray(vol.transpose(2, 1, 0))))


def _from_sitk(img: sitk.Image) -> np.ndarray:
    return sitk.GetArrayFromImage(img).transpose(2, 1, 0)


def _smooth_volume(size: tuple[int, int, int], seed: int = 0, sigma: float = 1.5) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = sitk.SmoothingRecursiveGaussian(sitk.GetImageFromArray(rng.normal(size=size[::-1])), sigma)
    arr = _from_sitk(img)
    return ((arr - arr.min()) / (arr.max() - arr.min())).astype(np.float64)


# ---------------------------------------------------------------------------------------------------------------
# DualEncoderRigidNet
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fusion", FUSIONS)
def test_net_shape_dtype_device(fusion, device_dtype):
    device, dtype = device_dtype
    net = DualEncoderRigidNet(fusion=fusion, **TINY).to(device=device, dtype=dtype)
    x = torch.rand(2, 2, 16, 20, 24, device=device, dtype=dtype)
    out = net(x)
    assert out.shape == (2, 6) and out.dtype == dtype and out.device.type == device.type
    assert net.forward_pair(x[:, :1], x[:, 1:]).shape == (2, 6)


@pytest.mark.parametrize("fusion", FUSIONS)
def test_net_identity_at_init(fusion):
    torch.manual_seed(0)
    net = DualEncoderRigidNet(fusion=fusion, **TINY)
    out = net(torch.rand(3, 2, 16, 16, 16))
    assert torch.equal(out, torch.zeros(3, 6))


def test_net_bounds_for_huge_inputs():
    net = DualEncoderRigidNet(max_translation=12.0, max_rotation=7.0, norm="BATCH", **TINY).eval()
    _randomize_head(net, scale=1e4)
    out = net(torch.randn(4, 2, 16, 16, 16) * 1e6)
    assert torch.isfinite(out).all()
    assert (out[:, :3].abs() <= 12.0).all() and (out[:, 3:].abs() <= 7.0).all()
    assert out.abs().max() > 6.0  # saturated, not trivially small


def test_net_forward_pair_matches_forward():
    net = DualEncoderRigidNet(**TINY).eval()
    _randomize_head(net, 0.1)
    m, f = torch.rand(2, 1, 16, 16, 16), torch.rand(2, 1, 16, 16, 16)
    assert torch.allclose(net(torch.cat([m, f], 1)), net.forward_pair(m, f))
    assert not torch.allclose(net.forward_pair(m, f), net.forward_pair(f, m))  # order matters


@pytest.mark.parametrize("fusion", FUSIONS)
def test_net_torchscript(fusion):
    net = DualEncoderRigidNet(fusion=fusion, **TINY).eval()
    _randomize_head(net, 0.1)
    scripted = torch.jit.script(net)
    x = torch.rand(2, 2, 16, 16, 16)
    with torch.no_grad():
        ref, out = net(x), scripted(x)
        out_pair = scripted.forward_pair(x[:, :1], x[:, 1:])
    assert ref.abs().max() > 0
    assert torch.allclose(ref, out, atol=1e-6) and torch.allclose(ref, out_pair, atol=1e-6)


def test_net_invalid_arguments():
    with pytest.raises(ValueError):
        DualEncoderRigidNet(fusion="attention")
    with pytest.raises(ValueError):
        DualEncoderRigidNet(channels=(4, 8), strides=(2,))
    net = DualEncoderRigidNet(**TINY)
    with pytest.raises(ValueError):
        net(torch.rand(1, 3, 16, 16, 16))


# ---------------------------------------------------------------------------------------------------------------
# RigidTransformer: pinned conventions
# ---------------------------------------------------------------------------------------------------------------
def test_transformer_identity_exact():
    grid = Grid.centered((10, 12, 14), (2.0, 1.5, 3.0), (5.0, -3.0, 7.0))
    vol = torch.rand(2, 3, 10, 12, 14, dtype=torch.float64)
    out = RigidTransformer(grid)(vol, torch.zeros(2, 6, dtype=torch.float64))
    assert torch.allclose(out, vol, atol=1e-12)


def test_transformer_voxel_and_mm_shift():
    """tx = +s mm gives out(x) = moving(x + s e_x) (content moves by -s along LPS x), as SimpleITK."""
    spacing = 2.0
    grid = Grid.centered((12, 10, 8), (spacing, spacing, spacing), (1.0, 2.0, 3.0))
    phys_x = torch.as_tensor(grid.origin[0] + spacing * np.arange(12), dtype=torch.float64)
    ramp = phys_x.view(1, 1, 12, 1, 1).expand(1, 1, 12, 10, 8).contiguous()  # value = LPS x in mm
    tr = RigidTransformer(grid)
    for s in (spacing, 1.0):  # a 1-voxel shift (2 mm) and a 1-mm shift (half voxel)
        out = tr(ramp, torch.tensor([[s, 0, 0, 0, 0, 0]], dtype=torch.float64))
        assert torch.allclose(out[0, 0, :-1], ramp[0, 0, :-1] + s, atol=1e-9)
        ref = _from_sitk(
            sitk.Resample(
                _to_sitk(ramp[0, 0].numpy(), grid),
                _to_sitk(ramp[0, 0].numpy(), grid),
                params_to_sitk([s, 0, 0, 0, 0, 0], grid.center()),
                sitk.sitkLinear,
                0.0,
            )
        )
        assert np.allclose(out[0, 0, :-1].numpy(), ref[:-1], atol=1e-6)
    # 1-voxel shift along y moves a marker by exactly one voxel towards -y
    vol = torch.zeros(1, 1, 12, 10, 8, dtype=torch.float64)
    vol[0, 0, 5, 6, 4] = 1.0
    out = tr(vol, torch.tensor([[0, spacing, 0, 0, 0, 0]], dtype=torch.float64))
    assert out[0, 0, 5, 5, 4] == pytest.approx(1.0) and out.sum() == pytest.approx(1.0)


def test_transformer_rotation_90_about_z():
    """rz = +90 deg: an anterior (-y, LPS) marker of the moving image appears at the patient's right (-x)."""
    grid = Grid.centered((21, 21, 5), (2.0, 2.0, 2.0), (10.0, -20.0, 5.0))
    c = grid.center()
    d = 12.0  # mm = 6 voxels
    marker = c + np.array([0.0, -d, 0.0])  # anterior of the centre
    idx = np.round(grid.physical_to_index() @ np.append(marker, 1.0))[:3].astype(int)
    vol = torch.zeros(1, 1, 21, 21, 5, dtype=torch.float64)
    vol[0, 0, idx[0], idx[1], idx[2]] = 1.0
    params = [0, 0, 0, 0, 0, 90.0]
    out = RigidTransformer(grid)(vol, torch.tensor([params], dtype=torch.float64))
    found = np.unravel_index(int(out.argmax()), out.shape[2:])
    found_phys = (grid.index_to_physical() @ np.append(np.asarray(found, dtype=float), 1.0))[:3]
    # out(x) = moving(T(x)): the marker shows where T(x) = marker, i.e. x = T^{-1}(marker)
    expected = np.asarray(params_to_sitk(params, c).GetInverse().TransformPoint(marker.tolist()))
    assert np.allclose(found_phys, expected, atol=1e-6)
    assert np.allclose(found_phys, c + np.array([-d, 0.0, 0.0]), atol=1e-6)  # patient right
    assert float(out.max()) == pytest.approx(1.0, abs=1e-9)


def test_transformer_matches_sitk_resample():
    fixed_grid = Grid.centered((20, 18, 16), (2.0, 2.5, 3.0), (3.0, -4.0, 10.0))
    moving_grid = Grid.centered((26, 22, 20), (1.8, 2.2, 2.6), (5.0, -2.0, 8.0))
    mov = _smooth_volume(moving_grid.size, seed=1)
    params = [3.0, -2.5, 4.0, 5.0, -7.0, 9.0]
    ref = _from_sitk(
        sitk.Resample(
            _to_sitk(mov, moving_grid),
            fixed_grid.to_sitk(sitk.sitkFloat64),
            params_to_sitk(params, fixed_grid.center()),
            sitk.sitkLinear,
            0.0,
        )
    )
    tr = RigidTransformer(fixed_grid, moving_grid)
    out = tr(torch.as_tensor(mov)[None, None], torch.tensor([params], dtype=torch.float64))[0, 0].numpy()
    inner = (slice(3, -3),) * 3
    assert np.abs(out[inner] - ref[inner]).max() < 1e-6
    # float32 path: same within single-precision interpolation error
    out32 = tr(torch.as_tensor(mov, dtype=torch.float32)[None, None], torch.tensor([params]))[0, 0].numpy()
    assert np.abs(out32[inner] - ref[inner]).max() < 1e-4


def test_transformer_gradcheck():
    grid = Grid.centered((5, 6, 4), (2.0, 1.5, 2.5))
    vol = torch.as_tensor(_smooth_volume((5, 6, 4), seed=2, sigma=1.0))[None, None]
    tr = RigidTransformer(grid)
    params = torch.tensor([[0.31, -0.27, 0.13, 2.1, -3.3, 4.7]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p: tr(vol, p), (params,), eps=1e-6, atol=1e-5)


# ---------------------------------------------------------------------------------------------------------------
# Cascade
# ---------------------------------------------------------------------------------------------------------------
class _ScriptedNet(torch.nn.Module):
    """Returns the given parameters in turn and records its inputs."""

    def __init__(self, outputs):
        super().__init__()
        self.outputs = list(outputs)
        self.inputs = []

    def forward_pair(self, moving, fixed):
        self.inputs.append(moving.detach().clone())
        return self.outputs[len(self.inputs) - 1].to(moving.dtype)


def test_cascade_composition_exact():
    grid = Grid.centered((24, 24, 24), (4.0, 4.0, 4.0), (5.0, -10.0, 20.0))
    c = grid.center()
    true = np.array([6.0, -4.0, 3.0, 5.0, -4.0, 8.0])
    first = np.array([3.0, -1.0, 1.0, 2.0, -1.0, 3.0])  # a partial estimate
    correction = matrix_to_params(np.linalg.inv(params_to_matrix(first, c)) @ params_to_matrix(true, c), c)
    g = torch.Generator().manual_seed(0)
    moving, fixed = phantom_pair_batch(grid, torch.as_tensor(true)[None], g)
    net = _ScriptedNet([torch.as_tensor(first)[None], torch.as_tensor(correction)[None]])
    out, hist = cascade_register(net, moving, fixed, grid, steps=2, return_all=True)
    assert np.allclose(out[0].numpy(), true, atol=1e-4)  # total = T o C, exactly (float32 output)
    assert np.allclose(hist[0][0].numpy(), first, atol=1e-5)
    # the second call saw the original moving image warped by the first estimate
    expected_w = warp_volume(moving, torch.as_tensor(params_to_matrix(first, c))[None], grid, grid)
    assert torch.allclose(net.inputs[1], expected_w)
    # and the composed transform aligns the pair better than the first estimate
    inner = (slice(None), slice(None)) + (slice(4, -4),) * 3
    err_first = (net.inputs[1] - fixed)[inner].abs().mean()
    err_total = (warp_volume(moving, torch.as_tensor(params_to_matrix(true, c))[None], grid, grid) - fixed)[inner]
    assert err_total.abs().mean() < 0.3 * err_first


def test_cascade_module_and_real_net():
    grid = Grid.centered((16, 16, 16), (4.0, 4.0, 4.0))
    net = DualEncoderRigidNet(**TINY).eval()
    _randomize_head(net, 0.05)
    x = torch.rand(2, 2, 16, 16, 16)
    with torch.no_grad():
        one = cascade_register(net, x[:, :1], x[:, 1:], grid, steps=1)
        three = CascadeRegistration(net, grid, steps=3)(x)
    assert torch.allclose(one, net(x))
    assert three.shape == (2, 6) and torch.isfinite(three).all()
    with pytest.raises(ValueError):
        cascade_register(net, x[:, :1], x[:, 1:], grid, steps=0)


# ---------------------------------------------------------------------------------------------------------------
# Smoke training
# ---------------------------------------------------------------------------------------------------------------
def test_smoke_training_translation():
    """24^3 phantom pairs, translations only (+-10 mm): loss falls, translation error at least halves."""
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    grid = Grid.centered((24, 24, 24), (4.0, 4.0, 4.0))
    gv = torch.Generator().manual_seed(1)
    p_val = random_params(8, gv)
    p_val[:, 3:] = 0
    m_val, f_val = phantom_pair_batch(grid, p_val, gv)
    net = DualEncoderRigidNet(channels=(8, 16, 32), strides=(2, 2, 2), pool_size=3, hidden=(64,))
    warp = RigidTransformer(grid)
    loss_fn = RigidRegistrationLoss(w_sup=1.0)
    steps = 40
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0 - s / steps)

    def val_error() -> float:
        net.eval()
        with torch.no_grad():
            pred = net.forward_pair(m_val, f_val)
        net.train()
        return float((pred[:, :3] - p_val[:, :3]).abs().mean())

    err0 = val_error()
    losses = []
    for _ in range(steps):
        p = random_params(4, g)
        p[:, 3:] = 0
        moving, fixed = phantom_pair_batch(grid, p, g)
        pred = net.forward_pair(moving, fixed)
        terms = loss_fn(warp(moving, pred), fixed, pred, p, grid=grid)
        opt.zero_grad()
        terms.total.backward()
        opt.step()
        sched.step()
        losses.append(float(terms.total.detach()))
    err1 = val_error()
    assert np.mean(losses[-10:]) < 0.7 * np.mean(losses[:10])
    assert err1 < 0.5 * err0, (err0, err1)
