"""The coarse level's pretraining (``engine/coarse_pretrain.py``): it lowers the coarse match loss, changes only the
coarse level, follows the schedule, and scores matches against the truth."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from monai_rigidreg.engine.coarse_pretrain import coarse_parameters, coarse_step, pretrain_coarse
from monai_rigidreg.engine.sampler import MotionRange
from monai_rigidreg.networks import ContextCorrelationNet

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _samples(seed: int):
    """Endless unmoved pairs: a smooth random CT context (32^3 at 8 mm) and, as the CBCT, its central half on the
    network grid (32^3 at 4 mm)."""
    g = torch.Generator().manual_seed(seed)
    while True:
        ctx = F.avg_pool3d(torch.rand(1, 1, 40, 40, 40, generator=g), 9, stride=1)[..., :32, :32, :32]
        ctx = (ctx - ctx.min()) / (ctx.max() - ctx.min())
        moving = F.interpolate(ctx[..., 8:24, 8:24, 8:24], scale_factor=2, mode="trilinear", align_corners=False)
        yield {"moving": moving[0], "context": ctx[0], "rigid_params": {"params": torch.zeros(6)}}


def test_pretraining_lowers_the_coarse_match_loss_and_changes_only_the_coarse_level():
    torch.manual_seed(0)
    net = ContextCorrelationNet(grid_size=(32, 32, 32), grid_spacing=(4.0, 4.0, 4.0), channels=(4, 8),
                                coarse_channels=(8, 8, 8), feat_channels=(8, 8, 4), select_cells=256)
    coarse = {id(p) for p in coarse_parameters(net)}
    before = {n: p.detach().clone() for n, p in net.named_parameters()}
    first, _ = coarse_step(net, [next(_samples(1)) for _ in range(2)])
    seen = []
    history = pretrain_coarse(net, lambda band: (seen.append(band), _samples(2))[1],
                              [(MotionRange(10.0, 10.0), 20), (MotionRange(20.0, 5.0), 10)], batch_size=2, lr=1e-2,
                              log_every=10)
    assert [b.max_translation for b in seen] == [10.0, 20.0]
    assert [r["step"] for r in history] == [10, 20, 30] and history[-1]["samples"] == 60
    assert [r["band_mm"] for r in history] == [10.0, 10.0, 20.0]
    last, near = coarse_step(net, [next(_samples(1)) for _ in range(2)])
    assert float(last.detach()) < float(first.detach()) - 0.5  # nats
    assert 0.0 <= near <= 1.0
    for name, p in net.named_parameters():
        changed = not torch.equal(p.detach(), before[name])
        if id(p) in coarse:
            continue
        assert not changed, name  # the encoder, heads and projections of the local levels are untouched
    assert any(not torch.equal(p.detach(), before[n]) for n, p in net.named_parameters() if id(p) in coarse)
