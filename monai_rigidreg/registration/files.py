"""Files in, files out: the inputs read, registered and the output folder written (the ``register`` command, the
bundle's ``inference.json`` and :class:`~monai_rigidreg.registration.pairs.RegistrationEvaluator`)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import PARAM_NAMES
from monai_rigidreg.export.couch_shifts import lps_to_iec
from monai_rigidreg.export.outputs import NO_REG_FOR_FILES, TRANSFORM_FORMATS, dicom_references, write_outputs
from monai_rigidreg.export.provenance import registration_provenance
from monai_rigidreg.export.record import ASSUMED_POSITION_SOURCE, couch_shift_record
from monai_rigidreg.io.dicom_series import check_distinct_inputs
from monai_rigidreg.io.volumes import load_volume
from monai_rigidreg.registration.inputs import check_register_inputs, check_same_patient
from monai_rigidreg.registration.match_region import MATCH_MODES, parse_roi
from monai_rigidreg.registration.registrar import RigidRegistrar

__all__ = ["register_files"]

logger = logging.getLogger(__name__)


def register_files(
    registrar: RigidRegistrar,
    fixed: str | Path,
    moving: str | Path,
    output_dir: str | Path,
    refine: bool = False,
    overwrite: bool = False,
    qc: bool = True,
    cascade_steps: int | None = None,
    fixed_series_uid: str | None = None,
    moving_series_uid: str | None = None,
    isocenter: Any = None,
    reg: str = "auto",
    transform_format: str = "tfm",
    fine_stage: bool | None = None,
    patient_position: str | None = None,
    global_init: bool | None = None,
    roi: Any = None,
    match: str = "soft",
    keep_couch: bool = False,
    allow_swapped: bool = False,
    allow_other_patient: bool = False,
) -> dict[str, Path]:
    """Load both volumes, register them and write the standard outputs.

    The inputs and the output folder are checked (:func:`~monai_rigidreg.registration.inputs.check_register_inputs`)
    before anything is read or computed, so a refused run costs nothing and writes nothing.

    Args:
        registrar: the loaded network (:meth:`~monai_rigidreg.registration.RigidRegistrar.from_bundle`).
        fixed, moving: CT and CBCT: NIfTI, MHA, NRRD or a DICOM folder.
        output_dir: the folder to write (must not exist or be empty unless ``overwrite``).
        refine, cascade_steps: as for :func:`~monai_rigidreg.registration.register`.
        overwrite, qc: as for :func:`~monai_rigidreg.export.outputs.write_outputs`.
        fixed_series_uid, moving_series_uid: DICOM series to read from a folder holding several.
        isocenter: plan isocentre (LPS mm, CT coordinates) of the couch shifts; default: the CBCT's centre (its
            coordinates taken as a CT point: a CBCT is reconstructed about the treatment isocentre), recorded in
            ``result.json`` with where it came from. The CT's DICOM Patient Position orients the couch axes
            (missing: head-first supine is assumed, with a warning, and recorded).
        reg: ``registration.dcm``: one of :data:`~monai_rigidreg.export.outputs.REG_MODES`.
        transform_format: ``"tfm"`` or ``"h5"`` (the ITK transform file).
        fine_stage: ``False``: the learned regression alone (see :func:`~monai_rigidreg.registration.register`).
        global_init, roi, match, keep_couch, allow_swapped: the global search, the region of interest, the match
            mode, the couches and inputs that look swapped, as for :func:`~monai_rigidreg.registration.register` (the
            ROI is read and checked before registering).
        allow_other_patient: register DICOM inputs whose headers name different patients (default: refused before
            registering, :func:`~monai_rigidreg.registration.inputs.check_same_patient`).
        patient_position: DICOM Patient Position of the CT (``HFS``, ``FFS``, ...) for the couch axes; default the
            CT's DICOM header, else head-first supine (assumed, with a warning). A value given here that the couch
            shifts do not support is refused before registering; one read from the header gives a warning and no
            couch shifts.

    Returns:
        ``{file name: path}`` of the files written (the result itself is in ``result.json``).
    """
    check_register_inputs(fixed, moving, output_dir, overwrite, cascade_steps)
    check_distinct_inputs(fixed, moving, fixed_series_uid, moving_series_uid)
    roi = parse_roi(roi)
    if match not in MATCH_MODES:
        raise InputError(f"match must be one of {MATCH_MODES}, got {match!r}")
    if transform_format not in TRANSFORM_FORMATS:
        raise InputError(f"--transform-format must be one of {TRANSFORM_FORMATS}, got {transform_format!r}")
    iso = None if isocenter is None else _point(isocenter, "isocenter")
    refs, reg_warning = dicom_references(fixed, moving, fixed_series_uid, moving_series_uid, reg)
    # the audit trail's header facts are read once, before registering; the couch axes come from them
    provenance = registration_provenance(fixed, moving, fixed_series_uid, moving_series_uid,
                                         bundle=getattr(registrar, "source", {}), device=str(registrar.device))
    patient_warning = check_same_patient(provenance["inputs"]["fixed"], provenance["inputs"]["moving"],
                                         allow_other_patient)
    position, position_source, position_problem = _patient_position(provenance["inputs"]["fixed"], patient_position)
    position_mismatch = _position_mismatch(provenance["inputs"]["fixed"], provenance["inputs"]["moving"], position,
                                           position_source)
    load_warnings: list[str] = []  # e.g. a DICOM series resampled over a slice gap
    fixed_img = load_volume(fixed, series_uid=fixed_series_uid, warnings=load_warnings)
    moving_img = load_volume(moving, series_uid=moving_series_uid, warnings=load_warnings)
    result = registrar(fixed_img, moving_img, refine=refine, cascade_steps=cascade_steps, fine_stage=fine_stage,
                       global_init=global_init, roi=roi, match=match, keep_couch=keep_couch,
                       allow_swapped=allow_swapped)
    result.provenance = provenance
    if load_warnings:  # in the audit trail too, before the registration's own
        result.details["warnings"] = load_warnings + result.details.get("warnings", [])
    for warning in (patient_warning, reg_warning, position_problem, position_mismatch):  # logged and recorded
        if warning:
            logger.warning("%s", warning)
            result.details.setdefault("warnings", []).append(warning)
    result.couch_shift = couch_shift_record(result.matrix, moving_img, position, position_source, iso,
                                            position_problem)
    paths = write_outputs(result, fixed_img, moving_img, output_dir, overwrite=overwrite, qc=qc,
                          names=(Path(fixed).name, Path(moving).name), transform_format=transform_format,
                          dicom_references=refs)
    if refs is None and reg == "auto" and not reg_warning:
        logger.info("%s", NO_REG_FOR_FILES)
    reasons = (result.details or {}).get("flag_reasons") or []
    look = ", check the QC figure" if qc else ", check the registered image"
    flag = f"; FLAGGED: {', '.join(reasons) or 'likely failure'}{look}" if result.flagged else ""
    logger.info("registered %s to %s: %s (confidence %s%s)", moving, fixed,
                ", ".join(f"{n}={v:.2f}" for n, v in zip(PARAM_NAMES, result.params)),
                "not assessed" if result.confidence is None else f"{result.confidence:.2f}", flag)
    return paths




def _patient_position(fixed_record: dict[str, Any], given: str | None) -> tuple[str | None, str, str]:
    """``(position or None, where it came from, why no couch shifts can be given or "")`` from ``--patient-position``
    or the CT's :func:`~monai_rigidreg.export.provenance.input_record`, before registering."""
    if given:
        lps_to_iec(given)  # InputError for an unsupported value the user gave: before any work
        return given.strip().upper(), "--patient-position", ""
    if fixed_record.get("format") != "dicom":
        return None, ASSUMED_POSITION_SOURCE, ""
    header = fixed_record.get("patient_position") or None
    if header is None:
        return None, "assumed (no Patient Position in the CT's header)", ""
    try:
        lps_to_iec(header)
    except InputError as exc:
        return None, "CT DICOM header", f"no couch shifts: the CT's {exc}"
    return header, "CT DICOM header", ""


