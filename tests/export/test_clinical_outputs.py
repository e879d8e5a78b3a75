"""The clinical outputs of ``monai-rigidreg register``: DICOM Spatial Registration, couch shifts, the elastix
parameter file that transformix applies, the .h5 transform, and the refusals that keep them honest."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from conftest import TINY_SIM, small_registrar_for_tests, true_motion_registrar, write_dicom_series

from monai_rigidreg.cli import main
from monai_rigidreg.core.geometry import transform_points
from monai_rigidreg.export.dicom_reg import read_spatial_registration
from monai_rigidreg.io import load_volume
from monai_rigidreg.registration import RigidRegistrar

MOTION = [5.0, -3.0, 4.0, 3.0, -2.0, 4.0]


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    from monai_rigidreg.simulation import simulate_pair

    return simulate_pair(tmp_path_factory.mktemp("clinical_pair"), phantom="shepp-logan-asym", params=MOTION, seed=5,
                         **{k: v for k, v in TINY_SIM.items() if k != "preset"})


@pytest.fixture(scope="module")
def dicom_pair(pair, tmp_path_factory):
    """The pair as two DICOM series, each with its own study-level facts and Frame of Reference UID."""
    root = tmp_path_factory.mktemp("clinical_dicom")
    write_dicom_series(load_volume(pair["fixed"]), root / "ct", "1.2.826.0.1.3680043.8.498.101",
                       frame_of_reference_uid="1.2.826.0.1.3680043.8.498.201", study_uid="1.2.826.0.1.3680043.8.498.1")
    write_dicom_series(load_volume(pair["moving"]), root / "cbct", "1.2.826.0.1.3680043.8.498.102",
                       frame_of_reference_uid="1.2.826.0.1.3680043.8.498.202", study_uid="1.2.826.0.1.3680043.8.498.1")
    return root / "ct", root / "cbct"


@pytest.fixture(autouse=True)
def small_network(monkeypatch):
    # the untrained network estimates the identity: its estimate replaced by the motion (conftest)
    reg = true_motion_registrar(small_registrar_for_tests(), MOTION)
    monkeypatch.setattr(RigidRegistrar, "from_bundle", classmethod(lambda cls, *a, **k: reg))


def test_dicom_inputs_get_a_spatial_registration_whose_matrix_inverts_the_transform(dicom_pair, tmp_path):
    ct, cbct = dicom_pair
    out = tmp_path / "out"
    assert main(["register", "--fixed", str(ct), "--moving", str(cbct), "--output-dir", str(out), "--no-qc"]) == 0
    ds = pydicom.dcmread(out / "registration.dcm")
    assert ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.66.1" and ds.Modality == "REG"
    assert ds.FrameOfReferenceUID == "1.2.826.0.1.3680043.8.498.201"  # the CT's
    referenced = {s.SeriesInstanceUID for s in ds.ReferencedSeriesSequence}
    assert referenced == {"1.2.826.0.1.3680043.8.498.101", "1.2.826.0.1.3680043.8.498.102"}
    matrices = read_spatial_registration(out / "registration.dcm")
    fixed_to_moving = np.array(json.loads((out / "result.json").read_text())["matrix"])
    # a moved pair: an identity estimate would let a missing inverse of the REG's matrix pass unseen
    assert np.abs(fixed_to_moving[:3, 3]).max() > 2.0 and np.abs(fixed_to_moving[:3, :3] - np.eye(3)).max() > 0.02
    tfm = sitk.ReadTransform(str(out / "transform.tfm"))
    pts = np.array([[0.0, 0.0, 0.0], [40.0, -30.0, 20.0], [-25.0, 35.0, -40.0]])
    moved = np.array([tfm.TransformPoint(p.tolist()) for p in pts])  # CT points -> CBCT points
    np.testing.assert_allclose(transform_points(fixed_to_moving, pts), moved, atol=1e-6)
    # the REG takes CBCT points back to the CT points (DS values keep about 1e-5 relative precision)
    np.testing.assert_allclose(transform_points(matrices["1.2.826.0.1.3680043.8.498.202"], moved), pts, atol=1e-3)
    np.testing.assert_allclose(matrices["1.2.826.0.1.3680043.8.498.201"], np.eye(4))
    if shutil.which("dciodvfy"):
        proc = subprocess.run(["dciodvfy", str(out / "registration.dcm")], capture_output=True, text=True,
                              encoding="utf-8", errors="replace")
        assert "Error" not in proc.stdout + proc.stderr, proc.stdout + proc.stderr


def test_reg_is_refused_or_explained_where_it_cannot_be_written(pair, dicom_pair, tmp_path, capsys):
    # NIfTI inputs carry no UIDs: --reg on is refused before anything is written
    out = tmp_path / "nifti"
    assert main(["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir", str(out),
                 "--reg", "on"]) == 2
    assert "no UIDs" in capsys.readouterr().err and not out.exists()
    # a CT and a CBCT sharing one Frame of Reference: no REG, and result.json says why
    ct, _ = dicom_pair
    same = tmp_path / "cbct_same_frame"
    write_dicom_series(load_volume(pair["moving"]), same, "1.2.826.0.1.3680043.8.498.103",
                       frame_of_reference_uid="1.2.826.0.1.3680043.8.498.201")
    out = tmp_path / "shared"
    assert main(["register", "--fixed", str(ct), "--moving", str(same), "--output-dir", str(out), "--no-qc"]) == 0
    assert not (out / "registration.dcm").exists()
    warnings = json.loads((out / "result.json").read_text())["details"]["warnings"]
    assert any("share one Frame of Reference UID" in w for w in warnings)


def test_couch_shift_equals_the_correction_at_the_isocentre(pair, tmp_path):
    out = tmp_path / "out"
    iso = (10.0, -20.0, 15.0)
    assert main(["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir", str(out),
                 "--no-qc", "--isocenter", ",".join(map(str, iso))]) == 0
    result = json.loads((out / "result.json").read_text())
    couch = result["couch_shift"]
    assert couch["isocentre_source"] == "--isocenter" and couch["isocentre_lps_mm"] == list(iso)
    assert couch["patient_position"] == "HFS" and couch["patient_position_assumed"] is True  # NIfTI: no header
    displacement = transform_points(np.array(result["matrix"]), np.array([iso]))[0] - np.array(iso)
    shift = np.array([couch["3dof"][k] for k in ("lateral", "longitudinal", "vertical")])
    np.testing.assert_allclose(np.linalg.norm(shift), np.linalg.norm(displacement), atol=1e-6)
    # HFS: patient left (+x) is IEC +X, posterior (+y) is IEC -Z and superior (+z) IEC +Y: the correction undoes the
    # displacement on each axis
    assert np.abs(displacement).min() > 0.5  # every axis moved, so a swapped or flipped axis shows
    np.testing.assert_allclose(shift, [-displacement[0], -displacement[2], displacement[1]], atol=1e-6)
    assert set(couch["6dof"]) == {"lateral", "longitudinal", "vertical", "pitch", "roll", "couch_rotation"}
    assert main(["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir",
                 str(tmp_path / "bad"), "--isocenter", "1,2"]) == 2


def test_transformix_applies_the_parameter_file_to_reproduce_registered(pair, tmp_path):
    itk = pytest.importorskip("itk", reason="itk-elastix (the optional 'elastix' extra) is not installed")
    if not hasattr(itk, "transformix_filter"):
        pytest.skip("itk is installed without itk-elastix")
    out = tmp_path / "out"
    assert main(["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir", str(out),
                 "--no-qc", "--transform-format", "h5"]) == 0
    assert (out / "transform.h5").is_file() and not (out / "transform.tfm").exists()
    assert sitk.ReadTransform(str(out / "transform.h5")).GetParameters() == pytest.approx(
        [np.deg2rad(v) for v in json.loads((out / "result.json").read_text())["params"].values()][3:] +
        list(json.loads((out / "result.json").read_text())["params"].values())[:3], abs=1e-9)
    pobj = itk.ParameterObject.New()
    pobj.ReadParameterFile(str(out / "TransformParameters.txt"))
    moving = itk.imread(str(pair["moving"]), itk.F)
    got = itk.array_from_image(itk.transformix_filter(moving, transform_parameter_object=pobj, log_to_console=False))
    want = sitk.GetArrayFromImage(load_volume(out / "registered.nii.gz"))
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, atol=1e-2 * float(np.ptp(want)))


def test_overwrite_never_deletes_what_it_did_not_write(pair, tmp_path, monkeypatch):
    """--overwrite replaces only a folder of earlier outputs: one that also holds the inputs is refused, intact."""
    case = tmp_path / "case1"
    case.mkdir()
    shutil.copy(pair["fixed"], case / "ct.nii.gz")
    shutil.copy(pair["moving"], case / "cbct.nii.gz")
    (case / "notes.txt").write_text("keep me")
    assert main(["register", "--fixed", str(case / "ct.nii.gz"), "--moving", str(case / "cbct.nii.gz"),
                 "--output-dir", str(case), "--overwrite", "--no-qc"]) == 2
    assert sorted(p.name for p in case.iterdir()) == ["cbct.nii.gz", "ct.nii.gz", "notes.txt"]
    out = tmp_path / "out"  # a folder of earlier outputs is replaced
    assert main(["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir", str(out)]) == 0
    assert main(["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir", str(out),
                 "--overwrite"]) == 0
    monkeypatch.chdir(tmp_path / "out")  # the current folder itself is never an output folder
    assert main(["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir", "."]) == 2


def _series_with_position(series, copy, position):
    """A copy of the DICOM series folder ``series`` at ``copy`` with Patient Position (0018,5100) ``position``."""
    shutil.copytree(series, copy)
    for f in copy.iterdir():
        ds = pydicom.dcmread(f)
        ds.PatientPosition = position
        ds.save_as(f)
    return copy


def test_patient_position_option_header_and_unsupported_values(pair, dicom_pair, tmp_path):
    runs = {}
    for name, extra in (("hfs", []), ("ffs", ["--patient-position", "FFS"])):
        out = tmp_path / name
        assert main(["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir", str(out),
                     "--no-qc", *extra]) == 0
        runs[name] = json.loads((out / "result.json").read_text())["couch_shift"]
    assert runs["ffs"]["patient_position"] == "FFS" and runs["ffs"]["patient_position_source"] == "--patient-position"
    # feet first: patient left is IEC -X and superior is -Y (a half turn about IEC Z), so lateral, longitudinal, pitch
    # (about X) and roll (about Y) change sign, vertical and the couch rotation (about Z) do not; every one of them
    # is non-zero under the motion, so a sign or an axis wrong shows
    hfs, ffs = runs["hfs"]["6dof"], runs["ffs"]["6dof"]
    assert min(abs(v) for v in hfs.values()) > 0.2, hfs
    for key in ("lateral", "longitudinal", "pitch", "roll"):
        np.testing.assert_allclose(ffs[key], -hfs[key], atol=1e-9, err_msg=key)
    for key in ("vertical", "couch_rotation"):
        np.testing.assert_allclose(ffs[key], hfs[key], atol=1e-9, err_msg=key)
    for key in ("lateral", "longitudinal", "vertical"):
        assert runs["ffs"]["3dof"][key] == ffs[key] and runs["hfs"]["3dof"][key] == hfs[key]
    assert main(["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir",
                 str(tmp_path / "sitting"), "--patient-position", "SITTING"]) == 2
    assert not (tmp_path / "sitting").exists()
    # a header value the couch model does not support: the registration is written, the couch shifts say why not
    ct = _series_with_position(dicom_pair[0], tmp_path / "ct_sitting", "SITTING")
    out = tmp_path / "from_header"
    assert main(["register", "--fixed", str(ct), "--moving", str(dicom_pair[1]), "--output-dir", str(out),
                 "--no-qc"]) == 0
    result = json.loads((out / "result.json").read_text())
    assert "unsupported patient position" in result["couch_shift"]["unavailable"]
    # the CT planned head first supine, the CBCT feet first: the CT's axes, and a warning in the audit trail
    ct_hfs = _series_with_position(dicom_pair[0], tmp_path / "ct_hfs", "HFS")
    cbct_ffs = _series_with_position(dicom_pair[1], tmp_path / "cbct_ffs", "FFS")
    out = tmp_path / "positions_differ"
    assert main(["register", "--fixed", str(ct_hfs), "--moving", str(cbct_ffs), "--output-dir", str(out),
                 "--no-qc"]) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["couch_shift"]["patient_position"] == "HFS"
    assert result["couch_shift"]["patient_position_source"] == "CT DICOM header"
    assert [w for w in result["details"]["warnings"]
            if "Patient Position is HFS and the CBCT's FFS: the couch shifts use HFS (CT DICOM header)" in w]


def test_a_dicom_slice_gap_is_recorded_in_result_json(pair, dicom_pair, tmp_path, caplog):
    """A CBCT series with a missing slice is resampled at its true slice positions (monai_rigidreg.io.dicom_series);
    the warning that says so is in the audit trail (result.json details.warnings), not only on the console."""
    ct, cbct = dicom_pair
    gappy = tmp_path / "cbct_gap"
    shutil.copytree(cbct, gappy)
    files = sorted(gappy.iterdir(), key=lambda f: float(pydicom.dcmread(f, stop_before_pixels=True)
                                                        .ImagePositionPatient[2]))
    files[len(files) // 2].unlink()
    out = tmp_path / "out"
    with caplog.at_level("WARNING"):
        assert main(["register", "--fixed", str(ct), "--moving", str(gappy), "--output-dir", str(out), "--no-qc"]) == 0
    warnings = json.loads((out / "result.json").read_text())["details"]["warnings"]
    assert [w for w in warnings if "unevenly spaced" in w and "resampled from" in w]
    assert "unevenly spaced" in caplog.text  # and still logged
    # whatever the console's verbosity (-qq: errors only), the audit trail keeps it
    quiet = tmp_path / "quiet"
    assert main(["register", "--fixed", str(ct), "--moving", str(gappy), "--output-dir", str(quiet), "--no-qc",
                 "-qq"]) == 0
    warnings = json.loads((quiet / "result.json").read_text())["details"]["warnings"]
    assert [w for w in warnings if "unevenly spaced" in w and "resampled from" in w]
