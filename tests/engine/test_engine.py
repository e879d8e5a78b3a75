"""Engine glue: batch preparation, criterion, metrics, handlers and the transform chains."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from monai.data import DataLoader, Dataset, load_decathlon_datalist

from monai_rigidreg.core.geometry import Grid, params_to_matrix
from monai_rigidreg.engine import (
    RegistrationCriterion,
    RegistrationPrepareBatch,
    ResumeHandler,
    RigidErrorMetric,
    canonical_grid,
    plot_history,
    registration_transforms,
)
from monai_rigidreg.losses import RigidRegistrationLoss


@pytest.mark.parametrize("quantity,expected", [("tx", 3.0), ("ty", 4.0), ("tz", 0.0), ("rx", 0.0), ("trans", 7 / 3),
                                               ("tre", 5.0)])
def test_rigid_error_metric_pure_translation(quantity, expected):
    m = RigidErrorMetric(quantity)
    pred = torch.tensor([[3.0, 4.0, 0.0, 10.0, -5.0, 2.0]])
    true = torch.tensor([[0.0, 0.0, 0.0, 10.0, -5.0, 2.0]])
    m(pred, true)
    assert float(m.aggregate()) == pytest.approx(expected, abs=1e-6)


def test_rigid_error_metric_wraps_angles_and_tre_of_rotation():
    m = RigidErrorMetric("rz")
    m(torch.tensor([[0, 0, 0, 0, 0, 179.0]]), torch.tensor([[0, 0, 0, 0, 0, -179.0]]))
    assert float(m.aggregate()) == pytest.approx(2.0)
    # TRE of a rotation error equals the mean displacement of the metric's own point grid
    m = RigidErrorMetric("tre", extent_mm=40.0, step_mm=20.0)
    m(torch.tensor([[0, 0, 0, 0, 0, 2.0]]), torch.zeros(1, 6))
    pts = np.stack(np.meshgrid(*[np.arange(-40, 41, 20.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    disp = (pts @ params_to_matrix([0, 0, 0, 0, 0, 2.0])[:3, :3].T) - pts
    assert float(m.aggregate()) == pytest.approx(np.linalg.norm(disp, axis=1).mean(), rel=1e-6)


def test_prepare_batch_and_criterion_pooling_keeps_supervised_term():
    g = torch.Generator().manual_seed(0)
    vol = torch.nn.functional.avg_pool3d(torch.rand(1, 1, 24, 24, 24, generator=g), 5, 1, 2)
    gt = {"params": torch.tensor([[3.0, 0, 0, 0, 0, 0]])}
    batch = {"moving": vol.clone(), "fixed": vol.clone(), "rigid_params": gt, "moving_fov": torch.ones_like(vol)}
    inputs, targets = RegistrationPrepareBatch()(batch)
    assert inputs.shape == (1, 2, 24, 24, 24) and targets["params"].shape == (1, 6) and "mask" in targets
    pred = torch.zeros(1, 6, requires_grad=True)
    losses = {}
    for pool in (1, 2):
        crit = RegistrationCriterion((24, 24, 24), (4.0, 4.0, 4.0), RigidRegistrationLoss(w_sup=1.0),
                                     image_loss_pool=pool)
        total = crit(pred, targets)
        total.backward()
        losses[pool] = crit.last_terms
        # a pure 3 mm translation error: the supervised term is exactly 3 mm at any pooling
        assert crit.last_terms["sup"] == pytest.approx(3.0, abs=1e-5)
        assert crit.last_terms["ssim"] == pytest.approx(0.0, abs=1e-4)  # identical images at identity
    assert pred.grad is not None and pred.grad[0, 0] < 0  # increasing tx lowers the loss


def test_canonical_grid_is_origin_centred():
    g = canonical_grid((8, 8, 8), (4.0, 4.0, 4.0))
    np.testing.assert_allclose(g.center(), 0.0, atol=1e-12)


def test_registration_transforms_on_simulated_pairs(tiny_dataset):
    items = load_decathlon_datalist(str(tiny_dataset), is_segmentation=False, data_list_key="training")
    val = registration_transforms("val", (16, 16, 16), (8.0, 8.0, 8.0))
    d = val(items[0])
    # validation keeps the simulator's ground truth (re-expressed about the fixed centre, here the isocentre)
    np.testing.assert_allclose(d["rigid_params"]["params"].numpy(), items[0]["params"], atol=1e-3)
    assert set(d) <= {"moving", "fixed", "moving_fov", "rigid_params", "cbct_degradation", "case_id"}
    assert 0.0 <= float(d["fixed"].min()) and float(d["fixed"].max()) <= 1.0
    train = registration_transforms("train", (16, 16, 16), (8.0, 8.0, 8.0))
    train.set_random_state(0)
    d1 = train(items[0])
    assert not np.allclose(d1["rigid_params"]["params"].numpy(), items[0]["params"], atol=1e-2)  # extra motion
    assert Grid.from_metatensor(d1["moving"]).size == (16, 16, 16)
    batch = next(iter(DataLoader(Dataset(items, train), batch_size=2)))
    inputs, targets = RegistrationPrepareBatch()(batch)
    assert inputs.shape == (2, 2, 16, 16, 16) and targets["params"].shape == (2, 6)


def test_resume_handler_picks_newest(tmp_path):
    for n in (3, 12, 7):
        (tmp_path / f"checkpoint_checkpoint_epoch={n}.pt").write_bytes(b"")
    assert ResumeHandler(tmp_path, {}).latest().name == "checkpoint_checkpoint_epoch=12.pt"
    assert ResumeHandler(tmp_path / "none", {}).latest() is None


def test_plot_history(tmp_path):
    hist = [{"epoch": e, "loss_total": 10.0 / e, "loss_sup": 5.0 / e, "val_tx": 2.0 / e, "val_rx": 1.0 / e,
             "val_tre": 3.0 / e} for e in range(1, 5)]
    p = plot_history(hist, tmp_path / "c.png")
    assert p.stat().st_size > 10000


def test_resume_handler_starts_from_init_weights_unless_a_checkpoint_resumes(tmp_path):
    """Fine-tuning: ``init_weights`` loads the network (optimizer and schedule start afresh); a checkpoint to resume
    from wins over it; a missing file is refused at construction."""
    import torch
    from ignite.engine import Engine

    src, dst = torch.nn.Linear(3, 2), torch.nn.Linear(3, 2)
    torch.save(src.state_dict(), tmp_path / "init.pt")
    assert not torch.equal(src.weight, dst.weight)
    ResumeHandler(tmp_path / "ckpt", {"network": dst}, resume=False, init_weights=tmp_path / "init.pt").attach(
        Engine(lambda e, b: None))
    assert torch.equal(src.weight, dst.weight) and torch.equal(src.bias, dst.bias)
    # resume=True without a checkpoint: the init weights too
    other = torch.nn.Linear(3, 2)
    ResumeHandler(tmp_path / "none", {"network": other}, resume=True, init_weights=tmp_path / "init.pt").attach(
        Engine(lambda e, b: None))
    assert torch.equal(src.weight, other.weight)
    with pytest.raises(FileNotFoundError, match="init_weights"):
        ResumeHandler(tmp_path, {"network": dst}, init_weights=tmp_path / "missing.pt")


def test_resume_handler_partial_init_takes_only_matching_tensors(tmp_path):
    """``init_partial``: the tensors whose names and shapes match are taken (also from a training checkpoint's
    ``"network"``), the others keep their fresh values; strict loading refuses the same file; nothing matching is an
    error."""
    import torch
    from ignite.engine import Engine

    src = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.Linear(2, 4))
    dst = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.Linear(2, 5))  # the second layer changed shape
    before = dst[1].weight.detach().clone()
    torch.save({"network": src.state_dict(), "optimizer": {}}, tmp_path / "ckpt.pt")
    ResumeHandler(tmp_path / "none", {"network": dst}, resume=False, init_weights=tmp_path / "ckpt.pt",
                  init_partial=True).attach(Engine(lambda e, b: None))
    assert torch.equal(dst[0].weight, src[0].weight) and torch.equal(dst[0].bias, src[0].bias)
    assert torch.equal(dst[1].weight, before)
    with pytest.raises(RuntimeError, match="size mismatch"):
        ResumeHandler(tmp_path / "none", {"network": dst}, resume=False,
                      init_weights=tmp_path / "ckpt.pt").attach(Engine(lambda e, b: None))
    torch.save(torch.nn.Linear(7, 7).state_dict(), tmp_path / "other.pt")
    with pytest.raises(ValueError, match="no tensor matches"):
        ResumeHandler(tmp_path / "none", {"network": torch.nn.Conv1d(1, 1, 3)}, resume=False,
                      init_weights=tmp_path / "other.pt", init_partial=True).attach(Engine(lambda e, b: None))


@pytest.mark.parametrize("autocast, expected", [("bfloat16", 1.0), (None, 0.0)])
def test_progress_handler_records_the_encoders_training_precision(autocast, expected):
    """``TrainingProgressHandler(network=...)``: each epoch's metrics say whether a submodule trained under bfloat16
    autocast (``train_bfloat16``), beside the samples seen (batch size x iterations); without the network there is no
    such entry."""
    from ignite.engine import Engine

    from monai_rigidreg.engine import TrainingProgressHandler

    inner = torch.nn.Linear(2, 2)
    inner.train_autocast = autocast
    network = torch.nn.Sequential(torch.nn.Identity(), inner)
    for net in (network, None):
        engine = Engine(lambda e, b: 0.0)
        TrainingProgressHandler(batch_size=3, network=net).attach(engine)
        engine.run([0] * 5, max_epochs=2)
        assert engine.state.metrics["train_samples"] == 30.0
        if net is None:
            assert "train_bfloat16" not in engine.state.metrics
        else:
            assert engine.state.metrics["train_bfloat16"] == expected
