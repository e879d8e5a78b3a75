"""``monai-rigidreg simulate`` (monai_rigidreg.simulation.simulate_command): an unusable phantom or an early
failure leaves no trace.

Split from the former tests/test_reliability.py (same assertions).
"""

from __future__ import annotations

import pytest
import SimpleITK as sitk
from conftest import TINY_SIM, last_line, listing, run_cli


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
