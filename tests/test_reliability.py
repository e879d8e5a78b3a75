"""Reliability at the boundary: every bad input gets one clear line and a documented exit status, nothing is left
behind or replaced (failures, Ctrl-C, SIGTERM, two runs into one folder), and geometry is never silently wrong.

Small volumes throughout (the register command runs a random-weight network on a 32^3 grid); the bundle is run in a
subprocess twice (MONAI's own command line).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import TINY_SIM, small_registrar_for_tests, write_dicom_series

from monai_rigidreg import outputs, registration, staging
from monai_rigidreg.cli import EXIT_CODES, main
from monai_rigidreg.errors import InputError, OutputExistsError, Terminated
from monai_rigidreg.io import list_dicom_series, load_volume
from monai_rigidreg.outputs import DEFAULT_OUTPUT_FILES, write_outputs
from monai_rigidreg.registration import RigidRegistrar

ROOT = Path(__file__).resolve().parents[1]
BUNDLE = ROOT / "bundles" / "cbct_ct_rigid"


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    from monai_rigidreg.simulation import simulate_pair

    return simulate_pair(tmp_path_factory.mktemp("pair"), phantom="shepp-logan-asym", params=[4, -3, 2, 2, -1, 3],
                         seed=3, device="cpu", **{k: v for k, v in TINY_SIM.items() if k != "preset"})


@pytest.fixture(scope="module")
def small_registrar():
    return small_registrar_for_tests(cascade_steps=1)


@pytest.fixture
def with_small_network(monkeypatch, small_registrar):
    """The register command with the small network instead of the shipped bundle."""
    monkeypatch.setattr(RigidRegistrar, "from_bundle", classmethod(lambda cls, *a, **k: small_registrar))


def listing(root: Path) -> list[str]:
    """Every path under ``root`` (hidden ones included), relative, sorted."""
    return sorted(str(p.relative_to(root)) for p in Path(root).rglob("*"))


def run_cli(capsys, args: list[str]) -> tuple[int, str]:
    code = main([str(a) for a in args])
    return code, capsys.readouterr().err


def last_line(err: str) -> str:
    lines = err.strip().splitlines()
    return lines[-1] if lines else ""


def constant_like(image: sitk.Image, value: float = 0.0) -> sitk.Image:
    out = sitk.Image(image.GetSize(), sitk.sitkFloat32)
    out.CopyInformation(image)
    return out + value


def in_main_thread() -> None:
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals reach the main thread only")


# ---------------------------------------------------------------------------------------------------------------
# register: bad input -> exit 2, one line naming the problem, nothing written or changed
# ---------------------------------------------------------------------------------------------------------------
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


def test_bad_device_strings_are_refused_before_any_work(pair, tmp_path, capsys):
    out = tmp_path / "out"
    for args in (["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir", out],
                 ["demo", "--output-dir", out]):
        code, err = run_cli(capsys, [*args, "--device", "gpu7"])
        assert code == 2 and "device 'gpu7' is not a device name (use auto, cpu, cuda or cuda:N)" in last_line(err)
        assert "Traceback" not in err
    datalist = tmp_path / "one.json"
    datalist.write_text(json.dumps({"training": [{"fixed": pair["fixed"], "moving": pair["moving"],
                                                  "params": [0.0] * 6}]}))
    code, err = run_cli(capsys, ["evaluate", "--datalist", datalist, "--output-dir", out, "--device", "gpu7"])
    assert code == 2 and "'gpu7' is not a device name" in last_line(err)
    assert listing(tmp_path) == ["one.json"]


def test_constant_inputs_are_refused_naming_which(pair, small_registrar):
    fixed, moving = load_volume(pair["fixed"]), load_volume(pair["moving"])
    with pytest.raises(InputError, match=r"the moving \(CBCT\) image is constant \(every voxel is 0\)"):
        small_registrar(fixed, constant_like(moving))
    with pytest.raises(InputError, match=r"the fixed \(CT\) image is constant \(every voxel is -1000\)"):
        small_registrar(constant_like(fixed, -1000.0), moving)


@pytest.mark.parametrize(("pixel", "lo", "hi"), [(sitk.sitkUInt8, 0, 255), (sitk.sitkInt8, -128, 127)])
def test_integer_cbct_registers_with_a_warning_naming_its_range(pair, tmp_path, with_small_network, capsys, caplog,
                                                               pixel, lo, hi):
    small = tmp_path / "cbct_preview.nii.gz"
    sitk.WriteImage(sitk.Cast(sitk.RescaleIntensity(load_volume(pair["moving"]), lo, hi), pixel), str(small))
    out = tmp_path / "out"
    with caplog.at_level("WARNING", logger="monai_rigidreg.registration"):
        code, err = run_cli(capsys, ["register", "--fixed", pair["fixed"], "--moving", small, "--output-dir", out])
    assert code == 0, err
    expected = f"the moving (CBCT) image's intensities range from {lo} to {hi}, which is not HU"
    assert expected in caplog.text
    result = json.loads((out / "result.json").read_text())
    assert [w for w in result["details"]["warnings"] if expected in w]
    assert not any("fixed" in w for w in result["details"]["warnings"])  # the CT is in HU
    # flagged whatever the signals say (they are calibrated on HU), naming the image
    assert result["flagged"] is True and result["confidence"] == 0.0
    assert result["details"]["signals"]["not_hu"] == ["moving (CBCT)"]


@pytest.mark.parametrize("damage", ["gz_cut", "gz_damaged", "nii_cut"])
def test_a_truncated_or_damaged_nifti_is_refused_before_registering(pair, tmp_path, with_small_network, capsys,
                                                                   damage):
    """ITK reads an integer NIfTI whose end is missing (or whose compressed data is damaged) without an error and
    fills what it lacks with zeros; registered, a real CBCT cut in half came out about 100 mm off with confidence
    0.83. The completeness check (monai_rigidreg.prefetch.check_nifti_complete) refuses it: exit 2, nothing written."""
    cbct = sitk.Cast(load_volume(pair["moving"]), sitk.sitkInt16)
    if damage == "nii_cut":
        path = tmp_path / "cbct.nii"
        sitk.WriteImage(cbct, str(path), False)
        raw = path.read_bytes()
        path.write_bytes(raw[: len(raw) * 9 // 10])
        expected = "truncated: "
    else:
        path = tmp_path / "cbct.nii.gz"
        sitk.WriteImage(cbct, str(path), True)
        raw = bytearray(path.read_bytes())
        if damage == "gz_cut":
            raw = raw[: len(raw) * 3 // 4]
            expected = "its compressed data ends early: the file is truncated"
        else:  # bytes changed in the middle: the deflate stream or the CRC-32 says so (and ITK may or may not)
            mid = len(raw) // 2
            raw[mid: mid + 8] = bytes(b ^ 0x5A for b in raw[mid: mid + 8])
            expected = ""
        path.write_bytes(bytes(raw))
    if damage != "gz_damaged":
        assert sitk.ReadImage(str(path)).GetSize() == cbct.GetSize()  # what ITK does alone: no error
    out = tmp_path / "out"
    code, err = run_cli(capsys, ["register", "--fixed", pair["fixed"], "--moving", path, "--output-dir", out])
    assert code == 2 and "unreadable or corrupt image file" in last_line(err) and expected in last_line(err), err
    assert str(path) in last_line(err) and "Traceback" not in err and not out.exists()


def test_roi_masks_that_are_not_a_3d_mask_are_refused_naming_the_problem(pair, tmp_path, with_small_network, capsys):
    masks = {"flat.nii.gz": (sitk.Image([8, 8], sitk.sitkUInt8) + 1, "the ROI mask: expected a 3D volume, got a 2D"),
             "four_d.nii.gz": (sitk.GetImageFromArray(np.ones((2, 6, 6, 6), np.uint8), isVector=False),
                               "the ROI mask: expected a 3D volume, got a 4D"),
             "blank.nii.gz": (sitk.Image([8, 8, 8], sitk.sitkUInt8), "the ROI mask is empty (no non-zero voxel)"),
             "zero_bytes.nii.gz": (None, "the ROI mask: unreadable or corrupt image file (Unable to determine")}
    out = tmp_path / "out"
    base = ["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir", out]
    for name, (image, expected) in masks.items():
        path = tmp_path / name
        if image is None:
            path.write_bytes(b"")
        else:
            sitk.WriteImage(image, str(path))
        code, err = run_cli(capsys, [*base, "--roi", path])
        assert code == 2 and expected in last_line(err) and name in last_line(err), err
        assert "Traceback" not in err and not out.exists()
    code, err = run_cli(capsys, [*base, "--roi", tmp_path / "missing.nii.gz"])
    assert code == 2 and "got '" in last_line(err) and "no such file, and not six numbers" in last_line(err)


def test_an_output_folder_that_cannot_be_written_is_refused_before_anything_is_read(pair, tmp_path, capsys,
                                                                                   with_small_network, monkeypatch):
    """Found by access(2) up front (it sees read-only mounts and immutable folders, even for root), not after the
    registration with a wrong reason; here access(2) is made to answer no for one folder, and any read fails the
    test."""
    from monai_rigidreg import io

    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = os.access
    monkeypatch.setattr(io.os, "access", lambda p, mode, **kw: False if Path(p) == locked else real_access(p, mode,
                                                                                                         **kw))
    monkeypatch.setattr(outputs, "load_volume", lambda *a, **k: pytest.fail("read before the output check"))
    base = ["register", "--fixed", pair["fixed"], "--moving", pair["moving"]]
    code, err = run_cli(capsys, [*base, "--output-dir", locked])
    assert code == 2 and last_line(err).endswith(f"{locked}: the output folder is not writable"), err
    code, err = run_cli(capsys, [*base, "--output-dir", locked / "sub"])
    assert code == 2 and f"cannot create the output folder: {locked} is not writable" in last_line(err), err
    assert listing(tmp_path) == ["locked"]
    # a link to a folder elsewhere: staging replaces the folder where it lies, so the link's own parent is not asked
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    link = locked / "link"
    link.symlink_to(elsewhere)
    from monai_rigidreg.io import check_output_dir

    assert check_output_dir(link) == link
    (elsewhere / "inner").mkdir()
    with pytest.raises(InputError, match="cannot create the output folder: .*locked is not writable"):
        check_output_dir(locked / "new")


def test_an_immutable_output_folder_is_refused_up_front(pair, tmp_path, with_small_network, capsys):
    """The same with a real immutable folder (chattr +i; root may write anywhere else), where the file system and
    the user allow setting it."""
    import shutil

    locked = tmp_path / "locked"
    locked.mkdir()
    if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(locked)], capture_output=True).returncode:
        pytest.skip("chattr +i is not available here (needs root and a file system with the immutable flag)")
    try:
        t = time.perf_counter()
        code, err = run_cli(capsys, ["register", "--fixed", pair["fixed"], "--moving", pair["moving"],
                                     "--output-dir", locked / "sub"])
        assert code == 2 and f"{locked} is not writable" in last_line(err), err
        code, err = run_cli(capsys, ["register", "--fixed", pair["fixed"], "--moving", pair["moving"],
                                     "--output-dir", locked])
        assert code == 2 and "the output folder is not writable" in last_line(err), err
        assert time.perf_counter() - t < 5.0  # no registration ran
    finally:
        subprocess.run(["chattr", "-i", str(locked)], check=True)
    assert listing(tmp_path) == ["locked"]


def test_the_note_that_no_reg_is_written_comes_only_with_written_outputs(pair, tmp_path, with_small_network, capsys,
                                                                          caplog):
    bad = tmp_path / "nan.nii.gz"
    image = load_volume(pair["moving"])
    image[2, 3, 4] = float("nan")
    sitk.WriteImage(image, str(bad))
    with caplog.at_level("INFO", logger="monai_rigidreg"):
        assert run_cli(capsys, ["register", "--fixed", pair["fixed"], "--moving", bad, "--output-dir",
                                tmp_path / "a"])[0] == 2
    assert "no DICOM Spatial Registration" not in caplog.text  # a refused run says nothing about outputs
    caplog.clear()
    with caplog.at_level("INFO", logger="monai_rigidreg"):
        assert run_cli(capsys, ["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--no-qc",
                                "--output-dir", tmp_path / "b"])[0] == 0
    messages = [r.getMessage() for r in caplog.records]
    note = [i for i, m in enumerate(messages) if m.startswith("no DICOM Spatial Registration")]
    done = [i for i, m in enumerate(messages) if m.startswith("registered ")]
    assert len(note) == 1 and len(done) == 1 and note[0] < done[0]


def test_a_fixed_image_inside_a_larger_moving_one_gets_a_swapped_inputs_warning(pair, small_registrar):
    """A CBCT given as --fixed and the CT as --moving registers (the inverse transform, couch shifts of the wrong
    sign) with a warning in the result; the usual order gets none. On the clinical-geometry and paper-protocol
    benchmark pairs the rule never fires in the usual order (``python benchmarks/bench_damaged_inputs.py``, last
    line: 102 pairs, bench_damaged_inputs_0.4.9_2026-12-03.txt)."""
    ct = load_volume(pair["fixed"])
    nx, ny, nz = ct.GetSize()
    inner = ct[nx // 4: 3 * nx // 4, ny // 4: 3 * ny // 4, nz // 4: 3 * nz // 4]  # keeps its physical place
    swapped = small_registrar(inner, ct, assess=False, resample_moving=False)
    assert [w for w in swapped.details.get("warnings", []) if "the fixed image lies inside the moving one" in w]
    usual = small_registrar(ct, inner, assess=False, resample_moving=False)
    assert not [w for w in usual.details.get("warnings", []) if "lies inside" in w]


def test_a_ct_without_air_is_warned_about_but_not_flagged_by_rule(pair, small_registrar):
    """A CT cropped to the body has no air, yet is in HU: a warning, but no forced flag (only ranges that are
    certainly not HU are flagged: no negative value, or an 8-bit span)."""
    from monai_rigidreg.registration import not_hu

    assert not_hu(0, 4095) and not_hu(0, 255) and not_hu(-128, 127) and not_hu(0.0, 1.0)
    assert not not_hu(-110, 1100) and not not_hu(-1000, 2000)
    ct = load_volume(pair["fixed"])
    cropped = sitk.Clamp(ct, lowerBound=-110.0, upperBound=3000.0)  # as if the air were cut away
    result = small_registrar(cropped, load_volume(pair["moving"]), resample_moving=False)
    assert [w for w in result.details.get("warnings", []) if "the fixed (CT) image holds no air" in w]
    assert "not_hu" not in result.details["signals"]


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
    from monai_rigidreg.engine.cli import bundle_command

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


def test_flagged_result_exits_0_or_3_with_fail_on_flag(pair, tmp_path, with_small_network, capsys, monkeypatch):
    args = ["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--no-qc"]
    monkeypatch.setattr(registration, "CONFIDENCE_THRESHOLD", 1.01)  # every result flagged
    assert run_cli(capsys, [*args, "--output-dir", tmp_path / "a"])[0] == 0
    assert json.loads((tmp_path / "a" / "result.json").read_text())["flagged"] is True
    assert run_cli(capsys, [*args, "--output-dir", tmp_path / "b", "--fail-on-flag"])[0] == 3
    assert (tmp_path / "b" / "transform.tfm").is_file()  # the outputs are written either way
    monkeypatch.setattr(registration, "CONFIDENCE_THRESHOLD", -1.0)  # nothing flagged
    assert run_cli(capsys, [*args, "--output-dir", tmp_path / "c", "--fail-on-flag"])[0] == 0


# ---------------------------------------------------------------------------------------------------------------
# Nothing lost, nothing left behind: concurrent runs, overwrite, Ctrl-C, SIGTERM
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def result(pair, small_registrar):
    fixed, moving = load_volume(pair["fixed"]), load_volume(pair["moving"])
    return small_registrar(fixed, moving, assess=False), fixed, moving


@pytest.mark.parametrize("start", ["absent", "empty"])
@pytest.mark.parametrize("rename", ["renameat2", "fallback"])
def test_a_folder_another_run_filled_meanwhile_is_never_replaced(result, tmp_path, monkeypatch, start, rename):
    res, fixed, moving = result
    if rename == "fallback":
        monkeypatch.setattr(staging, "_renameat2", lambda: None)
    else:
        assert staging._renameat2() is not None  # Linux/glibc: the kernel refuses to replace
    out = tmp_path / "new" / "out"
    if start == "empty":
        out.mkdir(parents=True)

    def other_run_finishes_first(*args, **kwargs):  # the QC figure is the last step before the final move
        out.mkdir(parents=True, exist_ok=True)
        (out / "result.json").write_text("the other run's result")

    monkeypatch.setattr(outputs, "qc_figure", other_run_finishes_first)
    with pytest.raises(OutputExistsError, match="another process"):
        write_outputs(res, fixed, moving, out)
    assert listing(tmp_path) == ["new", "new/out", "new/out/result.json"]
    assert (out / "result.json").read_text() == "the other run's result"


def test_two_runs_into_one_new_folder_one_wins_and_nothing_is_deleted(result, tmp_path, monkeypatch):
    res, fixed, moving = result
    out = tmp_path / "out"
    barrier = threading.Barrier(2)

    def qc(fixed, moving, registered, path, **kwargs):  # both runs have checked the folder and written everything
        barrier.wait(timeout=60)
        Path(path).write_bytes(b"png")

    monkeypatch.setattr(outputs, "qc_figure", qc)
    ends: list[str] = []

    def run() -> None:
        try:
            write_outputs(res, fixed, moving, out)
            ends.append("written")
        except OutputExistsError:
            ends.append("refused")

    threads = [threading.Thread(target=run) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert sorted(ends) == ["refused", "written"]
    assert listing(tmp_path) == sorted(["out", *(f"out/{n}" for n in DEFAULT_OUTPUT_FILES)])
    assert json.loads((out / "result.json").read_text())["params"]["tx"] == pytest.approx(res.params[0])


def test_overwrite_replaces_the_old_folder_only_once_the_new_one_is_complete(result, tmp_path, monkeypatch):
    res, fixed, moving = result
    out = tmp_path / "out"
    write_outputs(res, fixed, moving, out, qc=False)
    umask = os.umask(0o022)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o777 & ~umask  # a normal folder, not tempfile.mkdtemp's 0700
    old = {p.name: p.read_bytes() for p in out.iterdir()}

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(outputs, "qc_figure", disk_full)
    with pytest.raises(OSError, match="No space left"):
        write_outputs(res, fixed, moving, out, overwrite=True)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == old  # the old folder is untouched
    assert listing(tmp_path) == sorted(["out", *(f"out/{n}" for n in old)])  # and nothing else is there
    moved = registration.RegistrationResult(res.params + 1.0, res.center, None, res.timings)
    write_outputs(moved, fixed, moving, out, overwrite=True, qc=False)
    assert json.loads((out / "result.json").read_text())["params"]["tx"] == pytest.approx(res.params[0] + 1.0)
    assert listing(tmp_path) == sorted(["out", *(f"out/{n}" for n in old)])  # no aside or temporary folder left


def test_a_failing_volume_write_in_its_worker_leaves_nothing(result, tmp_path, monkeypatch):
    """registered.nii.gz is written in a worker thread while the QC figure is drawn: its failure reaches the caller
    after the figure, and no output or temporary folder is left; the figure's own failure waits for the worker."""
    res, fixed, moving = result
    out = tmp_path / "out"
    drawn = []

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    real_qc = outputs.qc_figure
    monkeypatch.setattr(outputs, "save_volume", disk_full)
    monkeypatch.setattr(outputs, "qc_figure", lambda *a, **k: (drawn.append(1), real_qc(*a, **k)))
    with pytest.raises(OSError, match="No space left"):
        write_outputs(res, fixed, moving, out)
    assert drawn == [1] and listing(tmp_path) == []
    written = []

    def slow_save(image, path):
        import time

        time.sleep(0.3)
        written.append(path.name)

    def qc_fails(*args, **kwargs):
        raise RuntimeError("figure failed")

    monkeypatch.setattr(outputs, "save_volume", slow_save)
    monkeypatch.setattr(outputs, "qc_figure", qc_fails)
    with pytest.raises(RuntimeError, match="figure failed"):
        write_outputs(res, fixed, moving, out)
    assert written == ["registered.nii.gz"] and listing(tmp_path) == []  # joined before the folder was removed


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


