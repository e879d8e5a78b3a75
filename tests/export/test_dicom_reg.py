"""The DICOM Spatial Registration (REG) writer: frames, matrix direction, references, DS lengths, IOD validity."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from conftest import oblique_direction, smooth_random_image, write_dicom_series
from pydicom.uid import UID, generate_uid
from pydicom.valuerep import is_valid_ds

from monai_rigidreg.core.errors import InputError, OutputExistsError
from monai_rigidreg.core.geometry import Grid, invert_matrix, params_to_matrix, params_to_sitk, transform_points
from monai_rigidreg.export.dicom_reg import (
    SPATIAL_REGISTRATION_SOP_CLASS_UID,
    SeriesReference,
    format_ds,
    read_spatial_registration,
    series_reference,
    write_spatial_registration,
)
from monai_rigidreg.io import load_volume

PARAMS = [5.0, -3.0, 2.0, 4.0, -2.0, 6.0]
"""Known fixed (CT) -> moving (CBCT) motion: mm and degrees about the CT centre."""

PATIENT = {
    "SpecificCharacterSet": "ISO_IR 192",
    "PatientName": "Müller^Anna",
    "PatientID": "RR-0001",
    "PatientBirthDate": "19600101",
    "PatientSex": "F",
    "StudyID": "S1",
    "AccessionNumber": "ACC42",
    "ReferringPhysicianName": "Doe^John",
    "BodyPartExamined": "PELVIS",
}


def _ct_image() -> sitk.Image:
    return smooth_random_image((10, 9, 6), (2.0, 2.0, 3.0), (-10.0, -9.0, -7.0), oblique_direction(0, 0, 10), seed=1)


def _cbct_image() -> sitk.Image:
    return smooth_random_image((8, 8, 5), (2.5, 2.5, 2.5), (-9.0, -8.0, -6.0), oblique_direction(0, 0, 0), seed=2)


def _set_header(directory: Path, values: dict[str, str]) -> None:
    """Add patient/study attributes to every file of a test series (SimpleITK writes them empty)."""
    for f in sorted(directory.glob("*.dcm")):
        ds = pydicom.dcmread(f)
        for keyword, value in values.items():
            setattr(ds, keyword, value)
        ds.save_as(f)


def _sop_instances(directory: Path) -> set[str]:
    return {str(pydicom.dcmread(f, stop_before_pixels=True).SOPInstanceUID) for f in directory.glob("*.dcm")}


def _make_series(tmp_path: Path, same_study: bool, same_frame: bool = False) -> tuple[Path, Path]:
    ct_dir, cbct_dir = tmp_path / "ct", tmp_path / "cbct"
    ct_frame = generate_uid()
    write_dicom_series(_ct_image(), ct_dir, generate_uid(), frame_of_reference_uid=ct_frame)
    write_dicom_series(_cbct_image(), cbct_dir, generate_uid(), shuffle_seed=1,
                       frame_of_reference_uid=ct_frame if same_frame else generate_uid(),
                       study_uid=None if same_study else generate_uid())
    _set_header(ct_dir, PATIENT)
    _set_header(cbct_dir, PATIENT)
    return ct_dir, cbct_dir


@pytest.fixture(params=[True, False], ids=["same-study", "cbct-in-other-study"])
def registration(tmp_path, request):
    """A CT and a CBCT series with their own frames, the known motion, and the REG written for them."""
    ct_dir, cbct_dir = _make_series(tmp_path, same_study=request.param)
    ct, cbct = series_reference(ct_dir), series_reference(cbct_dir)
    center = Grid.from_sitk(load_volume(ct_dir)).center()  # the rotation centre of the registration: the CT's
    fixed_to_moving = params_to_matrix(PARAMS, center)
    path = write_spatial_registration(tmp_path / "out" / "reg.dcm", ct, cbct, invert_matrix(fixed_to_moving),
                                      software_version="test-1.0")
    return dict(path=path, ct=ct, cbct=cbct, ct_dir=ct_dir, cbct_dir=cbct_dir, center=center,
                fixed_to_moving=fixed_to_moving, same_study=request.param)


def _item_for(ds: pydicom.Dataset, frame_uid: str) -> pydicom.Dataset:
    items = [it for it in ds.RegistrationSequence if it.FrameOfReferenceUID == frame_uid]
    assert len(items) == 1, f"expected one registration item for frame {frame_uid}"
    return items[0]


def _matrix(item: pydicom.Dataset) -> np.ndarray:
    (registration,) = item.MatrixRegistrationSequence
    (matrix_item,) = registration.MatrixSequence
    assert matrix_item.FrameOfReferenceTransformationMatrixType == "RIGID"
    values = matrix_item.FrameOfReferenceTransformationMatrix
    assert len(values) == 16
    return np.array([float(v) for v in values]).reshape(4, 4)


def test_reg_frames_matrix_and_header(registration):
    ds = pydicom.dcmread(registration["path"])
    ct, cbct = registration["ct"], registration["cbct"]
    assert ds.SOPClassUID == SPATIAL_REGISTRATION_SOP_CLASS_UID == ds.file_meta.MediaStorageSOPClassUID
    assert ds.SOPInstanceUID == ds.file_meta.MediaStorageSOPInstanceUID
    assert ds.Modality == "REG"
    assert UID(ds.SOPInstanceUID).is_valid and UID(ds.SeriesInstanceUID).is_valid
    assert ds.SeriesInstanceUID not in (ct.series_instance_uid, cbct.series_instance_uid)
    assert ds.ContentLabel == "RIGIDREG" and ds.SoftwareVersions == "test-1.0"
    assert ds.ContentDate and ds.ContentTime
    # the REG lives in the CT's frame and study, with the CT's patient facts
    assert ds.FrameOfReferenceUID == ct.frame_of_reference_uid != cbct.frame_of_reference_uid
    assert ds.StudyInstanceUID == ct.study_instance_uid
    assert str(ds.PatientName) == "Müller^Anna" and ds.PatientID == "RR-0001"
    assert (ds.PatientBirthDate, ds.PatientSex, ds.StudyID, ds.AccessionNumber) == ("19600101", "F", "S1", "ACC42")
    assert str(ds.ReferringPhysicianName) == "Doe^John" and ds.StudyDate == ct.study_date
    assert len(ds.RegistrationSequence) == 2

    np.testing.assert_array_equal(_matrix(_item_for(ds, ct.frame_of_reference_uid)), np.eye(4))
    moving_to_fixed = _matrix(_item_for(ds, cbct.frame_of_reference_uid))
    np.testing.assert_allclose(moving_to_fixed, np.linalg.inv(registration["fixed_to_moving"]), atol=1e-5)
    # a CT point x goes to T(x) in the CBCT under our transform (transform.tfm); the REG brings T(x) back to x
    tfm = params_to_sitk(PARAMS, registration["center"])
    ct_points = np.array([[0.0, 0.0, 0.0], [12.0, -7.0, 30.0], [-40.0, 25.0, -15.0]])
    cbct_points = np.array([tfm.TransformPoint(tuple(p)) for p in ct_points])
    np.testing.assert_allclose(transform_points(moving_to_fixed, cbct_points), ct_points, atol=1e-4)

    matrices = read_spatial_registration(registration["path"])
    assert set(matrices) == {ct.frame_of_reference_uid, cbct.frame_of_reference_uid}
    np.testing.assert_array_equal(matrices[ct.frame_of_reference_uid], np.eye(4))
    np.testing.assert_allclose(matrices[cbct.frame_of_reference_uid], moving_to_fixed, atol=0)


def test_reg_references_every_instance_of_both_series(registration):
    ds = pydicom.dcmread(registration["path"])
    ct, cbct = registration["ct"], registration["cbct"]
    ct_uids, cbct_uids = _sop_instances(registration["ct_dir"]), _sop_instances(registration["cbct_dir"])
    assert {i.sop_instance_uid for i in ct.instances} == ct_uids and len(ct.instances) == 6
    assert {i.sop_instance_uid for i in cbct.instances} == cbct_uids and len(cbct.instances) == 5

    def series_items(seq) -> dict[str, set[tuple[str, str]]]:
        return {s.SeriesInstanceUID: {(r.ReferencedSOPClassUID, r.ReferencedSOPInstanceUID)
                                      for r in s.ReferencedInstanceSequence} for s in seq}

    local = series_items(ds.ReferencedSeriesSequence)
    other = {st.StudyInstanceUID: series_items(st.ReferencedSeriesSequence)
             for st in ds.get("StudiesContainingOtherReferencedInstancesSequence", [])}
    ct_refs = {("1.2.840.10008.5.1.4.1.1.2", u) for u in ct_uids}  # CT Image Storage
    cbct_refs = {("1.2.840.10008.5.1.4.1.1.2", u) for u in cbct_uids}
    assert local[ct.series_instance_uid] == ct_refs
    if registration["same_study"]:
        assert local[cbct.series_instance_uid] == cbct_refs and not other
    else:
        assert cbct.series_instance_uid not in local
        assert cbct.study_instance_uid != ct.study_instance_uid
        assert other == {cbct.study_instance_uid: {cbct.series_instance_uid: cbct_refs}}
    for ref, refs in ((ct, ct_refs), (cbct, cbct_refs)):
        images = _item_for(ds, ref.frame_of_reference_uid).ReferencedImageSequence
        assert {(r.ReferencedSOPClassUID, r.ReferencedSOPInstanceUID) for r in images} == refs


def test_reg_decimal_strings_fit_16_characters(registration):
    ds = pydicom.dcmread(registration["path"])
    ds_values = [v for elem in ds.iterall() if elem.VR == "DS"
                 for v in (elem.value if elem.VM > 1 else [elem.value])]
    assert len(ds_values) == 32  # two 4x4 matrices
    for v in ds_values:
        text = getattr(v, "original_string", None) or str(v)
        assert len(text) <= 16 and is_valid_ds(text), text
    # and the raw bytes: every DS value of the file as written
    raw = registration["path"].read_bytes()
    matrix_item = _item_for(ds, registration["cbct"].frame_of_reference_uid)
    written = [str(v.original_string) for v in
               matrix_item.MatrixRegistrationSequence[0].MatrixSequence[0].FrameOfReferenceTransformationMatrix]
    assert "\\".join(written).encode() in raw


@pytest.mark.parametrize("value", [-0.12345678901234567, 1e-20, -1.2345678901234567e-300, 123456789012345678.0,
                                   np.pi * 1e5, -123.456789012345, 0.9999999999999999, 5e-324, -0.0, 42.0])
def test_format_ds_fits_and_round_trips(value):
    text = format_ds(value)
    assert len(text) <= 16 and is_valid_ds(text), text
    assert abs(float(text) - value) <= 5e-9 * abs(value)
    if abs(value) < 1e5:
        assert abs(float(text) - value) < 1e-9
    assert format_ds(-0.0) == "0" and format_ds(42.0) == "42"


def test_format_ds_refuses_non_finite():
    for v in (float("nan"), float("inf")):
        with pytest.raises(ValueError):
            format_ds(v)


def _dciodvfy(path: Path) -> str:
    exe = shutil.which("dciodvfy")
    if exe is None:
        pytest.skip("dciodvfy is not installed (Debian/Ubuntu package dicom3tools): the IOD validation is skipped")
    proc = subprocess.run([exe, str(path)], capture_output=True, text=True,
                          encoding="utf-8", errors="replace", timeout=60)
    return proc.stdout + proc.stderr


def test_reg_passes_dciodvfy(registration):
    report = _dciodvfy(registration["path"])
    assert "SpatialRegistration" in report, report  # the IOD dciodvfy recognised and checked
    errors = [line for line in report.splitlines() if line.startswith("Error")]
    assert not errors, report


def test_same_frame_of_reference_is_refused_unless_user_given(tmp_path):
    ct_dir, cbct_dir = _make_series(tmp_path, same_study=True, same_frame=True)
    ct, cbct = series_reference(ct_dir), series_reference(cbct_dir)
    assert ct.frame_of_reference_uid == cbct.frame_of_reference_uid
    with pytest.raises(InputError, match="share the Frame of Reference UID"):
        write_spatial_registration(tmp_path / "reg.dcm", ct, cbct, np.eye(4))
    assert not (tmp_path / "reg.dcm").exists()
    # the user states the CBCT's true frame explicitly: then the REG is written, with that frame
    user_frame = generate_uid()
    cbct = series_reference(cbct_dir, frame_of_reference_uid=user_frame)
    path = write_spatial_registration(tmp_path / "reg.dcm", ct, cbct, np.eye(4))
    assert set(read_spatial_registration(path)) == {ct.frame_of_reference_uid, user_frame}


def test_missing_uids_are_refused(tmp_path):
    # a DICOM series without a Frame of Reference UID (SimpleITK writes none by default)
    write_dicom_series(_ct_image(), tmp_path / "no_frame", generate_uid())
    with pytest.raises(InputError, match="no Frame of Reference UID"):
        series_reference(tmp_path / "no_frame")
    # a NIfTI volume carries no DICOM UIDs at all
    nifti = tmp_path / "ct.nii.gz"
    sitk.WriteImage(_ct_image(), str(nifti))
    with pytest.raises(InputError, match="not a DICOM file"):
        series_reference(nifti)
    with pytest.raises(InputError, match="no such file"):
        series_reference(tmp_path / "missing")
    # a hand-built reference with an empty UID
    ct = SeriesReference(generate_uid(), generate_uid(), generate_uid())
    cbct = SeriesReference(generate_uid(), generate_uid(), "")
    with pytest.raises(InputError, match="no Frame of Reference UID"):
        write_spatial_registration(tmp_path / "reg.dcm", ct, cbct, np.eye(4))
    with pytest.raises(InputError, match="not a valid DICOM UID"):
        write_spatial_registration(tmp_path / "reg.dcm", ct, SeriesReference("1.2", "1.3", "not-a-uid"), np.eye(4))


def test_user_given_uids_without_images(tmp_path):
    """NIfTI inputs with user-given UIDs: the REG names the two frames and references no images."""
    ct = SeriesReference(generate_uid(), generate_uid(), generate_uid(), patient_id="P1")
    cbct = SeriesReference(generate_uid(), generate_uid(), generate_uid(), patient_id="P1")
    moving_to_fixed = invert_matrix(params_to_matrix(PARAMS, (1.0, 2.0, 3.0)))
    path = write_spatial_registration(tmp_path / "reg.dcm", ct, cbct, moving_to_fixed)
    ds = pydicom.dcmread(path)
    assert "ReferencedSeriesSequence" not in ds and "StudiesContainingOtherReferencedInstancesSequence" not in ds
    np.testing.assert_allclose(read_spatial_registration(path)[cbct.frame_of_reference_uid], moving_to_fixed,
                               atol=1e-9)
    if shutil.which("dciodvfy"):
        report = _dciodvfy(path)
        assert not [ln for ln in report.splitlines() if ln.startswith("Error")], report


def test_bad_arguments_are_refused(tmp_path):
    ct = SeriesReference(generate_uid(), generate_uid(), generate_uid(), patient_id="P1")
    cbct = SeriesReference(generate_uid(), generate_uid(), generate_uid(), patient_id="P1")
    out = tmp_path / "reg.dcm"
    for bad, what in [(np.diag([2.0, 1.0, 1.0, 1.0]), "not rigid"), (np.diag([-1.0, 1.0, 1.0, 1.0]), "not rigid"),
                      (np.eye(3), "4x4"), (np.full((4, 4), np.nan), "NaN"),
                      (np.vstack([np.eye(4)[:3], [0.0, 0.0, 1.0, 1.0]]), "last row")]:
        with pytest.raises(InputError, match=what):
            write_spatial_registration(out, ct, cbct, bad)
    with pytest.raises(InputError, match="content_label"):
        write_spatial_registration(out, ct, cbct, np.eye(4), content_label="rigid-reg")
    with pytest.raises(InputError, match="same DICOM series"):
        write_spatial_registration(out, ct, SeriesReference(generate_uid(), ct.series_instance_uid, generate_uid()),
                                   np.eye(4))
    with pytest.raises(InputError, match="different patients"):
        write_spatial_registration(out, ct, SeriesReference(generate_uid(), generate_uid(), generate_uid(),
                                                            patient_id="P2"), np.eye(4))
    assert not out.exists()
    write_spatial_registration(out, ct, cbct, np.eye(4))
    with pytest.raises(OutputExistsError):
        write_spatial_registration(out, ct, cbct, np.eye(4))
    write_spatial_registration(out, ct, cbct, np.eye(4), overwrite=True)
    assert [p.name for p in tmp_path.iterdir()] == ["reg.dcm"]  # no partial file left behind


def test_read_spatial_registration_refuses_other_files(tmp_path):
    write_dicom_series(_ct_image(), tmp_path / "ct", generate_uid(), frame_of_reference_uid=generate_uid())
    with pytest.raises(InputError, match="not a DICOM Spatial Registration"):
        read_spatial_registration(next((tmp_path / "ct").glob("*.dcm")))
    with pytest.raises(InputError, match="no such file"):
        read_spatial_registration(tmp_path / "missing.dcm")