def _position_mismatch(fixed_record: dict[str, Any], moving_record: dict[str, Any], position: str | None,
                       position_source: str) -> str:
    """The warning to record where the CT's and the CBCT's DICOM Patient Position (0018,5100) differ, naming the
    position the couch shifts use (``position`` from ``position_source``, :func:`_patient_position`; ``None``: no
    couch shifts), else ``""``; nothing is said where either lacks one.

    >>> hfs, ffs = ({"format": "dicom", "patient_position": p} for p in ("HFS", "FFS"))
    >>> _position_mismatch(hfs, ffs, "HFS", "CT DICOM header").split(";")[0]
    "the CT's Patient Position is HFS and the CBCT's FFS: the couch shifts use HFS (CT DICOM header)"
    """
    if fixed_record.get("format") != "dicom" or moving_record.get("format") != "dicom":
        return ""
    ct, cbct = (str(r.get("patient_position") or "").strip().upper() for r in (fixed_record, moving_record))
    if not ct or not cbct or ct == cbct:
        return ""
    used = f"the couch shifts use {position} ({position_source})" if position else "no couch shifts are given"
    return (f"the CT's Patient Position is {ct} and the CBCT's {cbct}: {used}; a patient treated in another "
            "position than planned needs checking before the couch is moved")


def _point(value: Any, name: str) -> tuple[float, float, float]:
    """``"x,y,z"`` or three numbers -> a point (mm); :class:`~monai_rigidreg.core.errors.InputError` otherwise."""
    parts = value.replace(",", " ").split() if isinstance(value, str) else list(value)
    try:
        point = tuple(float(v) for v in parts)
    except (TypeError, ValueError):
        point = ()
    if len(point) != 3 or not all(abs(v) < 1e6 for v in point):
        raise InputError(f"{name} must be three numbers x,y,z in mm (CT coordinates, LPS), got {value!r}")
    return point  # type: ignore[return-value]