def test_sigterm_while_writing_outputs_from_python_cleans_up(result, tmp_path, monkeypatch):
    """Library use (and the bundle): write_outputs turns SIGTERM into cleanup where nothing else handles it."""
    in_main_thread()
    res, fixed, moving = result
    previous = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        monkeypatch.setattr(outputs, "qc_figure", lambda *a, **k: (os.kill(os.getpid(), signal.SIGTERM),
                                                                   time.sleep(30)))
        with pytest.raises(Terminated):
            write_outputs(res, fixed, moving, tmp_path / "out")
        assert listing(tmp_path) == []
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_a_failed_demo_leaves_nothing(tmp_path, monkeypatch, capsys):
    from monai_rigidreg.simulation import pair as pair_module

    def simulated_then_failed(output_dir, **kwargs):
        Path(output_dir).mkdir(parents=True)
        (Path(output_dir) / "simct.nii.gz").write_bytes(b"half a volume")
        raise InputError("the simulation failed")

    monkeypatch.setattr(pair_module, "simulate_pair", simulated_then_failed)
    code, err = run_cli(capsys, ["demo", "--output-dir", tmp_path / "new" / "demo", "--device", "cpu"])
    assert (code, last_line(err)) == (2, "monai-rigidreg demo: error: the simulation failed")
    assert listing(tmp_path) == []


