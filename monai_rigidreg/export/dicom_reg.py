"""DICOM Spatial Registration objects (REG, SOP Class 1.2.840.10008.5.1.4.1.1.66.1) for a rigid CBCT -> CT result.

A REG object states how the patient coordinates of one DICOM Frame of Reference map into another. The object
written here lives in the planning CT's Frame of Reference (the fixed image) and holds two registration items:

1. the CT's own frame, with the identity matrix (DICOM's way of saying "this is the reference");
2. the CBCT's frame (the moving image), with the rigid 4x4 matrix ``M`` that maps a point given in CBCT patient
   coordinates to the same anatomical point in CT patient coordinates: ``[x_ct, 1] = M @ [x_cbct, 1]``.

Both coordinate systems are DICOM patient coordinates, which are LPS millimetres like every coordinate in this
project (``docs/conventions.md``). Our ``transform.tfm`` maps the other way (fixed/CT points to moving/CBCT points,
ITK's resampling direction), so the matrix to store is its **inverse**::

    moving_to_fixed = geometry.invert_matrix(geometry.sitk_to_matrix(io.read_transform("transform.tfm")))

The matrix is written row-major as 16 Decimal Strings of at most 16 characters (:func:`format_ds`), type RIGID.

A registration only makes sense between two *different* frames of reference that the DICOM headers name: a CT and
a CBCT that share one Frame of Reference UID (DICOM then already declares their coordinates identical), or an
input without UIDs (NIfTI, MHA, NRRD), raise :class:`~monai_rigidreg.core.errors.InputError` rather than a REG with
made-up relationships. A caller who knows the true UIDs passes them explicitly: ``frame_of_reference_uid=`` of
:func:`series_reference`, or a :class:`SeriesReference` built by hand.

Typical use::

    ct = series_reference("ct_dicom/")
    cbct = series_reference("cbct_dicom/")
    # result: a RegistrationResult; result.matrix maps CT points to CBCT points, the REG needs its inverse
    write_spatial_registration("out/reg.dcm", ct, cbct, geometry.invert_matrix(result.matrix))
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pydicom
from numpy.typing import ArrayLike
from pydicom.dataset import Dataset, FileDataset, FileMetaDataset
from pydicom.errors import InvalidDicomError
from pydicom.sequence import Sequence as DicomSequence
from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, ExplicitVRLittleEndian, generate_uid

from monai_rigidreg import __version__
from monai_rigidreg.core.errors import InputError
from monai_rigidreg.io.dicom_series import format_ds, is_valid_uid, list_dicom_series, select_dicom_series
from monai_rigidreg.io.volumes import check_output_path

__all__ = [
    "SPATIAL_REGISTRATION_SOP_CLASS_UID",
    "InstanceReference",
    "SeriesReference",
    "series_reference",
    "write_spatial_registration",
    "read_spatial_registration",
    "format_ds",
]

SPATIAL_REGISTRATION_SOP_CLASS_UID = "1.2.840.10008.5.1.4.1.1.66.1"
"""SOP Class UID of the (rigid) Spatial Registration Storage IOD."""

MANUFACTURER = "monai-rigidreg"

_PYDICOM_MAJOR = int(pydicom.__version__.split(".")[0])

# CID 7100 "RCS Registration Method Type"
_CODE_FRAME_IDENTITY = ("125021", "DCM", "Frame of Reference Identity")
_CODE_IMAGE_CONTENT = ("125024", "DCM", "Image Content-based Alignment")

# the header attributes a series reference copies from its first file (keyword -> SeriesReference field)
_PATIENT_STUDY_FIELDS = {
    "PatientName": "patient_name",
    "PatientID": "patient_id",
    "PatientBirthDate": "patient_birth_date",
    "PatientSex": "patient_sex",
    "StudyID": "study_id",
    "StudyDate": "study_date",
    "StudyTime": "study_time",
    "AccessionNumber": "accession_number",
    "ReferringPhysicianName": "referring_physician_name",
    "StudyDescription": "study_description",
    "PositionReferenceIndicator": "position_reference_indicator",
    "Laterality": "laterality",
    "BodyPartExamined": "body_part_examined",
    "Modality": "modality",
}


class InstanceReference(NamedTuple):
    """One referenced DICOM instance (an image slice of a series)."""

    sop_class_uid: str
    sop_instance_uid: str


@dataclass(frozen=True)
class SeriesReference:
    """The header facts of one DICOM image series that a Spatial Registration object needs.

    Built by :func:`series_reference` from the files of a series, or by hand with user-given UIDs (for example
    for a volume converted to NIfTI whose original UIDs the user knows); ``instances`` may then be empty, and the
    REG references the frame of reference only.

    Attributes:
        study_instance_uid: Study Instance UID (0020,000D).
        series_instance_uid: Series Instance UID (0020,000E).
        frame_of_reference_uid: Frame of Reference UID (0020,0052): the patient coordinate system (LPS mm) of the
            series.
        instances: SOP Class / SOP Instance UID of every image of the series, in slice order.
        modality, patient_name, patient_id, patient_birth_date, patient_sex, study_id, study_date, study_time,
        accession_number, referring_physician_name, study_description, position_reference_indicator,
        laterality, body_part_examined: the patient, study, frame-of-reference and series attributes as stored
            (DICOM string forms; empty if absent). The REG copies those of the fixed (CT) series.
        source: the directory or file the facts were read from, if any (for messages).
    """

    study_instance_uid: str
    series_instance_uid: str
    frame_of_reference_uid: str
    instances: tuple[InstanceReference, ...] = ()
    modality: str = ""
    patient_name: str = ""
    patient_id: str = ""
    patient_birth_date: str = ""
    patient_sex: str = ""
    study_id: str = ""
    study_date: str = ""
    study_time: str = ""
    accession_number: str = ""
    referring_physician_name: str = ""
    study_description: str = ""
    position_reference_indicator: str = ""
    laterality: str = ""
    body_part_examined: str = ""
    source: Path | None = field(default=None, compare=False)


# ---------------------------------------------------------------------------------------------------------------
# Reading the header facts of a series
# ---------------------------------------------------------------------------------------------------------------
def series_reference(directory: str | Path, series_uid: str | None = None,
                     frame_of_reference_uid: str | None = None) -> SeriesReference:
    """Read the :class:`SeriesReference` of the DICOM series that :func:`monai_rigidreg.io.load_volume` reads.

    Args:
        directory: a DICOM series folder (the series is chosen exactly as ``load_volume`` chooses it:
            ``series_uid`` if given, else the largest series), or a single DICOM file (a multi-frame image).
        series_uid: the Series Instance UID to use in a folder with several series.
        frame_of_reference_uid: a user-given Frame of Reference UID that replaces the one in the files (or stands in
            for a missing one). Only for a caller who knows it; nothing here guesses one.

    Returns:
        the UIDs of the study, series and frame of reference, every image's SOP Class / Instance UID, and the
        patient and study attributes of the series' first file.

    Raises:
        InputError: the path is missing or not DICOM (a NIfTI, MHA or NRRD file carries no DICOM UIDs), a file of
            the series is unreadable, a UID is missing or invalid, or the files of the series disagree on the
            study or the frame of reference.
    """
    p = Path(directory)
    if not p.exists():
        raise InputError("no such file or directory", p)
    if p.is_dir():
        series = list_dicom_series(p)
        chosen = select_dicom_series(p, series_uid, series)
        files = [Path(f) for f in series[chosen]]
    else:
        files = [p]
    headers = [_read_header(f, p) for f in files]

    def common(keyword: str, what: str) -> str:
        values = {str(h.get(keyword, "") or "").strip() for h in headers}
        if len(values) > 1:
            raise InputError(f"the files of the series disagree on the {what} ({keyword}): {sorted(values)}", p)
        return values.pop()

    study_uid = common("StudyInstanceUID", "Study Instance UID")
    found_series_uid = common("SeriesInstanceUID", "Series Instance UID")
    if frame_of_reference_uid is None:
        for_uid = common("FrameOfReferenceUID", "Frame of Reference UID")
        if not for_uid:
            raise InputError(
                "the DICOM series has no Frame of Reference UID (0020,0052), so no DICOM registration can name its "
                "coordinate system; pass the true one as frame_of_reference_uid= only if you know it", p)
    else:
        for_uid = str(frame_of_reference_uid).strip()
    instances: list[InstanceReference] = []
    seen: set[str] = set()
    for f, h in zip(files, headers):
        sop_class, sop_instance = (str(h.get(k, "") or "").strip() for k in ("SOPClassUID", "SOPInstanceUID"))
        if not (sop_class and sop_instance):
            raise InputError("DICOM file has no SOP Class UID or SOP Instance UID", f)
        if sop_instance not in seen:  # the same instance stored twice is referenced once
            seen.add(sop_instance)
            instances.append(InstanceReference(sop_class, sop_instance))
    facts = {name: _text(headers[0].get(keyword, "")) for keyword, name in _PATIENT_STUDY_FIELDS.items()}
    ref = SeriesReference(study_instance_uid=study_uid, series_instance_uid=found_series_uid,
                          frame_of_reference_uid=for_uid, instances=tuple(instances), source=p, **facts)
    _check_reference(ref, "series")
    return ref


def _read_header(path: Path, source: Path) -> Dataset:
    try:
        return pydicom.dcmread(str(path), stop_before_pixels=True)
    except InvalidDicomError as exc:
        hint = (" (a NIfTI, MHA or NRRD volume carries no DICOM UIDs: a DICOM registration needs the DICOM series "
                "of the CT and the CBCT, or user-given UIDs in a SeriesReference)") if path == source else ""
        raise InputError(f"not a DICOM file{hint}", path) from exc
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"unreadable DICOM file ({exc})", path) from exc


def _text(value: object) -> str:
    return "" if value is None else str(value).strip()


# ---------------------------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------------------------
def write_spatial_registration(
    path: str | Path,
    fixed: SeriesReference,
    moving: SeriesReference,
    moving_to_fixed: ArrayLike,
    content_label: str = "RIGIDREG",
    description: str = "Rigid CBCT to planning CT registration",
    software_version: str | None = None,
    series_number: int | None = None,
    content_creator_name: str = "",
    overwrite: bool = False,
) -> Path:
    """Write a DICOM Spatial Registration object for a rigid registration of ``moving`` (CBCT) to ``fixed`` (CT).

    Args:
        path: the file to write (e.g. ``reg.dcm``); its folder is created. An existing file is refused unless
            ``overwrite``.
        fixed: the planning CT. The REG takes its Frame of Reference UID, its study (the REG joins the CT's study)
            and its patient and study attributes.
        moving: the CBCT.
        moving_to_fixed: rigid 4x4 matrix mapping CBCT (moving) patient coordinates to CT (fixed) patient
            coordinates, LPS mm: ``[x_ct, 1] = M @ [x_cbct, 1]``. This is the **inverse** of the fixed -> moving
            matrix of ``transform.tfm`` / ``RegistrationResult``.
        content_label: Content Label (CS: at most 16 of ``A-Z 0-9 _`` and space).
        description: Content Description and Series Description (at most 64 characters).
        software_version: Software Versions of the equipment module (default: this package's version).
        series_number: Series Number of the new REG series (default: empty).
        content_creator_name: Content Creator's Name (PN; default empty).
        overwrite: replace an existing file.

    Returns:
        the path written. The file appears only once complete.

    Raises:
        InputError: a missing or invalid UID, CT and CBCT in the same Frame of Reference or the same series,
            different Patient IDs, a matrix that is not a finite rigid 4x4 (rotation + translation), or a bad
            ``content_label`` or ``description``.
        OutputExistsError: ``path`` exists and ``overwrite`` is false.
    """
    _check_reference(fixed, "fixed (CT)")
    _check_reference(moving, "moving (CBCT)")
    if fixed.frame_of_reference_uid == moving.frame_of_reference_uid:
        raise InputError(
            f"the CT (fixed) and the CBCT (moving) share the Frame of Reference UID {fixed.frame_of_reference_uid}: "
            "DICOM already declares their patient coordinates identical, so no registration between them can be "
            "stored. If one of them is wrong, pass the true UID explicitly (series_reference(..., "
            "frame_of_reference_uid=...))")
    if fixed.series_instance_uid == moving.series_instance_uid:
        raise InputError(f"the CT (fixed) and the CBCT (moving) are the same DICOM series "
                         f"{fixed.series_instance_uid}")
    if fixed.patient_id and moving.patient_id and fixed.patient_id != moving.patient_id:
        raise InputError(f"the CT (fixed) and the CBCT (moving) belong to different patients (Patient ID "
                         f"{fixed.patient_id!r} and {moving.patient_id!r})")
    matrix = _check_rigid(moving_to_fixed)
    label = str(content_label)
    if not (0 < len(label) <= 16 and all(c.isascii() and (c.isupper() or c.isdigit() or c in "_ ") for c in label)):
        raise InputError(f"content_label must be 1 to 16 characters of A-Z, 0-9, '_' and space, got {label!r}")
    if len(description) > 64:
        raise InputError(f"description must fit in 64 characters (DICOM LO), got {len(description)}")
    out = check_output_path(path, overwrite)

    now = datetime.now()
    date, time = now.strftime("%Y%m%d"), now.strftime("%H%M%S.%f")
    sop_instance_uid = generate_uid()

    meta = FileMetaDataset()
    meta.FileMetaInformationVersion = b"\x00\x01"
    meta.MediaStorageSOPClassUID = SPATIAL_REGISTRATION_SOP_CLASS_UID
    meta.MediaStorageSOPInstanceUID = sop_instance_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = FileDataset(str(out), {}, file_meta=meta, preamble=b"\x00" * 128)

    texts = [fixed.patient_name, fixed.referring_physician_name, fixed.study_description, description,
             content_creator_name, fixed.study_id, fixed.accession_number, fixed.position_reference_indicator]
    if not all(str(t).isascii() for t in texts):
        ds.SpecificCharacterSet = "ISO_IR 192"  # UTF-8
    # SOP Common
    ds.SOPClassUID = SPATIAL_REGISTRATION_SOP_CLASS_UID
    ds.SOPInstanceUID = sop_instance_uid
    ds.InstanceCreationDate, ds.InstanceCreationTime = date, time
    # Patient and General Study, copied from the CT
    ds.PatientName = fixed.patient_name
    ds.PatientID = fixed.patient_id
    ds.PatientBirthDate = fixed.patient_birth_date
    ds.PatientSex = fixed.patient_sex
    ds.StudyInstanceUID = fixed.study_instance_uid
    ds.StudyDate = fixed.study_date
    ds.StudyTime = fixed.study_time
    ds.ReferringPhysicianName = fixed.referring_physician_name
    ds.StudyID = fixed.study_id
    ds.AccessionNumber = fixed.accession_number
    if fixed.study_description:
        ds.StudyDescription = fixed.study_description
    # General Series and Spatial Registration Series
    ds.Modality = "REG"
    ds.SeriesInstanceUID = generate_uid()
    ds.SeriesNumber = "" if series_number is None else str(int(series_number))
    ds.SeriesDate, ds.SeriesTime = date, time
    if fixed.body_part_examined:
        ds.BodyPartExamined = fixed.body_part_examined
    if fixed.laterality or not fixed.body_part_examined:
        # Type 2C (required for a paired body part): the CT's value, or empty (unknown) where no body part is named
        ds.Laterality = fixed.laterality
    if description:
        ds.SeriesDescription = description
    # Frame of Reference: the CT's
    ds.FrameOfReferenceUID = fixed.frame_of_reference_uid
    ds.PositionReferenceIndicator = fixed.position_reference_indicator
    # General Equipment
    ds.Manufacturer = MANUFACTURER
    ds.ManufacturerModelName = MANUFACTURER
    ds.SoftwareVersions = __version__ if software_version is None else str(software_version)
    # Spatial Registration (with the Content Identification macro)
    ds.ContentDate, ds.ContentTime = date, time
    ds.InstanceNumber = "1"
    ds.ContentLabel = label
    ds.ContentDescription = description
    ds.ContentCreatorName = content_creator_name
    ds.RegistrationSequence = DicomSequence([
        _registration_item(fixed, np.eye(4), _CODE_FRAME_IDENTITY,
                           "Planning CT (fixed): the reference frame, identity"),
        _registration_item(moving, matrix, _CODE_IMAGE_CONTENT,
                           "CBCT (moving) to planning CT (fixed) coordinates, LPS mm"),
    ])
    # Common Instance Reference
    same_study = [s for s in (fixed, moving) if s.instances and s.study_instance_uid == fixed.study_instance_uid]
    if same_study:
        ds.ReferencedSeriesSequence = DicomSequence([_series_item(s) for s in same_study])
    if moving.instances and moving.study_instance_uid != fixed.study_instance_uid:
        study = Dataset()
        study.StudyInstanceUID = moving.study_instance_uid
        study.ReferencedSeriesSequence = DicomSequence([_series_item(moving)])
        ds.StudiesContainingOtherReferencedInstancesSequence = DicomSequence([study])

    partial = out.with_name(f".{out.name}.partial")
    try:
        _save(ds, partial)
        os.replace(partial, out)
    finally:
        partial.unlink(missing_ok=True)
    return out


def _check_reference(ref: SeriesReference, role: str) -> None:
    where = ref.source
    for name, what in (("study_instance_uid", "Study Instance UID"), ("series_instance_uid", "Series Instance UID"),
                       ("frame_of_reference_uid", "Frame of Reference UID")):
        value = getattr(ref, name)
        if not value:
            raise InputError(f"the {role} series has no {what}: a DICOM registration cannot be written without it "
                             "(inputs without DICOM UIDs, such as NIfTI, need user-given UIDs)", where)
        if not is_valid_uid(value):
            raise InputError(f"the {role} series' {what} {value!r} is not a valid DICOM UID", where)
    for inst in ref.instances:
        for value in inst:
            if not is_valid_uid(value):
                raise InputError(f"the {role} series references an invalid SOP UID {value!r}", where)


def _check_rigid(matrix: ArrayLike) -> np.ndarray:
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"moving_to_fixed is not a numeric 4x4 matrix ({exc})") from exc
    if m.shape != (4, 4):
        raise InputError(f"moving_to_fixed must be a 4x4 matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise InputError("moving_to_fixed holds NaN or infinite values")
    r = m[:3, :3]
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise InputError(f"moving_to_fixed is not an affine 4x4 matrix: its last row is {m[3].tolist()}")
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) <= 0:
        raise InputError("moving_to_fixed is not rigid: its 3x3 block is not a proper rotation (scaling, shear or "
                         "a reflection); a RIGID registration cannot hold it")
    return m


def _code_item(code: tuple[str, str, str]) -> Dataset:
    item = Dataset()
    item.CodeValue, item.CodingSchemeDesignator, item.CodeMeaning = code
    return item


def _registration_item(ref: SeriesReference, matrix: np.ndarray, code: tuple[str, str, str],
                       comment: str) -> Dataset:
    matrix_item = Dataset()
    matrix_item.FrameOfReferenceTransformationMatrixType = "RIGID"
    matrix_item.FrameOfReferenceTransformationMatrix = [format_ds(v) for v in np.asarray(matrix).ravel()]
    registration = Dataset()
    registration.RegistrationTypeCodeSequence = DicomSequence([_code_item(code)])
    registration.FrameOfReferenceTransformationComment = comment
    registration.MatrixSequence = DicomSequence([matrix_item])
    item = Dataset()
    item.FrameOfReferenceUID = ref.frame_of_reference_uid
    if ref.instances:
        item.ReferencedImageSequence = DicomSequence(_instance_items(ref.instances))
    item.MatrixRegistrationSequence = DicomSequence([registration])
    return item


def _instance_items(instances: Iterable[InstanceReference]) -> list[Dataset]:
    items = []
    for inst in instances:
        item = Dataset()
        item.ReferencedSOPClassUID = inst.sop_class_uid
        item.ReferencedSOPInstanceUID = inst.sop_instance_uid
        items.append(item)
    return items


def _series_item(ref: SeriesReference) -> Dataset:
    item = Dataset()
    item.SeriesInstanceUID = ref.series_instance_uid
    item.ReferencedInstanceSequence = DicomSequence(_instance_items(ref.instances))
    return item


def _save(ds: FileDataset, path: Path) -> None:
    """Write ``ds`` as a DICOM Part 10 file (preamble, file meta group, explicit VR little endian)."""
    if _PYDICOM_MAJOR >= 3:
        pydicom.dcmwrite(str(path), ds, enforce_file_format=True)
    else:  # pydicom 2.4: the encoding is read from these flags, the file format forced by write_like_original
        ds.is_little_endian, ds.is_implicit_VR = True, False
        pydicom.dcmwrite(str(path), ds, write_like_original=False)


# ---------------------------------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------------------------------
def read_spatial_registration(path: str | Path) -> dict[str, np.ndarray]:
    """The matrices of a DICOM Spatial Registration object, per registered Frame of Reference UID.

    Args:
        path: a REG file (SOP Class 1.2.840.10008.5.1.4.1.1.66.1), written here or by another system.

    Returns:
        ``{frame_of_reference_uid: M}``, one 4x4 float64 matrix per registration item, each mapping patient
        coordinates of that frame (LPS mm) into the REG's own Frame of Reference (for a REG of this module, the
        CT's; its own entry is the identity). Where an item holds several matrices they are composed in the order
        listed (the first applied first).

    Raises:
        InputError: the file is missing, not DICOM, not a Spatial Registration, or an item has no Frame of
            Reference UID or a matrix that is not 16 numbers.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError("no such file", p)
    ds = _read_header(p, p)
    if str(ds.get("SOPClassUID", "")) != SPATIAL_REGISTRATION_SOP_CLASS_UID:
        raise InputError(f"not a DICOM Spatial Registration object (SOP Class UID {ds.get('SOPClassUID', '')!r}, "
                         f"expected {SPATIAL_REGISTRATION_SOP_CLASS_UID})", p)
    out: dict[str, np.ndarray] = {}
    for k, item in enumerate(ds.get("RegistrationSequence", []), start=1):
        uid = str(item.get("FrameOfReferenceUID", "") or "")
        if not uid:
            raise InputError(f"registration item {k} names no Frame of Reference UID (only images)", p)
        total = np.eye(4)
        for registration in item.get("MatrixRegistrationSequence", [])[:1]:
            for matrix_item in registration.get("MatrixSequence", []):
                total = _matrix_values(matrix_item.get("FrameOfReferenceTransformationMatrix"), p, k) @ total
        out[uid] = total
    return out


def _matrix_values(values: Sequence[float] | None, path: Path, k: int) -> np.ndarray:
    try:
        m = np.asarray([float(v) for v in (values or [])], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"registration item {k}: unreadable matrix ({exc})", path) from exc
    if m.size != 16:
        raise InputError(f"registration item {k}: expected 16 matrix values, got {m.size}", path)
    return m.reshape(4, 4)
