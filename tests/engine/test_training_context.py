"""A small from-scratch training run of the context network on the on-the-fly sampler's stream lowers its error."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch
from conftest import synth_ct

from monai_rigidreg.core.geometry import Grid, point_distances_torch
from monai_rigidreg.engine import RegistrationCriterion, RegistrationPrepareBatch
from monai_rigidreg.engine.sampler import MotionRange, RigidPairSampler, sources_from_cts
from monai_rigidreg.networks import ContextCorrelationNet, TwoStageRigidNet

SIZE, SPACING = (32, 32, 32), (4.0, 4.0, 4.0)


@pytest.mark.slow
def test_short_training_run_lowers_the_error_on_its_stream(tmp_path):
    path = tmp_path / "ct.nii.gz"
    sitk.WriteImage(synth_ct(Grid.centered((80, 80, 64), (3.0,) * 3), seed=7, radius_mm=100.0), str(path))
    sources = sources_from_cts([path], network_spacing=SPACING[0], context_spacing=8.0, isocenter_max=30.0)
    sampler = RigidPairSampler(sources, network_size=SIZE, network_spacing=SPACING, seed=1,
                               motions=(MotionRange(12.0, 10.0),))
    torch.manual_seed(0)
    net = ContextCorrelationNet(grid_size=SIZE, grid_spacing=SPACING, channels=(8, 16), coarse_channels=(8, 16, 16),
                                feat_channels=(16, 16, 8), passes=(1, 1), select_cells=512)
    model = TwoStageRigidNet(net, None)
    criterion = RegistrationCriterion(SIZE, SPACING, w_match=1.0)
    prepare = RegistrationPrepareBatch()
    optimizer = torch.optim.Adam(model.parameters(), lr=2e-3)
    points = torch.as_tensor(np.stack(np.meshgrid(*[np.linspace(-48, 48, 4)] * 3, indexing="ij"), -1).reshape(-1, 3))
    rng = np.random.default_rng(123)
    held = [sampler.draw(rng) for _ in range(8)]  # a fixed set of the stream, drawn once

    def stream_error() -> float:
        from monai.data import list_data_collate

        inputs, targets = prepare(list_data_collate(held))
        model.eval()
        with torch.no_grad():
            pred = model(inputs)
        model.train()
        return float(point_distances_torch(pred.double(), targets["params"].double(), points).mean())

    before = stream_error()
    from monai.data import DataLoader

    loader = iter(DataLoader(sampler, batch_size=2, num_workers=0))
    for _ in range(80):
        inputs, targets = prepare(next(loader))
        loss = criterion(model(inputs, stages=True), targets)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    after = stream_error()
    assert after < 0.75 * before, (before, after)
