"""``monai-rigidreg train`` (monai_rigidreg.engine.train_command): bad options and an earlier run refused before
``monai.bundle`` starts.

Split from the former tests/test_reliability.py (same assertions).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import last_line, run_cli

ROOT = Path(__file__).resolve().parents[2]
BUNDLE = ROOT / "bundles" / "cbct_ct_rigid"


def test_train_refuses_bad_options_and_an_earlier_run_before_monai_bundle_starts(pair, tmp_path, capsys,
                                                                                monkeypatch):
    """Each bad option ends with one line and exit 2 before the bundle run starts (its errors are tracebacks), and
    a folder holding an earlier run needs --resume (a second run had replaced its model.pt and history.json)."""
    import subprocess as sp

    monkeypatch.setattr(sp, "call", lambda *a, **k: pytest.fail("monai.bundle started"))
    good = tmp_path / "train.json"
    good.write_text(json.dumps({"training": [{"fixed": pair["fixed"], "moving": pair["moving"]}]}))
    base = ["train", "--datalist", good, "--val-datalist", good, "--output-dir", tmp_path / "runs"]
    cases = [(["--epochs", "0"], "--epochs must be at least 1, got 0"),
             (["--epoch-length", "-3"], "--epoch-length must be at least 1"),
             (["--num-workers", "-1"], "--num-workers must be at least 0"),
             (["--learning-rate", "nan"], "--learning-rate must be a positive number, got nan"),
             (["--learning-rate", "-1"], "--learning-rate must be a positive number"),
             (["--device", "tpu7"], "device 'tpu7' is not a device name"),
             (["--bundle", tmp_path], "not a bundle: it has no configs/train.json"),
             (["--init-weights", good], "--init-weights: not a readable PyTorch checkpoint"),
             (["--set", "ckpt_dir=" + str(BUNDLE / "models")], "inside the installed monai-rigidreg package"),
             (["--set", "epochs"], "--set expects KEY=VALUE")]
    for extra, expected in cases:
        code, err = run_cli(capsys, [*base, *extra])
        assert code == 2 and expected in last_line(err), (extra, err)
        assert "Traceback" not in err
    for text, expected in (("{not json", "not valid JSON"), (json.dumps({"training": []}), "holds no cases"),
                           (json.dumps({"training": [{"moving": pair["moving"]}]}), "item 0 has no 'fixed'")):
        bad = tmp_path / "bad.json"
        bad.write_text(text)
        code, err = run_cli(capsys, ["train", "--datalist", bad, "--val-datalist", good, "--output-dir",
                                     tmp_path / "runs"])
        assert code == 2 and expected in last_line(err), err
    assert not (tmp_path / "runs").exists()
    # a training checkpoint (network, optimizer, ...) is not weights to start from; the validation datalist is read
    # under 'training', as train.json reads it
    import torch

    checkpoint = tmp_path / "checkpoint_checkpoint_epoch=1.pt"
    torch.save({"network": {"w": torch.zeros(2)}, "optimizer": {"state": {}}}, checkpoint)
    code, err = run_cli(capsys, [*base, "--init-weights", checkpoint])
    assert code == 2 and "--init-weights needs the network's weights" in last_line(err), err
    validation = tmp_path / "val.json"
    validation.write_text(json.dumps({"validation": [{"fixed": pair["fixed"], "moving": pair["moving"]}]}))
    code, err = run_cli(capsys, ["train", "--datalist", good, "--val-datalist", validation, "--output-dir",
                                 tmp_path / "runs"])
    assert code == 2 and "datalist has none of the keys ['training']" in last_line(err), err
    # --device auto leaves the bundle its own choice (torch.device('auto') would fail inside monai.bundle)
    from monai_rigidreg.cli import build_parser
    from monai_rigidreg.engine.train_command import bundle_command

    args = build_parser().parse_args([str(a) for a in [*base, "--device", "auto"]])
    assert "--device" not in bundle_command(args)
    args = build_parser().parse_args([str(a) for a in [*base, "--device", "cpu"]])
    assert bundle_command(args)[bundle_command(args).index("--device") + 1] == "$torch.device('cpu')"
    earlier = tmp_path / "runs" / "models"
    earlier.mkdir(parents=True)
    (earlier / "model.pt").write_bytes(b"an earlier run's weights")
    code, err = run_cli(capsys, base)
    assert code == 2 and "it holds an earlier training run (model.pt); pass --resume" in last_line(err), err
    assert (earlier / "model.pt").read_bytes() == b"an earlier run's weights"