# ---------------------------------------------------------------------------------------------------------------
# simulate, evaluate: validated before anything is written
# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad", ["corrupt", "2d"])
def test_simulate_with_an_unusable_phantom_writes_nothing(tmp_path, capsys, bad):
    phantom = tmp_path / f"{bad}.nii.gz"
    if bad == "corrupt":
        phantom.write_bytes(b"not a NIfTI file" * 20)
        message = "unreadable or corrupt image file"
    else:
        sitk.WriteImage(sitk.Image(16, 16, sitk.sitkInt16), str(phantom))
        message = "expected a 3D volume, got a 2D image"
    empty = tmp_path / "empty"
    empty.mkdir()
    for out in (tmp_path / "new" / "sim", empty):
        code, err = run_cli(capsys, ["simulate", "--output-dir", out, "--phantom", phantom, "--device", "cpu",
                                     "--no-progress"])
        assert code == 2 and f"{phantom.name}: {message}" in last_line(err), err
    assert listing(tmp_path) == [f"{bad}.nii.gz", "empty"]  # no simulation.json, no new folders


def test_simulate_failing_before_any_volume_leaves_no_trace(tmp_path, monkeypatch):
    from monai_rigidreg.simulation import dataset

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(dataset, "write_simct", interrupted)
    with pytest.raises(KeyboardInterrupt):
        dataset.simulate_dataset(tmp_path / "new" / "sim", num_cases=1, progress=False, device="cpu", **TINY_SIM)
    assert listing(tmp_path) == []


