"""CorrelationRigidNet and its parts: the cost volume, the closed-form rigid fit, levels, the isocentre crop."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from monai.data import MetaTensor

from monai_rigidreg.core.geometry import Grid, matrix_to_params_torch, params_to_matrix_torch
from monai_rigidreg.core.warp import warp_volume
from monai_rigidreg.engine import RegistrationCriterion
from monai_rigidreg.engine.data import registration_transforms
from monai_rigidreg.networks import (
    CorrelationRigidNet,
    GaussNewtonStage,
    TwoStageRigidNet,
    local_cost_volume,
    unit_channels,
    weighted_rigid_fit,
)
from monai_rigidreg.networks.correlation_net import _MatchLevel, parabola_shifts
from monai_rigidreg.transforms import RandIsocenterCropd


def test_rigid_fit_recovers_transform_and_ignores_zero_weight_outliers():
    g = torch.Generator().manual_seed(0)
    p = torch.randn(2, 200, 3, generator=g, dtype=torch.float64) * 40
    truth = torch.tensor([[5.0, -3.0, 10.0, 20.0, -10.0, 25.0], [-30.0, 12.0, 0.5, -28.0, 29.0, 2.0]],
                         dtype=torch.float64)
    t = params_to_matrix_torch(truth)
    q = (t[:, :3, :3] @ p.transpose(1, 2)).transpose(1, 2) + t[:, None, :3, 3]
    w = torch.ones(2, 200, dtype=torch.float64)
    q[:, :20] += 50.0  # outliers ...
    w[:, :20] = 0.0  # ... with no weight
    fit = weighted_rigid_fit(p, q, w, prior=0.0)
    assert torch.allclose(matrix_to_params_torch(fit), truth, atol=1e-6)
    # the same outliers with full weight pull the fit away (the weights matter)
    bad = weighted_rigid_fit(p, q, torch.ones_like(w), prior=0.0)
    assert (matrix_to_params_torch(bad) - truth).abs().max() > 1.0


def test_rigid_fit_gradient_is_finite_at_identity():
    p = torch.randn(1, 64, 3, dtype=torch.float64) * 30
    q = p.clone().requires_grad_(True)
    fit = weighted_rigid_fit(p, q, torch.ones(1, 64, dtype=torch.float64))
    matrix_to_params_torch(fit).sum().backward()
    assert torch.isfinite(q.grad).all()


def test_local_cost_volume_peaks_at_the_shift_with_its_sign():
    fm = torch.randn(1, 8, 6, 6, 6, generator=torch.Generator().manual_seed(1))
    ff = torch.roll(fm, shifts=(1, -2, 0), dims=(2, 3, 4))  # fixed[n] = moving[n - (1, -2, 0)]
    cv = local_cost_volume(fm, ff, 2)
    assert cv.shape == (1, 125, 6, 6, 6)
    idx = int(cv[0, :, 3, 3, 3].argmax())
    assert (idx // 25 - 2, (idx // 5) % 5 - 2, idx % 5 - 2) == (-1, 2, 0)
    assert float(cv[0, idx, 3, 3, 3]) == pytest.approx(1.0, abs=1e-5)


def test_local_cost_volume_is_the_cosine_with_each_shifted_cell():
    # every entry against its definition, on a batch of two anisotropic maps: a transposed axis, a shift of the
    # wrong sign or a border that is not zero fails it
    g = torch.Generator().manual_seed(4)
    fm, ff = torch.randn(2, 5, 4, 6, 3, generator=g), torch.randn(2, 5, 4, 6, 3, generator=g)
    r, k = 1, 3
    cv = local_cost_volume(fm, ff, r)
    assert cv.shape == (2, k**3, 4, 6, 3)
    un, uf = torch.nn.functional.normalize(fm, dim=1), torch.nn.functional.normalize(ff, dim=1)
    want = torch.zeros_like(cv)
    for i, (dx, dy, dz) in enumerate((a, b, c) for a in range(-r, r + 1) for b in range(-r, r + 1)
                                     for c in range(-r, r + 1)):
        for x in range(4):
            for y in range(6):
                for z in range(3):
                    if 0 <= x + dx < 4 and 0 <= y + dy < 6 and 0 <= z + dz < 3:
                        want[:, i, x, y, z] = (uf[:, :, x, y, z] * un[:, :, x + dx, y + dy, z + dz]).sum(1)
    torch.testing.assert_close(cv, want, atol=1e-6, rtol=0)
    # unit-norm maps given as such (``unit=True``) are used as they are: the same cosines, and twice the features
    # give four times the products (nothing normalised a second time), with and without gradients
    torch.testing.assert_close(local_cost_volume(un, uf, r, unit=True), want, atol=1e-6, rtol=0)
    torch.testing.assert_close(local_cost_volume(2 * un, 2 * uf, r, unit=True), 4 * want, atol=4e-6, rtol=0)
    twice = local_cost_volume((2 * un).requires_grad_(), 2 * uf, r, unit=True)
    torch.testing.assert_close(twice.detach(), 4 * want, atol=4e-6, rtol=0)


def _cost_by_definition(fm: torch.Tensor, ff: torch.Tensor, r: int) -> torch.Tensor:
    """The local cost volume through autograd's own operations: each shift's cosine on zero-padded views."""
    un, uf = torch.nn.functional.normalize(fm, dim=1), torch.nn.functional.normalize(ff, dim=1)
    x, y, z = ff.shape[2:]
    padded = torch.nn.functional.pad(un, (r,) * 6)
    k = 2 * r + 1
    return torch.stack([(uf * padded[:, :, a:a + x, b:b + y, c:c + z]).sum(1)
                        for a in range(k) for b in range(k) for c in range(k)], 1)


def test_local_cost_volume_gradients_are_those_of_its_definition():
    # the hand-written backward against autograd's on anisotropic maps, with a weight per entry: a gradient routed
    # to the wrong shift, the wrong input or through a transposed axis fails it
    g = torch.Generator().manual_seed(6)
    fm = torch.randn(2, 5, 4, 6, 3, generator=g, dtype=torch.float64, requires_grad=True)
    ff = torch.randn(2, 5, 4, 6, 3, generator=g, dtype=torch.float64, requires_grad=True)
    weight = torch.randn(2, 125, 4, 6, 3, generator=g, dtype=torch.float64)
    got = torch.autograd.grad((local_cost_volume(fm, ff, 2) * weight).sum(), (fm, ff))
    want = torch.autograd.grad((_cost_by_definition(fm, ff, 2) * weight).sum(), (fm, ff))
    for a, b in zip(got, want):
        assert a.shape == b.shape
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10)
    assert float(got[0].abs().max()) > 0.01 and float(got[1].abs().max()) > 0.01


def test_local_cost_volume_gradient_reaches_only_inputs_that_ask_for_it():
    g = torch.Generator().manual_seed(7)
    fm = torch.randn(1, 3, 4, 4, 4, generator=g, dtype=torch.float64, requires_grad=True)
    ff = torch.randn(1, 3, 4, 4, 4, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a: local_cost_volume(a, ff, 1), (fm,), fast_mode=True)
    (grad,) = torch.autograd.grad(local_cost_volume(fm, ff, 1).sum(), (fm,))
    (want,) = torch.autograd.grad(_cost_by_definition(fm, ff, 1).sum(), (fm,))
    torch.testing.assert_close(grad, want, atol=1e-10, rtol=1e-10)
    with torch.no_grad():  # inference: no graph, the same values
        torch.testing.assert_close(local_cost_volume(fm, ff, 1), _cost_by_definition(fm, ff, 1), atol=1e-12, rtol=0)


def test_unit_channels_is_normalize_along_the_channels():
    # each voxel's channel vector to unit length (not a spatial axis: a transposed reduction fails it); a zero vector
    # stays zero as with F.normalize's clamped norm; the gradient is F.normalize's
    g = torch.Generator().manual_seed(8)
    x = torch.randn(2, 5, 3, 4, 6, generator=g, dtype=torch.float64)
    x[1, :, 2, 3, 5] = 0.0
    x.requires_grad_(True)
    got = unit_channels(x)
    want = torch.nn.functional.normalize(x, dim=1)
    torch.testing.assert_close(got, want, atol=1e-12, rtol=0)
    torch.testing.assert_close(got.detach().norm(dim=1)[0], torch.ones(3, 4, 6, dtype=torch.float64))
    assert float(got[1, :, 2, 3, 5].abs().max()) == 0.0
    weight = torch.randn(got.shape, generator=g, dtype=torch.float64)
    (a,) = torch.autograd.grad((got * weight).sum(), (x,))
    (b,) = torch.autograd.grad((want * weight).sum(), (x,))
    torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10)


def test_parabola_shifts_find_a_subcell_peak_with_its_sign_per_axis():
    # costs of a concave quadratic peaked at (0.3, -1.2, 0.45) cells in a +-2 window, three cells, two cases
    r, k = 2, 5
    grid = torch.arange(-r, r + 1, dtype=torch.float64)
    dx, dy, dz = torch.meshgrid(grid, grid, grid, indexing="ij")
    peaks = [(0.3, -1.2, 0.45), (-0.49, 0.0, 1.8), (2.0, -2.0, 0.1)]
    costs = []
    for px, py, pz in peaks:
        costs.append(1.0 - 0.1 * ((dx - px) ** 2 + 0.5 * (dy - py) ** 2 + 2.0 * (dz - pz) ** 2))
    cost = torch.stack(costs, -1).reshape(k**3, 3, 1, 1)[None].float()  # [1, K^3, 3, 1, 1]
    shifts = parabola_shifts(cost.expand(2, -1, -1, -1, -1), r)
    assert shifts.shape == (2, 3, 3) and shifts.dtype == torch.float64
    # a parabola through three samples of a quadratic finds its vertex exactly; on the window's border the
    # integer shift is kept (no neighbour beyond it)
    assert shifts[0, 0].tolist() == pytest.approx([0.3, -1.2, 0.45], abs=1e-5)
    assert shifts[1, 1].tolist() == pytest.approx([-0.49, 0.0, 2.0], abs=1e-5)  # z: best shift on the border
    assert shifts[0, 2].tolist() == pytest.approx([2.0, -2.0, 0.1], abs=1e-5)
    level = _MatchLevel(4, 4, radius=2, temperature=33.0, subcell="parabola")
    assert level.subcell == "parabola"
    with pytest.raises(ValueError, match="subcell"):
        _MatchLevel(4, 4, radius=2, temperature=33.0, subcell="spline")


def test_subcell_readout_switches_without_changing_weights():
    torch.manual_seed(0)
    a = CorrelationRigidNet(grid_size=(32, 32, 32), channels=(4, 8, 8), feat_channels=(8, 8))
    b = CorrelationRigidNet(grid_size=(32, 32, 32), channels=(4, 8, 8), feat_channels=(8, 8), subcell="parabola")
    b.load_state_dict(a.state_dict())  # no parameters of its own: the same checkpoint runs both ways
    x = torch.rand(1, 2, 32, 32, 32)
    la, lb = a.forward_levels(x[:, :1], x[:, 1:]), b.forward_levels(x[:, :1], x[:, 1:])
    assert torch.allclose(la[0], lb[0])  # the coarse (global) level is the same
    assert not torch.allclose(la[1], lb[1])  # the fine level reads the cost volume differently


def test_cell_centres_are_the_stride_voxels_in_mm_about_the_grid_centre():
    net = CorrelationRigidNet(grid_size=(32, 32, 16), grid_spacing=(2.0, 2.0, 3.0), channels=(4, 4, 4),
                              feat_channels=(4, 4))
    cells = net.cells_coarse.reshape(4, 4, 2, 3)
    # cell n of the stride-8 map sits on voxel 8 n; the grid centre is voxel (size - 1) / 2
    assert cells[0, 0, 0].tolist() == pytest.approx([(0 - 15.5) * 2, (0 - 15.5) * 2, (0 - 7.5) * 3])
    assert cells[3, 1, 1].tolist() == pytest.approx([(24 - 15.5) * 2, (8 - 15.5) * 2, (8 - 7.5) * 3])
    with pytest.raises(ValueError, match="divisible"):
        CorrelationRigidNet(grid_size=(30, 32, 32))


def test_network_shapes_levels_and_two_stage_switch():
    net = CorrelationRigidNet(grid_size=(32, 32, 32), channels=(4, 8, 8), feat_channels=(8, 8), fine_passes=2)
    x = torch.rand(2, 2, 32, 32, 32)
    levels = net.forward_levels(x[:, :1], x[:, 1:])
    assert len(levels) == 3 and all(lv.shape == (2, 6) for lv in levels)
    assert torch.allclose(net(x), levels[-1])
    two = TwoStageRigidNet(net, GaussNewtonStage(grid_spacing=(2.0, 2.0, 2.0), iterations=(2,), levels=(2,)),
                           fine_stage_enabled=False)
    out = two(x, stages=True)
    assert torch.equal(out["params"], out["coarse"]) and torch.allclose(out["params"], levels[-1])
    assert len(out["levels"]) == 2 and torch.allclose(out["levels"][0], levels[0])
    with pytest.raises(ValueError, match="network grid"):
        net(torch.rand(1, 2, 32, 32, 16))


def test_network_is_trainable_end_to_end_through_the_levels():
    net = CorrelationRigidNet(grid_size=(32, 32, 32), channels=(4, 8, 8), feat_channels=(8, 8))
    x = torch.rand(1, 2, 32, 32, 32)
    crit = RegistrationCriterion((32, 32, 32), (2.0, 2.0, 2.0), image_loss_pool=1, w_levels=0.5)
    two = TwoStageRigidNet(net, None)
    targets = {"moving": x[:, :1], "fixed": x[:, 1:], "params": torch.tensor([[4.0, 0, 0, 0, 0, 5.0]])}
    loss = crit(two(x, stages=True), targets)
    assert "level0" in crit.last_terms
    loss.backward()
    grads = {n: p.grad for n, p in net.named_parameters()}
    for name in ("stages.0", "coarse.project", "fine.project", "coarse.weight_head", "fine.log_temperature"):
        assert any(g is not None and g.abs().sum() > 0 for n, g in grads.items() if n.startswith(name)), name


def _bright_dot_pair(shape=(80, 80, 80), dot=(50, 30, 41)):
    vol = torch.full((1, *shape), -1000.0)
    vol[:, 10:70, 10:70, 10:70] = 0.0  # body
    vol[(0, *dot)] = 1000.0
    affine = torch.diag(torch.tensor([-2.0, -2.0, 2.0, 1.0], dtype=torch.float64))
    affine[:3, 3] = torch.tensor([70.0, 60.0, -50.0], dtype=torch.float64)
    img = MetaTensor(vol, affine=affine)
    return img


def test_isocenter_crop_is_whole_voxel_and_keeps_the_physical_position():
    img = _bright_dot_pair()
    crop = RandIsocenterCropd(keys="fixed", size=32, max_offset=30.0, spacing=2.0).set_random_state(0)
    grid_in = Grid.from_metatensor(img)
    offsets = set()
    for _ in range(10):
        out = crop({"fixed": img})["fixed"]
        g = Grid.from_metatensor(out)
        assert out.shape == (1, 32, 32, 32)
        # the crop's voxels are the input's voxels: same spacing, origin on an input voxel
        idx = grid_in.physical_to_index() @ np.append(np.asarray(g.origin), 1.0)
        assert np.allclose(idx[:3], np.round(idx[:3]), atol=1e-6)
        off = np.asarray(g.center()) - np.asarray(grid_in.center())
        assert np.all(np.abs(off) <= 30.0)
        assert np.allclose(off, crop.last_offset_mm)  # LPS axes = array axes for this affine (RAS diag(-2, -2, 2))
        offsets.add(tuple(np.round(off, 3)))
    assert len(offsets) > 5  # random


def test_context_chain_cuts_moving_and_fixed_to_one_grid_around_the_isocentre(tmp_path):
    import SimpleITK as sitk

    rng = np.random.default_rng(0)
    arr = np.full((80, 80, 80), -1000.0, np.float32)
    arr[10:70, 10:70, 10:70] = rng.normal(0, 200, (60, 60, 60))
    arr = sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(sitk.GetImageFromArray(arr), 1.5))
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing((2.0, 2.0, 2.0))
    img.SetOrigin((-79.0, -79.0, -79.0))
    sitk.WriteImage(img, str(tmp_path / "ct.nii.gz"))
    item = {"fixed": str(tmp_path / "ct.nii.gz"), "moving": str(tmp_path / "ct.nii.gz"),
            "params": [0.0] * 6, "center": [0.0, 0.0, 0.0]}
    chain = registration_transforms("train", [32] * 3, [2.0] * 3, translate_range=0.0, rotate_range=0.0,
                                    degrade=False, context_size=[64] * 3, isocenter_offset=20.0)
    chain.set_random_state(1)
    for _ in range(3):
        d = chain(dict(item))
        f, m = d["fixed"], d["moving"]
        assert np.allclose(Grid.from_metatensor(f).center(), Grid.from_metatensor(m).center())
        assert float(torch.abs(f - m).max()) < 1e-4  # identical voxels: no half-voxel shift between the two
        assert np.allclose(d["rigid_params"]["center"].numpy(), Grid.from_metatensor(f).center(), atol=1e-4)
    # with a motion: the recorded ground truth (about the isocentre) brings the moved image back
    chain = registration_transforms("train", [32] * 3, [2.0] * 3, translate_range=8.0, rotate_range=15.0,
                                    axis_prob=1.0, degrade=False, context_size=[64] * 3, isocenter_offset=20.0)
    chain.set_random_state(2)
    d = chain(dict(item))
    g = Grid.centered((32,) * 3, (2.0,) * 3)
    p = d["rigid_params"]["params"][None].double()
    back = warp_volume(d["moving"][None].as_tensor(), params_to_matrix_torch(p).float(), g, g)
    f = d["fixed"][None].as_tensor()
    inner = (slice(None), slice(None), slice(6, 26), slice(6, 26), slice(6, 26))
    err = float((back[inner] - f[inner]).abs().mean())
    unmoved = float((d["moving"][None].as_tensor()[inner] - f[inner]).abs().mean())
    assert err < 0.25 * unmoved


def _synth_stream(n: int, seed: int, size: int = 32, spacing: float = 4.0):
    """``n`` (moving, fixed, params) samples: synthetic anatomy, a random motion of up to 12 mm / 12 degrees."""
    from monai_rigidreg.simulation.synth import synth_hu_volume, synth_label_map

    g = Grid.centered((size,) * 3, (spacing,) * 3)
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        s = int(rng.integers(0, 10_000))
        hu = synth_hu_volume(synth_label_map(g, s, radius_mm=size * spacing / 2), s, g, radius_mm=size * spacing / 2)
        fixed = ((hu.clamp(-1000, 2000) + 1000) / 3000).float()[None, None]
        params = torch.tensor([np.r_[rng.uniform(-12, 12, 3), rng.uniform(-12, 12, 3)]], dtype=torch.float32)
        # moving(x) = fixed(T^-1 x), so that fixed(x) = moving(T x) with T fixed -> moving
        inv = torch.linalg.inv(params_to_matrix_torch(params.double()))
        moving = warp_volume(fixed, inv.float(), g, g)
        moving = moving + 0.01 * torch.randn(moving.shape, generator=torch.Generator().manual_seed(i))
        out.append((moving, fixed, params))
    return out


@pytest.mark.slow
def test_training_from_scratch_reduces_the_error_on_its_stream():
    """A real learning test: a small network trained for a few hundred steps on CPU halves its error."""
    torch.manual_seed(0)
    spacing = 4.0
    net = CorrelationRigidNet(grid_size=(32, 32, 32), grid_spacing=(spacing,) * 3, channels=(8, 16, 16),
                              feat_channels=(16, 16), radius=2)
    crit = RegistrationCriterion((32, 32, 32), (spacing,) * 3, image_loss_pool=1, w_levels=0.5)
    crit.loss.w_ssim = crit.loss.w_ncc = crit.loss.w_mi = 0.0
    two = TwoStageRigidNet(net, None)
    probe = _synth_stream(6, seed=123)

    def error() -> float:
        with torch.no_grad():
            return float(np.mean([float(crit.loss.sup_term(net(torch.cat([m, f], 1)), p, crit.grid))
                                  for m, f, p in probe]))

    before = error()
    opt = torch.optim.Adam(net.parameters(), lr=2e-3)
    train = _synth_stream(24, seed=7)
    for step in range(150):
        m, f, p = train[step % len(train)]
        loss = crit(two(torch.cat([m, f], 1), stages=True), {"moving": m, "fixed": f, "params": p})
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = error()
    assert after < 0.5 * before, (before, after)


@pytest.mark.parametrize("norm", ["INSTANCE", "BATCH", ("INSTANCE", {"affine": True})])
@pytest.mark.parametrize("shape", [(1, 16, 2, 2), (16, 32, 2, 3), (32, 32, 1, 2), (16, 8, 1, 1)])
def test_residual_stage_is_monai_residual_unit(norm, shape):
    """ResidualStage3d has MONAI ResidualUnit's state-dict keys and, with the same weights, its output (stride 2 and
    1, channels changed or kept, one or more subunits, instance/batch norm, train and eval mode)."""
    from monai.networks.blocks import ResidualUnit

    from monai_rigidreg.networks.blocks import ResidualStage3d

    c_in, c_out, stride, subunits = shape
    torch.manual_seed(0)
    ref = ResidualUnit(spatial_dims=3, in_channels=c_in, out_channels=c_out, strides=stride, kernel_size=3,
                       subunits=subunits, act="PRELU", norm=norm)
    with torch.no_grad():  # PReLU slopes and norm affines away from their defaults, so a mix-up would show
        for name, p in ref.named_parameters():
            if name.endswith("A.weight") or ".N." in name:
                p.uniform_(0.1, 0.9)
    ours = ResidualStage3d(c_in, c_out, stride=stride, subunits=subunits, norm=norm)
    assert list(ours.state_dict()) == list(ref.state_dict())
    ours.load_state_dict(ref.state_dict())
    x = torch.randn(2, c_in, 9, 8, 7, generator=torch.Generator().manual_seed(1))
    for train in (True, False):
        ref.train(train)
        ours.train(train)
        out = ours(x)
        assert out.shape == (2, c_out, *(-(-n // stride) for n in (9, 8, 7)))
        torch.testing.assert_close(out, ref(x), atol=1e-6, rtol=1e-6)
    with pytest.raises(ValueError, match="norm"):
        ResidualStage3d(1, 2, norm="GROUP")


def test_shipped_weights_load_into_correlation_net():
    """The shipped checkpoint (trained with MONAI's ResidualUnit) loads with strict keys into the network the
    bundle builds."""
    from monai_rigidreg.bundle import load_bundle_network

    net, _ = load_bundle_network()
    assert any(".conv.unit0.adn.A.weight" in k for k in net.state_dict())


@pytest.mark.parametrize("stride", [1, 2])
def test_onednn_conv_is_the_torch_convolution_for_one_volume(stride):
    """OneDNNConv3d sends a single float32 CPU volume to oneDNN: the output and the gradients are nn.Conv3d's (to
    float rounding) for the same weights; a batch of two and float64 take nn.Conv3d's own path (identical)."""
    from monai_rigidreg.networks.blocks import OneDNNConv3d

    torch.manual_seed(0)
    ref = torch.nn.Conv3d(6, 5, 3, stride, 1)
    ours = OneDNNConv3d(6, 5, 3, stride, 1)
    ours.load_state_dict(ref.state_dict())
    x = torch.randn(1, 6, 11, 9, 10, generator=torch.Generator().manual_seed(2), requires_grad=True)
    out, want = ours(x), ref(x)
    assert out.shape == want.shape == (1, 5, *(-(-n // stride) for n in (11, 9, 10)))
    torch.testing.assert_close(out, want, atol=1e-5, rtol=1e-5)
    g_ours = torch.autograd.grad(out.square().sum(), [x, ours.weight])
    g_ref = torch.autograd.grad(want.square().sum(), [x, ref.weight])
    for a, b in zip(g_ours, g_ref):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)
    with torch.no_grad():
        two = torch.randn(2, 6, 11, 9, 10)
        assert torch.equal(ours(two), ref(two))
        assert torch.equal(ours.double()(x.double()), ref.double()(x.double()))


@pytest.mark.parametrize("case", [
    # batch, channels in / out, size, kernel, stride, padding
    (3, 4, 5, (9, 8, 7), 3, 1, 1),
    (2, 3, 4, (11, 9, 10), 3, 2, 1),
    (2, 2, 3, (12, 7, 9), (3, 1, 5), (2, 1, 3), (1, 0, 2)),
    (1, 1, 6, (10, 10, 10), 3, 2, 1),  # one volume, one input channel (the encoders' first convolution)
])
def test_onednn_conv_weight_gradient_by_a_swapped_convolution_is_autograds(case):
    """Training on CPU (the weight needs a gradient): OneDNNConv3d takes the swapped-convolution weight gradient
    (_SwappedWeightGradConv3d). In float64 its output and the input, weight and bias gradients equal nn.Conv3d's to
    1e-10 for odd sizes, anisotropic kernels, strides and paddings; with the weight frozen, or under no_grad, it does
    not take that path."""
    from monai_rigidreg.networks.blocks import OneDNNConv3d

    batch, c_in, c_out, size, kernel, stride, padding = case
    torch.manual_seed(0)
    ref = torch.nn.Conv3d(c_in, c_out, kernel, stride, padding).double()
    ours = OneDNNConv3d(c_in, c_out, kernel, stride, padding).double()
    ours.load_state_dict(ref.state_dict())
    x = torch.randn(batch, c_in, *size, dtype=torch.float64, generator=torch.Generator().manual_seed(3),
                    requires_grad=True)
    out, want = ours(x), ref(x)
    assert "SwappedWeightGrad" in type(out.grad_fn).__name__
    torch.testing.assert_close(out, want, atol=1e-12, rtol=1e-12)
    weights = torch.randn(want.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    got = torch.autograd.grad((out * weights).sum(), [x, ours.weight, ours.bias])
    expected = torch.autograd.grad((want * weights).sum(), [x, ref.weight, ref.bias])
    for a, b in zip(got, expected):
        assert a.shape == b.shape
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10)
    ours.weight.requires_grad_(False)
    assert "SwappedWeightGrad" not in type(ours(x).grad_fn).__name__
    ours.weight.requires_grad_(True)
    with torch.no_grad():
        assert ours(x).grad_fn is None


def test_onednn_conv_weight_gradient_at_training_size_in_float32():
    """The context network's largest training convolution, ``[4, 16, 32^3]`` 16 -> 16 kernel 3 (here 20^3): the
    float32 weight gradient of the swapped convolution is nn.Conv3d's to float rounding; one transposed in its two
    channel axes (a mix-up of input and output channels) is not."""
    from monai_rigidreg.networks.blocks import OneDNNConv3d

    torch.manual_seed(0)
    ref = torch.nn.Conv3d(16, 16, 3, 1, 1)
    ours = OneDNNConv3d(16, 16, 3, 1, 1)
    ours.load_state_dict(ref.state_dict())
    x = torch.randn(4, 16, 20, 20, 20, generator=torch.Generator().manual_seed(5))
    g_ours = torch.autograd.grad(ours(x).square().sum(), ours.weight)[0]
    g_ref = torch.autograd.grad(ref(x).square().sum(), ref.weight)[0]
    torch.testing.assert_close(g_ours, g_ref, atol=1e-3, rtol=1e-4)
    assert not torch.allclose(g_ours.transpose(0, 1), g_ref, atol=1e-3, rtol=1e-4)


@pytest.mark.parametrize("stride", [1, 2])
def test_onednn_conv_weight_gradient_under_bfloat16_autocast(stride):
    """The context network trains its encoders under ``torch.autocast(dtype=bfloat16)`` where the CPU has the kernels
    (``train_context.json``'s ``train_autocast``). There the swapped-convolution path runs in bfloat16 like
    nn.Conv3d (the same bfloat16 output) and returns every gradient in its tensor's dtype (float32), each equal to
    nn.Conv3d's under the same autocast to bfloat16 rounding; the weight gradient transposed in its channel axes
    is not. (Before this was handled, the backward mixed a float32 input with a bfloat16 gradient and raised.)"""
    from monai_rigidreg.networks.blocks import OneDNNConv3d

    torch.manual_seed(0)
    ref = torch.nn.Conv3d(6, 6, 3, stride, 1)
    ours = OneDNNConv3d(6, 6, 3, stride, 1)
    ours.load_state_dict(ref.state_dict())
    x = torch.randn(2, 6, 11, 10, 9, generator=torch.Generator().manual_seed(6), requires_grad=True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out, want = ours(x), ref(x)
    assert "SwappedWeightGrad" in type(out.grad_fn).__name__
    assert out.dtype == want.dtype == torch.bfloat16
    torch.testing.assert_close(out, want, atol=0.0, rtol=0.0)
    weights = torch.randn(want.shape, generator=torch.Generator().manual_seed(7))
    got = torch.autograd.grad((out.float() * weights).sum(), [x, ours.weight, ours.bias])
    expected = torch.autograd.grad((want.float() * weights).sum(), [x, ref.weight, ref.bias])
    for a, b in zip(got, expected):
        assert a.dtype == b.dtype == torch.float32 and a.shape == b.shape
        scale = float(b.abs().max())
        torch.testing.assert_close(a, b, atol=1e-2 * scale, rtol=0.0)  # bfloat16 keeps 8 bits
    assert not torch.allclose(got[1].transpose(0, 1), expected[1], atol=1e-2 * float(expected[1].abs().max()))


def test_pointwise_columns_is_the_volume_head_on_columns():
    """A kernel-1 head run on ``[B, C, N]`` columns (the 4 mm level's match weights): the output and the gradients
    (inputs and every weight) are those of the same modules on a ``[B, C, N, 1, 1]`` volume; a channel mix-up (the
    weights transposed) fails it; a kernel-3 convolution is refused."""
    from monai_rigidreg.networks.blocks import pointwise_columns

    torch.manual_seed(0)
    head = torch.nn.Sequential(torch.nn.Conv3d(6, 4, 1), torch.nn.PReLU(), torch.nn.Conv3d(4, 1, 1))
    x = torch.randn(3, 6, 17, requires_grad=True)
    out, want = pointwise_columns(head, x), head(x[..., None, None])[..., 0, 0]
    assert out.shape == (3, 1, 17)
    torch.testing.assert_close(out, want, atol=1e-6, rtol=1e-6)
    params = [x, *head.parameters()]
    for a, b in zip(torch.autograd.grad(out.square().sum(), params), torch.autograd.grad(want.square().sum(), params)):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    mixed = torch.nn.functional.conv1d(x, head[0].weight.flatten(2).flip(1), head[0].bias)
    assert not torch.allclose(mixed, head[0](x[..., None, None])[..., 0, 0], atol=1e-3)
    with pytest.raises(ValueError, match="kernel-1"):
        pointwise_columns(torch.nn.Sequential(torch.nn.Conv3d(6, 1, 3)), x)
