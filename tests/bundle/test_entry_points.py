"""The bundle's entry points (monai_rigidreg.bundle.entry_points): bad inputs end ``python -m monai.bundle run``
with one line and exit 2.

Split from the former tests/test_reliability.py (same assertions).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import last_line, listing

from monai_rigidreg.bundle import entry_points

ROOT = Path(__file__).resolve().parents[2]
BUNDLE = ROOT / "bundles" / "cbct_ct_rigid"


def test_bundle_check_inputs_ends_the_run_with_one_line(pair, tmp_path, capsys):
    missing = tmp_path / "missing.nii.gz"
    for fixed, message in [("", "no fixed image given"),
                           (missing, "missing.nii.gz: no such file or directory (the fixed image)")]:
        with pytest.raises(SystemExit) as info:
            entry_points.bundle_check_inputs(fixed, pair["moving"], tmp_path / "out")
        assert info.value.code == 2
        assert message in last_line(capsys.readouterr().err)
    with pytest.raises(SystemExit):
        entry_points.bundle_check_inputs(pair["fixed"], pair["moving"], tmp_path / "out", cascade_steps=0)
    assert "cascade_steps must be a whole number >= 1, got 0" in capsys.readouterr().err
    # the weights not where bundle_root says (the bundle run from elsewhere without --bundle_root): where to run it
    with pytest.raises(SystemExit) as info:
        entry_points.bundle_check_inputs(pair["fixed"], pair["moving"], tmp_path / "out",
                                         checkpoint="./models/model.pt")
    assert info.value.code == 2
    assert last_line(capsys.readouterr().err) == ("monai-rigidreg bundle: error: no network weights at "
                                                  f"./models/model.pt: {entry_points.WHERE_TO_RUN}")
    assert listing(tmp_path) == []


def test_monai_bundle_run_reports_bad_inputs_in_one_line(pair, tmp_path):
    """``python -m monai.bundle run`` on the shipped inference config: a missing --fixed (refused before the network
    is built), a corrupt one (refused when read) and a run from elsewhere without --bundle_root (the weights not
    found: where to run it from): exit 2, the message last, no traceback, no output folder."""
    corrupt = tmp_path / "corrupt.nii.gz"
    corrupt.write_bytes(b"\x00" * 100)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    root = ["--bundle_root", str(BUNDLE)]
    for extra, message in [([*root], "monai-rigidreg bundle: error: no fixed image given"),
                           ([*root, "--fixed", str(corrupt)], "corrupt.nii.gz: unreadable or corrupt image file"),
                           (["--fixed", pair["fixed"]], "no network weights at ./models/model.pt: --bundle_root must "
                                                        "name the bundle folder")]:
        proc = subprocess.run([sys.executable, "-m", "monai.bundle", "run", "--config_file",
                               str(BUNDLE / "configs" / "inference.json"),
                               "--moving", pair["moving"], "--output_dir", str(tmp_path / "out"), "--device",
                               "$torch.device('cpu')", *extra], cwd=tmp_path, capture_output=True, text=True,
                              encoding="utf-8", errors="replace",
                              timeout=300, env=env)
        assert proc.returncode == 2, proc.stderr[-3000:]
        assert message in last_line(proc.stderr) and "Traceback" not in proc.stderr, proc.stderr[-3000:]
        assert not (tmp_path / "out").exists()