def test_evaluate_refuses_an_empty_datalist_and_a_bad_max_cases(pair, tmp_path, capsys):
    empty = tmp_path / "empty.json"
    empty.write_text(json.dumps({"training": []}))
    code, err = run_cli(capsys, ["evaluate", "--datalist", empty, "--output-dir", tmp_path / "eval"])
    assert code == 2 and "empty.json: datalist key 'training' holds no cases" in last_line(err)
    one = tmp_path / "one.json"
    one.write_text(json.dumps({"training": [{"fixed": pair["fixed"], "moving": pair["moving"], "params": [0] * 6}]}))
    code, err = run_cli(capsys, ["evaluate", "--datalist", one, "--output-dir", tmp_path / "eval", "--max-cases", "0"])
    assert code == 2 and "max_cases must be a whole number >= 1, got 0" in last_line(err)
    assert listing(tmp_path) == ["empty.json", "one.json"]


# ---------------------------------------------------------------------------------------------------------------
# exit codes: documented, and the same scheme for usage errors and internal failures
# ---------------------------------------------------------------------------------------------------------------
def test_exit_codes_are_documented_in_every_help_and_the_readme(capsys):
    for command in ("simulate", "train", "register", "evaluate", "demo"):
        with pytest.raises(SystemExit) as info:
            main([command, "--help"])
        assert info.value.code == 0
        text = " ".join(capsys.readouterr().out.split())
        for code in EXIT_CODES:
            assert f" {code} " in text.split("exit status:")[1], (command, code)
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme.split("### Exit codes", 1)[1].split("\n#", 1)[0]
    for code in EXIT_CODES:
        assert f"| {code} |" in section, code
    assert main([]) == 2  # no command: a usage error, as argparse's own
    with pytest.raises(SystemExit) as info:
        main(["register", "--fixed"])
    assert info.value.code == 2


