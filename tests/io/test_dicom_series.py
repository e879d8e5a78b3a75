"""DICOM series (monai_rigidreg.io.dicom_series): a series with a missing slice registers like the complete one.

Split from the former tests/test_reliability.py (same assertions).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from conftest import write_dicom_series

from monai_rigidreg.io import list_dicom_series, load_volume
from monai_rigidreg.registration import RigidRegistrar


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


def test_a_folder_without_dicom_files_is_one_clean_line(pair, tmp_path, capfd):
    """A non-DICOM folder as an input: one line naming it, without ITK's two raw warning lines (GDCM's "No Series
    were found", printed by ITK itself to the process's stderr), and the warning display is left as it was."""
    import SimpleITK as sitk

    from monai_rigidreg.cli import main

    folder = tmp_path / "not_dicom"
    folder.mkdir()
    (folder / "notes.txt").write_text("not an image")
    before = sitk.ProcessObject.GetGlobalWarningDisplay()
    code = main(["register", "--fixed", str(pair["fixed"]), "--moving", str(folder), "--output-dir",
                 str(tmp_path / "out")])
    err = capfd.readouterr().err
    assert code == 2 and err.strip().splitlines() == [
        f"monai-rigidreg register: error: {folder}: directory holds no DICOM image series (give a DICOM series "
        "folder, or an image file: NIfTI, MHA, NRRD)"], err
    assert sitk.ProcessObject.GetGlobalWarningDisplay() == before

