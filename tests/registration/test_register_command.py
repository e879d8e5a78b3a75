"""``monai-rigidreg register`` at the boundary: bad input gets one line and exit 2, a flagged result exit 0 or 3,
an interrupted run leaves nothing (monai_rigidreg.registration.register_command).

Split from the former tests/test_reliability.py (same assertions).
"""

from __future__ import annotations

import json
import os
import signal
import time

import pytest
import SimpleITK as sitk
from conftest import constant_like, in_main_thread, last_line, listing, run_cli

from monai_rigidreg.export import outputs
from monai_rigidreg.io import load_volume
from monai_rigidreg.registration import confidence


def test_register_refuses_bad_input_with_one_line_and_no_debris(pair, tmp_path, with_small_network, capsys):
    work = tmp_path / "work"
    work.mkdir()
    a_file = work / "a_file.txt"
    a_file.write_text("keep me")
    zeros = work / "zeros.nii.gz"
    sitk.WriteImage(constant_like(load_volume(pair["moving"])), str(zeros))
    before = listing(work)
    base = ["register", "--fixed", pair["fixed"], "--moving", pair["moving"]]
    cases = [
        (base + ["--output-dir", a_file, "--overwrite"], "a_file.txt: already exists; refusing to overwrite it (it is "
                                                         "a file, not a folder"),
        (base + ["--output-dir", a_file / "out"], "a_file.txt: cannot create the output folder: this parent of it "
                                                  "is a file"),
        (base + ["--output-dir", work / ("x" * 256)], "an output folder name is longer than 255 bytes"),
        (base + ["--output-dir", work / "out", "--cascade-steps", "-1"], "cascade_steps must be a whole number >= 1, "
                                                                         "got -1"),
        (["register", "--fixed", work / "missing.nii.gz", "--moving", pair["moving"], "--output-dir", work / "out"],
         "missing.nii.gz: no such file or directory (the fixed image)"),
        (["register", "--fixed", pair["fixed"], "--moving", zeros, "--output-dir", work / "out"],
         "the moving (CBCT) image is constant (every voxel is 0): there is nothing to register"),
        (base + ["--output-dir", work / "out", "--roi", "1,2,3"], "an ROI box needs six finite numbers"),
        (base + ["--output-dir", work / "out", "--roi", "5000,5000,5000,5100,5100,5100"],
         "the region of interest does not overlap the CT"),
    ]
    for args, message in cases:
        code, err = run_cli(capsys, args)
        assert code == 2, (args, err)
        assert message in last_line(err) and last_line(err).startswith("monai-rigidreg register: error: "), err
        assert "Traceback" not in err
        assert listing(work) == before, args  # no output, no temporary folder
        assert a_file.read_text() == "keep me"


def test_flagged_result_exits_0_or_3_with_fail_on_flag(pair, tmp_path, with_small_network, small_registrar, capsys,
                                                      monkeypatch):
    args = ["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--no-qc"]
    monkeypatch.setattr(confidence, "CONFIDENCE_THRESHOLD", 1.01)  # every result flagged
    assert run_cli(capsys, [*args, "--output-dir", tmp_path / "a"])[0] == 0
    assert json.loads((tmp_path / "a" / "result.json").read_text())["flagged"] is True
    assert run_cli(capsys, [*args, "--output-dir", tmp_path / "b", "--fail-on-flag"])[0] == 3
    assert (tmp_path / "b" / "transform.tfm").is_file()  # the outputs are written either way
    # nothing flagged: the rule's limit below any score, and no calibration (the small test network's results are
    # not what the shipped calibration was fitted on)
    monkeypatch.setattr(confidence, "CONFIDENCE_THRESHOLD", -1.0)
    monkeypatch.setattr(small_registrar, "calibration", None)
    assert run_cli(capsys, [*args, "--output-dir", tmp_path / "c", "--fail-on-flag"])[0] == 0


@pytest.mark.parametrize("how", ["sigterm", "ctrl-c"])
def test_sigterm_or_ctrl_c_during_register_leaves_nothing(pair, tmp_path, with_small_network, monkeypatch, capsys,
                                                          how):
    in_main_thread()
    previous = signal.getsignal(signal.SIGTERM)

    def interrupted_while_writing(*args, **kwargs):
        if how == "sigterm":
            os.kill(os.getpid(), signal.SIGTERM)  # a real signal; the command's handler raises in this thread
            time.sleep(30)
        raise KeyboardInterrupt

    monkeypatch.setattr(outputs, "qc_figure", interrupted_while_writing)
    code, err = run_cli(capsys, ["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir",
                                 tmp_path / "new" / "out"])
    assert (code, last_line(err)) == ((143, "monai-rigidreg register: terminated") if how == "sigterm" else
                                      (130, "monai-rigidreg register: interrupted"))
    assert listing(tmp_path) == []  # no output, no hidden temporary folder, not even the parent it made
    assert signal.getsignal(signal.SIGTERM) == previous


def test_register_json_prints_one_json_object_on_stdout_and_the_log_on_stderr(fast_pair, tmp_path):
    """``register --json``: stdout is one JSON object (result.json's record and the output files by name), the log
    and warnings go to stderr; without it the summary is followed by a list of the files (for people)."""
    import subprocess
    import sys

    out = tmp_path / "out"
    argv = [sys.executable, "-m", "monai_rigidreg.cli", "register", "--fixed", str(fast_pair["fixed"]), "--moving",
            str(fast_pair["moving"]), "--output-dir", str(out), "--no-qc", "--device", "cpu", "--threads", "1"]
    done = subprocess.run([*argv, "--json"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    record = json.loads(done.stdout)  # the whole of stdout
    assert record == {**json.loads((out / "result.json").read_text()), "outputs": record["outputs"]}
    assert sorted(record["outputs"]) == ["TransformParameters.txt", "registered.nii.gz", "result.json",
                                         "transform.tfm"]
    assert all(os.path.isfile(p) for p in record["outputs"].values())
    assert {"params", "couch_shift", "confidence", "flagged", "provenance"} <= set(record)
    assert "INFO" in done.stderr and "registered" in done.stderr  # the log, on stderr
    human = subprocess.run([*argv, "--overwrite"], capture_output=True, text=True)
    assert human.returncode == 0 and "\noutputs:\n" in human.stdout and "transform.tfm" in human.stdout