def test_internal_failures_are_one_line_with_exit_1_and_file_system_errors_exit_2(monkeypatch, capsys):
    import monai_rigidreg.register_cli as register_cli

    args = ["register", "--fixed", "ct", "--moving", "cbct", "--output-dir", "out"]

    def bug(_):
        raise ZeroDivisionError("float division by zero")

    monkeypatch.setattr(register_cli, "run", bug)
    code, err = run_cli(capsys, args)
    assert code == 1 and "Traceback" not in err
    assert last_line(err).startswith("monai-rigidreg register: internal error: ZeroDivisionError: float division by "
                                     "zero (a bug; rerun with -v")
    code, err = run_cli(capsys, ["-v", *args])
    assert code == 1 and "Traceback" in err

    def denied(_):
        raise PermissionError(13, "Permission denied", "/data/out")

    monkeypatch.setattr(register_cli, "run", denied)
    code, err = run_cli(capsys, args)
    assert (code, last_line(err)) == (2, "monai-rigidreg register: error: /data/out: Permission denied")


# ---------------------------------------------------------------------------------------------------------------
# the bundle: the same checks, one line, exit 2
# ---------------------------------------------------------------------------------------------------------------
def test_bundle_check_inputs_ends_the_run_with_one_line(pair, tmp_path, capsys):
    missing = tmp_path / "missing.nii.gz"
    for fixed, message in [("", "no fixed image given"),
                           (missing, "missing.nii.gz: no such file or directory (the fixed image)")]:
        with pytest.raises(SystemExit) as info:
            outputs.bundle_check_inputs(fixed, pair["moving"], tmp_path / "out")
        assert info.value.code == 2
        assert message in last_line(capsys.readouterr().err)
    with pytest.raises(SystemExit):
        outputs.bundle_check_inputs(pair["fixed"], pair["moving"], tmp_path / "out", cascade_steps=0)
    assert "cascade_steps must be a whole number >= 1, got 0" in capsys.readouterr().err
    assert listing(tmp_path) == []


