"""``monai-rigidreg simulate`` (monai_rigidreg.simulation.simulate_command): an unusable phantom or an early
failure leaves no trace; a pair simulated from a CT keeps the CT's frame; ``--motion``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import KNOWN_MOTION, TINY_SIM, last_line, listing, run_cli


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


CT_CENTRE = np.array([35.0, -60.0, 110.0])
"""Where the test's input CT lies (LPS mm): far from the origin, where the simulation used to put every pair."""


@pytest.fixture(scope="module")
def ct_file(fast_pair, tmp_path_factory):
    """A CT file centred on :data:`CT_CENTRE`: the fast pair's Sim-CT (Sim-CT 64^3 at 4 mm) moved there."""
    ct = sitk.ReadImage(fast_pair["fixed"])
    size = np.asarray(ct.GetSize(), dtype=float)
    centre = np.asarray(ct.TransformContinuousIndexToPhysicalPoint(((size - 1) / 2).tolist()))
    ct.SetOrigin(tuple(np.asarray(ct.GetOrigin()) + CT_CENTRE - centre))
    path = tmp_path_factory.mktemp("ct") / "planning_ct.nii.gz"
    sitk.WriteImage(ct, str(path))
    return path


def test_a_pair_simulated_from_a_ct_registers_against_that_ct_to_the_recorded_motion(ct_file, tmp_path, capsys):
    """``simulate --phantom CT --motion ...`` keeps the CT's frame: registered against the input CT itself (not the
    Sim-CT), the CBCT gives the recorded motion about the recorded centre. Before 0.5 the pair was centred on the
    origin, and this registration reported the CT's offset from the origin as motion (ty -82 mm against 3 mm)."""
    import monai_rigidreg

    out = tmp_path / "sim"
    code, err = run_cli(capsys, ["simulate", "--output-dir", out, "--phantom", ct_file, "--motion", *KNOWN_MOTION,
                                 "--device", "cpu", "--no-progress"])
    assert code == 0, err
    dataset = json.loads((out / "dataset.json").read_text())
    assert "input CT's frame" in dataset["frame"]
    np.testing.assert_allclose(dataset["frame_offset_mm"], CT_CENTRE, atol=1e-6)
    (item,) = dataset["training"]
    assert item["params"] == KNOWN_MOTION and item["group"] == "given"
    np.testing.assert_allclose(item["center"], CT_CENTRE, atol=1e-6)
    for key in ("fixed", "moving"):
        image = sitk.ReadImage(str(out / item[key]))
        size = np.asarray(image.GetSize(), dtype=float)
        centre = image.TransformContinuousIndexToPhysicalPoint(((size - 1) / 2).tolist())
        np.testing.assert_allclose(centre, CT_CENTRE, atol=1e-6)  # both volumes where the CT is
    result = monai_rigidreg.register(str(ct_file), str(out / item["moving"]), device="cpu")
    np.testing.assert_allclose(result.center, item["center"], atol=1e-6)
    np.testing.assert_allclose(result.params, item["params"], atol=0.5)  # a wrong frame is off by ~130 mm


def test_ct_frame_false_centres_the_pair_on_the_origin_and_built_in_datasets_resume(ct_file, tmp_path, capsys):
    """``--set ct_frame=False``: the pair of earlier releases (centred on the origin), said so in dataset.json; the
    configuration identity of a built-in phantom has no new field, so its datasets of earlier releases resume."""
    from monai_rigidreg.simulation import make_config

    out = tmp_path / "centred"
    code, err = run_cli(capsys, ["simulate", "--output-dir", out, "--phantom", ct_file, "--motion", *KNOWN_MOTION,
                                 "--set", "ct_frame=False", "--device", "cpu", "--no-progress", *_tiny_sets()])
    assert code == 0, err
    dataset = json.loads((out / "dataset.json").read_text())
    assert dataset["frame_offset_mm"] == [0.0, 0.0, 0.0] and "ct_frame=False" in dataset["frame"]
    np.testing.assert_allclose(dataset["training"][0]["center"], 0.0, atol=1e-9)
    assert "ct_frame" not in make_config("fast").identity() and "motion" not in make_config("fast").identity()
    assert make_config("fast", phantom=str(ct_file)).identity()["ct_frame"] is True


def _tiny_sets() -> list[str]:
    return [f"--set={k}={v}" for k, v in TINY_SIM.items() if k != "preset"]


def test_motion_is_checked_and_excludes_a_protocol(tmp_path, capsys):
    code, err = run_cli(capsys, ["simulate", "--output-dir", tmp_path / "a", "--motion", *KNOWN_MOTION,
                                 "--protocol", "random", "--device", "cpu"])
    assert code == 2 and "give --protocol or --motion, not both" in last_line(err)
    code, err = run_cli(capsys, ["simulate", "--output-dir", tmp_path / "b", "--motion", "1", "2", "3", "4", "5",
                                 "nan", "--device", "cpu"])
    assert code == 2 and "'motion' must be six finite numbers" in last_line(err)
    assert listing(tmp_path) == []
    code, err = run_cli(capsys, ["simulate", "--output-dir", tmp_path / "c", "--motion", *KNOWN_MOTION,
                                 "--num-cases", "2", "--device", "cpu", "--no-progress", *_tiny_sets()])
    assert code == 0, err
    items = json.loads((tmp_path / "c" / "dataset.json").read_text())["training"]
    assert [it["params"] for it in items] == [KNOWN_MOTION] * 2  # two realisations of one motion
