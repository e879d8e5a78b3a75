"""The README's main-job command: ``monai-rigidreg demo`` simulates, registers with the shipped weights, reports."""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk

from monai_rigidreg.cli import main
from monai_rigidreg.demo import DEMO_MOTION, run_demo
from monai_rigidreg.errors import OutputExistsError
from monai_rigidreg.io import read_transform


def test_demo_recovers_the_known_motion_with_the_shipped_weights(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--output-dir", str(out), "--device", "cpu"]) == 0
    printed = capsys.readouterr().out
    assert "target registration error" in printed and "transform.tfm" in printed
    report = json.loads((out / "demo.json").read_text())
    assert list(report["true"].values()) == list(DEMO_MOTION)
    # the shipped network at the demo's 2 mm grids: sub-millimetre, confident, within 0.5 mm / 1 degree per axis
    assert report["tre_mm"] < 1.0 and report["confidence"] >= 0.5, report
    err = np.array(list(report["abs_error"].values()))
    assert np.all(err[:3] < 0.5) and np.all(err[3:] < 1.0), report["abs_error"]
    for name in ("transform.tfm", "registered.nii.gz", "result.json", "qc.png"):
        assert (out / "registration" / name).is_file(), name
    tfm = read_transform(out / "registration" / "transform.tfm")
    np.testing.assert_allclose(tfm.GetParameters()[3:], list(report["pred"].values())[:3], atol=1e-3)
    assert sitk.ReadImage(str(out / "data" / "simct.nii.gz")).GetSize() == (128, 128, 128)
    # an existing output folder is refused (exit status != 0, a message) and left as it was
    before = (out / "demo.json").read_text()
    assert main(["demo", "--output-dir", str(out), "--device", "cpu"]) != 0
    assert "exists" in capsys.readouterr().err.lower()
    assert (out / "demo.json").read_text() == before
    with pytest.raises(OutputExistsError):
        run_demo(out)