def test_monai_bundle_run_reports_bad_inputs_in_one_line(pair, tmp_path):
    """``python -m monai.bundle run`` on the shipped inference config: a missing --fixed (refused before the network
    is built) and a corrupt one (refused when read): exit 2, the message last, no traceback, no output folder."""
    corrupt = tmp_path / "corrupt.nii.gz"
    corrupt.write_bytes(b"\x00" * 100)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    for extra, message in [([], "monai-rigidreg bundle: error: no fixed image given"),
                           (["--fixed", str(corrupt)], "corrupt.nii.gz: unreadable or corrupt image file")]:
        proc = subprocess.run([sys.executable, "-m", "monai.bundle", "run", "--config_file",
                               str(BUNDLE / "configs" / "inference.json"), "--bundle_root", str(BUNDLE),
                               "--moving", pair["moving"], "--output_dir", str(tmp_path / "out"), "--device",
                               "$torch.device('cpu')", *extra], cwd=tmp_path, capture_output=True, text=True,
                              encoding="utf-8", errors="replace",
                              timeout=300, env=env)
        assert proc.returncode == 2, proc.stderr[-3000:]
        assert message in last_line(proc.stderr) and "Traceback" not in proc.stderr, proc.stderr[-3000:]
        assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------------------------------------------
# geometry: a DICOM series with a missing slice registers like the complete series
# ---------------------------------------------------------------------------------------------------------------
def test_dicom_ct_with_a_missing_slice_registers_like_the_complete_series(fast_pair, tmp_path):
    # the shipped network (deterministic on the CPU; SimpleITK's Mattes MI refinement varies with its thread count)
    registrar = RigidRegistrar.from_bundle(device="cpu")
    uid = "1.2.826.0.1.3680043.2.1125.55"
    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    d = tmp_path / "ct"
    write_dicom_series(fixed, d, uid)
    complete = registrar(load_volume(d), moving, assess=False, resample_moving=False).params
    Path(list_dicom_series(d)[uid][fixed.GetSize()[2] // 2 + 3]).unlink()  # a slice inside the body
    gapped = registrar(load_volume(d), moving, assess=False, resample_moving=False).params
    assert np.abs(gapped[:3] - complete[:3]).max() < 0.5  # mm
    assert np.abs(gapped[3:] - complete[3:]).max() < 0.5  # degrees
