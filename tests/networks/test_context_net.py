"""The context correlation network: its geometry (cells, sub-cell readout, fits, context grid), its match loss, and
the registrar's way of giving it the CT context."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from monai_rigidreg.core.geometry import Grid, matrix_to_params_torch, params_to_matrix_torch
from monai_rigidreg.losses import match_loss
from monai_rigidreg.networks import ContextCorrelationNet, TwoStageRigidNet
from monai_rigidreg.networks.context_net import (
    context_from_fixed,
    robust_rigid_fit,
    sparse_cost_volume,
    subcell_shifts,
)
from monai_rigidreg.networks.correlation_net import local_cost_volume, parabola_shifts

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _smooth_field(points_mm: torch.Tensor, channels: int = 16, seed: int = 0, wavelength_mm: float = 24.0
                  ) -> torch.Tensor:
    """``[C, N]`` smooth random features at ``points_mm`` ``[N, 3]``: sums of plane waves (band-limited, so a
    sub-cell shift of the points is a sub-cell shift of the features)."""
    g = torch.Generator().manual_seed(seed)
    k = torch.randn(channels, 4, 3, generator=g, dtype=torch.float64)
    k = k / k.norm(dim=-1, keepdim=True) * (2 * math.pi / wavelength_mm)
    phase = torch.rand(channels, 4, generator=g, dtype=torch.float64) * 2 * math.pi
    return torch.cos(torch.einsum("cwd,nd->cwn", k, points_mm) + phase[..., None]).sum(1)


def _cell_points(size: int, cell_mm: float) -> torch.Tensor:
    ax = (torch.arange(size, dtype=torch.float64) - (size - 1) / 2) * cell_mm
    return torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_finest_level_recovers_a_half_cell_shift(axis):
    """A shift of half a 4 mm cell (2 mm) along one axis, read by the 4 mm level's sparse cost volume, sub-cell
    parabola and robust closed-form fit, comes back as that translation to 0.1 mm (no rotation)."""
    cell, size, shift = 4.0, 24, 2.0
    pts = _cell_points(size, cell)
    d = torch.zeros(3, dtype=torch.float64)
    d[axis] = shift
    ff = _smooth_field(pts).reshape(1, -1, size, size, size).float()
    # the moving content moved by +d: what the fixed shows at x, the moving shows at x + d
    fm = _smooth_field(pts - d).reshape(1, -1, size, size, size).float()
    inner = torch.zeros(size, size, size, dtype=torch.bool)
    inner[2:-2, 2:-2, 2:-2] = True
    index = torch.nonzero(inner.flatten())[:, 0][None]
    cost = sparse_cost_volume(fm, ff, index, 1)
    cells = pts[index[0]][None]
    matched = cells + subcell_shifts(cost, 1) * cell
    fit = robust_rigid_fit(cells, matched, torch.ones(1, cells.shape[1], dtype=torch.float64), sigma_mm=cell)
    params = matrix_to_params_torch(fit)[0]
    assert abs(float(params[axis]) - shift) < 0.1
    others = [i for i in range(3) if i != axis]
    assert float(params[others].abs().max()) < 0.1
    assert float(params[3:].abs().max()) < 0.05  # degrees


def test_sparse_cost_volume_is_the_local_cost_volume_at_the_selected_cells():
    g = torch.Generator().manual_seed(1)
    fm, ff = torch.randn(2, 5, 6, 7, 8, generator=g), torch.randn(2, 5, 6, 7, 8, generator=g)
    dense = local_cost_volume(fm, ff, 2).flatten(2).transpose(1, 2)  # [B, N, 125]
    index = torch.stack([torch.randperm(6 * 7 * 8, generator=g)[:40] for _ in range(2)])
    sparse = sparse_cost_volume(fm, ff, index, 2)
    expected = dense.gather(1, index[..., None].expand(-1, -1, 125))
    torch.testing.assert_close(sparse, expected, atol=1e-5, rtol=1e-5)
    # features of unit norm given as such: the same cosines; ``unit=True`` normalises nothing (twice the features,
    # four times the products), so the network's one normalisation per map is the only one
    from monai_rigidreg.networks import unit_channels

    um, uf = unit_channels(fm), unit_channels(ff)
    torch.testing.assert_close(sparse_cost_volume(um, uf, index, 2, unit=True), sparse, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(sparse_cost_volume(2 * um, 2 * uf, index, 2, unit=True), 4 * sparse, atol=1e-5,
                               rtol=1e-5)


def test_subcell_shifts_equal_parabola_shifts_inside_the_window():
    """Where the argmax is inside the search window on every axis, the readout is the shipped network's parabola."""
    g = torch.Generator().manual_seed(2)
    cost = torch.randn(2, 125, 4, 5, 6, generator=g).double()
    flat = cost.flatten(2).transpose(1, 2)
    best = flat.argmax(-1)
    index = torch.stack([best // 25, (best // 5) % 5, best % 5], -1)
    inner = ((index > 0) & (index < 4)).all(-1)
    assert inner.any() and (~inner).any()
    torch.testing.assert_close(subcell_shifts(flat, 2)[inner], parabola_shifts(cost, 2)[inner])


@pytest.mark.parametrize("true_shift", [0.5, -0.5, 0.9, -0.3, 1.0])
def test_subcell_shift_on_the_window_border_is_not_snapped(true_shift):
    """A quadratic cost peaking at ``true_shift`` cells along x (radius 1) is read back exactly, also where the
    argmax lies on the border of the window."""
    ax = torch.arange(-1, 2, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    peak = torch.tensor([true_shift, 0.0, 0.0], dtype=torch.float64)
    cost = -((grid - peak) ** 2).sum(-1)[None, None]
    got = subcell_shifts(cost, 1)[0, 0]
    torch.testing.assert_close(got, peak)


def test_robust_fit_ignores_outliers_and_recovers_the_rigid_transform():
    g = torch.Generator().manual_seed(3)
    p = torch.randn(1, 400, 3, generator=g, dtype=torch.float64) * 40
    truth = params_to_matrix_torch(torch.tensor([[3.0, -2.0, 5.0, 4.0, -6.0, 10.0]], dtype=torch.float64))
    q = p @ truth[:, :3, :3].transpose(1, 2) + truth[:, None, :3, 3]
    q[:, :40] += torch.randn(1, 40, 3, generator=g, dtype=torch.float64) * 60  # 10 % gross outliers
    w = torch.ones(1, 400, dtype=torch.float64)
    plain = matrix_to_params_torch(robust_rigid_fit(p, q, w, 4.0, iterations=0))
    robust = matrix_to_params_torch(robust_rigid_fit(p, q, w, 4.0, iterations=4))
    err_plain = (plain - matrix_to_params_torch(truth)).abs().max()
    err_robust = (robust - matrix_to_params_torch(truth)).abs().max()
    assert err_robust < 0.05 < err_plain


def test_context_from_fixed_keeps_the_centre():
    """The pooled, padded fixed image lies on the context grid of the same centre: a bright voxel pair of the 2 mm
    grid lands on the 4 mm voxel at the same physical position."""
    fixed = torch.zeros(1, 1, 16, 16, 16)
    fixed[0, 0, 10:12, 4:6, 6:8] = 1.0  # 2x2x2 block: exactly one pooled voxel
    ctx = context_from_fixed(fixed, 2)
    assert ctx.shape == (1, 1, 16, 16, 16)
    net_grid = Grid.centered((16,) * 3, (2.0,) * 3)
    ctx_grid = Grid.centered((16,) * 3, (4.0,) * 3)
    where = torch.nonzero(ctx[0, 0] > 0.5)[0].double().numpy()
    block_centre = net_grid.index_to_physical() @ np.array([10.5, 4.5, 6.5, 1.0])
    assert np.allclose(ctx_grid.index_to_physical() @ np.append(where, 1.0), block_centre)


def _true_matrix(params):
    return params_to_matrix_torch(torch.tensor([params], dtype=torch.float64))


def test_match_loss_local_is_low_only_at_the_true_shift():
    """A local record whose logits peak at the true shift scores low; peaking at the mirrored shift scores high
    (a sign flip of the label fails this)."""
    shifts = torch.stack(torch.meshgrid(*[torch.arange(-1, 2, dtype=torch.float64)] * 3, indexing="ij"),
                         -1).reshape(-1, 3) * 4.0  # mm, 4 mm cells
    cells = _cell_points(3, 4.0)
    truth = _true_matrix([4.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # every fixed cell's match is one cell along +x
    right = (shifts == torch.tensor([4.0, 0.0, 0.0], dtype=torch.float64)).all(-1)
    wrong = (shifts == torch.tensor([-4.0, 0.0, 0.0], dtype=torch.float64)).all(-1)
    record = {"kind": "local", "cells": cells, "shifts": shifts, "start": torch.eye(4, dtype=torch.float64)[None]}
    good = match_loss({**record, "logits": (right.float() * 20.0).expand(1, len(cells), -1)}, truth)
    bad = match_loss({**record, "logits": (wrong.float() * 20.0).expand(1, len(cells), -1)}, truth)
    assert float(good) < 1e-3
    assert float(bad) > 10.0


def test_match_loss_local_accounts_for_the_start_estimate():
    """After the CBCT was warped by the truth itself, the right match is no shift."""
    shifts = torch.stack(torch.meshgrid(*[torch.arange(-1, 2, dtype=torch.float64)] * 3, indexing="ij"),
                         -1).reshape(-1, 3) * 4.0
    cells = _cell_points(3, 4.0)
    truth = _true_matrix([3.0, -2.0, 1.0, 5.0, 0.0, -4.0])
    zero = (shifts == 0).all(-1)
    record = {"kind": "local", "cells": cells, "shifts": shifts, "start": truth,
              "logits": (zero.float() * 20.0).expand(1, len(cells), -1)}
    assert float(match_loss(record, truth)) < 1e-3


def test_match_loss_global_points_at_the_ct_position_of_each_cbct_cell():
    cand = _cell_points(5, 16.0)  # CT context cells
    cells = _cell_points(2, 16.0) + 8.0  # CBCT cells at +-8 + 8 mm
    truth = _true_matrix([16.0, 16.0, 16.0, 0.0, 0.0, 0.0])  # CT point x maps to x + 16: cell q comes from q - 16
    want = cells - 16.0  # on the candidate lattice
    logits = -((want[:, None, :] - cand[None]) ** 2).sum(-1)[None] * 10.0
    record = {"kind": "global", "cells": cells, "candidates": cand}
    good = match_loss({**record, "logits": logits.float()}, truth)
    flipped = -((cells + 16.0)[:, None, :] - cand[None]) ** 2
    bad = match_loss({**record, "logits": (flipped.sum(-1)[None] * 10.0).float()}, truth)
    assert float(good) < 0.1
    assert float(bad) > 10.0


@pytest.fixture(scope="module")
def small_net():
    torch.manual_seed(0)
    return ContextCorrelationNet(grid_size=(32, 32, 32), grid_spacing=(4.0, 4.0, 4.0), channels=(4, 8),
                                 coarse_channels=(4, 8, 8), feat_channels=(8, 8, 4), select_cells=256).eval()


def test_network_shapes_levels_and_records(small_net):
    x = torch.rand(2, 1, 32, 32, 32)
    levels, records = small_net.forward_levels(x, x.flip(2), matches=True)
    assert len(levels) == 1 + sum(small_net.passes) == len(records)
    assert all(level.shape == (2, 6) for level in levels)
    assert [r["kind"] for r in records] == ["global"] + ["local"] * sum(small_net.passes)
    assert records[-1]["logits"].shape == (2, 256, 27)


def test_two_stage_takes_the_context_as_channels_or_as_fixed_channels(small_net):
    """The bundle's ``[B, 3, ...]`` input and the registrar's fixed-with-context form give the same estimate."""
    model = TwoStageRigidNet(small_net, None).eval()
    g = torch.Generator().manual_seed(4)
    m, f, c = (torch.rand(1, 1, 32, 32, 32, generator=g) for _ in range(3))
    with torch.no_grad():
        a = model(torch.cat([m, f, c], 1))
        b = model.forward_pair(m, torch.cat([f, c], 1))
        without = model(torch.cat([m, f], 1))
    torch.testing.assert_close(a, b)
    assert not torch.allclose(a, without)  # the context is used


def test_training_mode_returns_match_records_for_the_criterion(small_net):
    from monai_rigidreg.engine import RegistrationCriterion

    model = TwoStageRigidNet(small_net, None).train()
    m = torch.rand(2, 1, 32, 32, 32)
    out = model(torch.cat([m, m], 1), stages=True)
    n = 1 + sum(small_net.passes)
    assert len(out["matches"]) == n
    crit = RegistrationCriterion((32, 32, 32), (4.0, 4.0, 4.0), w_match=1.0)
    loss = crit(out, {"moving": m, "fixed": m, "params": torch.zeros(2, 6)})
    loss.backward()
    assert {f"match{i}" for i in range(n)} <= set(crit.last_terms)
    assert small_net.coarse_project.weight.grad is not None
    small_net.eval()


def test_training_autocast_leaves_inference_and_matching_in_float32():
    torch.manual_seed(1)
    kw = {"grid_size": (32, 32, 32), "grid_spacing": (4.0, 4.0, 4.0), "channels": (4, 8), "coarse_channels": (4, 8, 8),
          "feat_channels": (8, 8, 4), "select_cells": 128}
    plain = ContextCorrelationNet(**kw).eval()
    mixed = ContextCorrelationNet(**kw, train_autocast="bfloat16").eval()
    mixed.load_state_dict(plain.state_dict())
    x = torch.rand(1, 1, 32, 32, 32)
    with torch.no_grad():
        torch.testing.assert_close(mixed.forward_levels(x, x.flip(3))[-1], plain.forward_levels(x, x.flip(3))[-1])
    mixed.train()
    _, records = mixed.forward_levels(x, x.flip(3), matches=True)
    assert all(r["logits"].dtype == torch.float32 for r in records)


def test_training_step_under_bfloat16_autocast_gives_nn_conv3ds_gradients(monkeypatch):
    """A training step with ``train_autocast="bfloat16"`` (what ``train_context.json`` selects on a CPU with bfloat16
    kernels) runs forward, the criterion and backward through the encoders' ``OneDNNConv3d`` (the swapped-convolution
    weight gradient), and gives the loss and the gradients of the same step with plain ``nn.Conv3d`` convolutions
    under the same autocast: every parameter's gradient float32 and finite, cosine over all parameters above 0.9999.
    (The float32 step is no reference: at this random start bfloat16 alone moves the loss by 3 %.)"""
    from monai_rigidreg.engine import RegistrationCriterion
    from monai_rigidreg.networks.blocks import OneDNNConv3d

    kw = {"grid_size": (32, 32, 32), "grid_spacing": (4.0, 4.0, 4.0), "channels": (4, 8), "coarse_channels": (4, 8, 8),
          "feat_channels": (8, 8, 4), "select_cells": 128}
    g = torch.Generator().manual_seed(5)
    fixed = torch.nn.functional.avg_pool3d(torch.rand(2, 1, 40, 40, 40, generator=g), 5, stride=1)[..., :32, :32, :32]
    moving = torch.roll(fixed, 2, dims=2)
    target = {"moving": moving, "fixed": fixed, "params": torch.tensor([[8.0, 0, 0, 0, 0, 0]] * 2)}
    losses, grads = [], []
    for plain_conv in (False, True):
        if plain_conv:
            monkeypatch.setattr(OneDNNConv3d, "_conv_forward", torch.nn.Conv3d._conv_forward)
        torch.manual_seed(2)
        net = ContextCorrelationNet(**kw, train_autocast="bfloat16")
        model = TwoStageRigidNet(net, None).train()
        crit = RegistrationCriterion((32, 32, 32), (4.0, 4.0, 4.0), w_match=1.0)
        loss = crit(model(torch.cat([moving, fixed], 1), stages=True), target)
        loss.backward()
        named = [(n, p.grad) for n, p in net.named_parameters() if p.grad is not None]
        assert all(gr.dtype == torch.float32 and torch.isfinite(gr).all() for _, gr in named)
        losses.append(float(loss.detach()))
        grads.append(torch.cat([gr.flatten() for _, gr in named]))
    assert losses[0] == pytest.approx(losses[1], rel=1e-5)
    assert grads[0].shape == grads[1].shape
    assert float(torch.nn.functional.cosine_similarity(grads[0], grads[1], dim=0)) > 0.9999


def test_coarse_start_both_keeps_per_sample_the_start_that_matches_the_images_better(monkeypatch):
    """``coarse_start``: with the local levels held still (each correction the identity), the estimate is the start.
    Sample 0 has no motion, sample 1 moved +12 mm along x, and the coarse level says +12 mm for both: ``"coarse"``
    keeps +12 mm for both, ``"identity"`` 0 for both, ``"both"`` the one that matches the images (0, then +12 mm);
    training always starts from the coarse estimate."""
    torch.manual_seed(0)
    net = ContextCorrelationNet(grid_size=(32, 32, 32), grid_spacing=(4.0, 4.0, 4.0), channels=(4, 8),
                                coarse_channels=(4, 8, 8), feat_channels=(8, 8, 4), select_cells=256)
    g = torch.Generator().manual_seed(3)
    x = torch.nn.functional.avg_pool3d(torch.rand(1, 1, 40, 40, 40, generator=g), 9, stride=1)[..., :32, :32, :32]
    x = (x - x.min()) / (x.max() - x.min())
    moving = torch.cat([x, torch.roll(x, 3, dims=2)])  # moving(y) = fixed(y - 12 mm) in sample 1
    fixed = torch.cat([x, x])
    shift = params_to_matrix_torch(torch.tensor([[12.0, 0, 0, 0, 0, 0]] * 2, dtype=torch.float64))

    def coarse(m, c):
        return shift.clone(), {"kind": "global"}

    def still(level, fm_feats, ff, total, fixed_weight, fixed_, warped):
        return torch.eye(4, dtype=torch.float64).expand(warped.shape[0], 4, 4).clone(), {"kind": "local"}

    monkeypatch.setattr(net, "_coarse", coarse)
    monkeypatch.setattr(net, "_local", still)
    expected = {"coarse": [12.0, 12.0], "identity": [0.0, 0.0], "both": [0.0, 12.0]}
    net.eval()
    for start, tx in expected.items():
        net.coarse_start = start
        with torch.no_grad():
            out = net.forward_pair(moving, fixed)
        assert out.shape == (2, 6)
        torch.testing.assert_close(out[:, 0].double(), torch.tensor(tx, dtype=torch.float64), atol=1e-4, rtol=0)
        assert float(out[:, 1:].abs().max()) < 1e-4
    net.train()
    net.coarse_start = "both"
    out = net.forward_pair(moving, fixed)
    torch.testing.assert_close(out[:, 0].detach().double(), torch.tensor([12.0, 12.0], dtype=torch.float64),
                               atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="coarse_start"):
        ContextCorrelationNet(grid_size=(32, 32, 32), grid_spacing=(4.0, 4.0, 4.0), coarse_start="search")


def test_coarse_passes_compose_the_coarse_level_on_the_cbct_resampled_by_the_estimate(monkeypatch):
    """``coarse_passes=2`` (evaluation only): the second coarse pass sees the CBCT warped by the first estimate and
    its correction is composed after it (``first @ second``: fixed -> moving); training runs the coarse level once."""
    from monai_rigidreg.core.warp import warp_volume

    torch.manual_seed(0)
    net = ContextCorrelationNet(grid_size=(32, 32, 32), grid_spacing=(4.0, 4.0, 4.0), channels=(4, 8),
                                coarse_channels=(4, 8, 8), feat_channels=(8, 8, 4), select_cells=256,
                                coarse_passes=2)
    first = params_to_matrix_torch(torch.tensor([[6.0, 0, 0, 0, 0, 20.0]], dtype=torch.float64))
    second = params_to_matrix_torch(torch.tensor([[0, 8.0, 0, 0, 0, 0]], dtype=torch.float64))
    seen = []

    def coarse(m, c):
        seen.append(m.clone())
        return (first if len(seen) == 1 else second).clone(), {"kind": "global"}

    def still(level, fm_feats, ff, total, fixed_weight, fixed_, warped):
        return torch.eye(4, dtype=torch.float64).expand(warped.shape[0], 4, 4).clone(), {"kind": "local"}

    monkeypatch.setattr(net, "_coarse", coarse)
    monkeypatch.setattr(net, "_local", still)
    moving, fixed = torch.rand(1, 1, 32, 32, 32), torch.rand(1, 1, 32, 32, 32)
    net.eval()
    with torch.no_grad():
        levels = net.forward_levels(moving, fixed)
    assert len(seen) == 2 and len(levels) == 1 + sum(net.passes)
    torch.testing.assert_close(seen[1], warp_volume(moving, first, net.grid, net.grid))
    expected = matrix_to_params_torch(first @ second).float()
    torch.testing.assert_close(levels[0], expected, atol=1e-4, rtol=0)
    torch.testing.assert_close(levels[-1], expected, atol=1e-4, rtol=0)
    assert not torch.allclose(expected, matrix_to_params_torch(second @ first).float(), atol=0.1)  # order matters
    seen.clear()
    net.train()
    net.forward_levels(moving, fixed)
    assert len(seen) == 1
    with pytest.raises(ValueError, match="coarse_passes"):
        ContextCorrelationNet(grid_size=(32, 32, 32), grid_spacing=(4.0, 4.0, 4.0), coarse_passes=0)
