"""The output folder of a registration (monai_rigidreg.export.outputs with monai_rigidreg.io.staging): nothing lost,
nothing left behind (concurrent runs, overwrite, a failing write, SIGTERM), the note about registration.dcm.

Split from the former tests/test_reliability.py (same assertions).
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import in_main_thread, listing, run_cli, true_motion_registrar

from monai_rigidreg import registration
from monai_rigidreg.core.errors import OutputExistsError, Terminated
from monai_rigidreg.export import outputs
from monai_rigidreg.export.outputs import DEFAULT_OUTPUT_FILES, write_outputs
from monai_rigidreg.io import load_volume, staging


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


@pytest.fixture(scope="module")
def result(pair, small_registrar):
    """A result under the pair's true motion (the untrained network's estimate, the identity, would write zeros)."""
    fixed, moving = load_volume(pair["fixed"]), load_volume(pair["moving"])
    return true_motion_registrar(small_registrar, pair["params"])(fixed, moving, assess=False), fixed, moving


def test_registered_nii_follows_the_parameters_written_beside_it(pair, small_registrar, tmp_path):
    """The registrar's own resampling is written where it was made under the result's parameters; a result whose
    parameters were changed since (composed with a correction, say) gets registered.nii.gz under the new ones, not a
    stale image beside the new transform."""
    fixed, moving = load_volume(pair["fixed"]), load_volume(pair["moving"])
    res = small_registrar(fixed, moving, assess=False)
    assert res.registered is not None and res.registered_is_current()
    write_outputs(res, fixed, moving, tmp_path / "same", qc=False)
    as_made = sitk.GetArrayFromImage(res.registered)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(load_volume(tmp_path / "same" / "registered.nii.gz")),
                                  as_made)
    moved = np.asarray(pair["params"], dtype=np.float64)
    assert not dataclasses.replace(res, params=moved).registered_is_current()  # a copy with new parameters
    assert not dataclasses.replace(res, registered=sitk.Image(res.registered)).registered_is_current()
    res.params = moved
    assert not res.registered_is_current()
    write_outputs(res, fixed, moving, tmp_path / "moved", qc=False)
    written = sitk.GetArrayFromImage(load_volume(tmp_path / "moved" / "registered.nii.gz"))
    fill = float(sitk.GetArrayViewFromImage(moving).min())
    want = sitk.GetArrayFromImage(sitk.Resample(moving, fixed, res.transform, sitk.sitkLinear, fill))
    np.testing.assert_allclose(written, want, atol=1e-3)
    assert np.abs(written - as_made).max() > 100.0  # the motion shows in the image


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
    written = json.loads((out / "result.json").read_text())["params"]
    assert np.abs(res.params).min() > 0.5 and list(written.values()) == pytest.approx(res.params)


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


def test_qc_window_percentiles_are_numpys_without_numpy_ma():
    """The QC figure's window: ``np.percentile``'s numbers exactly (its linear interpolation, dtypes of CT volumes,
    the ends), computed without importing ``numpy.ma`` (a cost of the ``register`` command's start)."""
    import subprocess
    import sys

    import numpy as np

    from monai_rigidreg.export.qc_figure import percentiles

    rng = np.random.default_rng(0)
    for trial in range(60):
        a = rng.normal(0, 500, int(rng.integers(1, 3000))).astype((np.int16, np.float32, np.float64)[trial % 3])
        for q in ([1, 99], [0, 100], [50], [1.5, 97.25]):
            want, got = np.percentile(a, q), percentiles(a, q)
            assert np.array_equal(want, got) and want.dtype == got.dtype, (trial, q)
    code = ("import sys, numpy as np; from monai_rigidreg.export.qc_figure import percentiles; "
            "percentiles(np.arange(100, dtype=np.int16).reshape(4, 5, 5), [1, 99]); print('numpy.ma' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout == "False\n"
