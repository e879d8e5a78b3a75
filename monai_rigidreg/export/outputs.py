"""The output folder of a registration: ``transform.tfm`` (or ``.h5``), ``TransformParameters.txt`` (elastix),
``registered.nii.gz``, ``result.json`` (with the couch shifts and the audit trail), ``qc.png`` and, for DICOM
inputs, ``registration.dcm`` (a DICOM Spatial Registration object).

:func:`write_outputs` writes them for a :class:`~monai_rigidreg.registration.RegistrationResult`;
:func:`~monai_rigidreg.registration.files.register_files` reads, registers and writes (the ``register`` command and
the bundle's ``inference.json``); :func:`dicom_references` finds the two series a ``registration.dcm`` refers to.
"""

from __future__ import annotations

import json
import logging
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import SimpleITK as sitk

from monai_rigidreg import __version__
from monai_rigidreg.core.errors import InputError, signals_deferred
from monai_rigidreg.core.geometry import invert_matrix
from monai_rigidreg.export.elastix_params import ELASTIX_PARAMETER_FILE, write_elastix_transform
from monai_rigidreg.export.qc_figure import qc_figure
from monai_rigidreg.export.record import complete_record
from monai_rigidreg.export.transform_files import write_transform
from monai_rigidreg.io.staging import staged_output_dir, step
from monai_rigidreg.io.volumes import resample, save_volume

if TYPE_CHECKING:  # pydicom is imported on use: NIfTI inputs do not pay for it (0.08 s, python -X importtime)
    from monai_rigidreg.export.dicom_reg import SeriesReference
    from monai_rigidreg.registration.result import RegistrationResult

__all__ = [
    "OUTPUT_FILES",
    "DEFAULT_OUTPUT_FILES",
    "TRANSFORM_FORMATS",
    "REG_MODES",
    "NO_REG_FOR_FILES",
    "write_outputs",
    "dicom_references",
]

logger = logging.getLogger(__name__)

OUTPUT_FILES: tuple[str, ...] = ("transform.tfm", "transform.h5", ELASTIX_PARAMETER_FILE, "registered.nii.gz",
                                  "result.json", "qc.png", "registration.dcm")
"""The files :func:`write_outputs` can write: ``transform.tfm`` or ``transform.h5`` (``transform_format``),
``qc.png`` with ``qc=True``, ``registration.dcm`` with DICOM references; the others always."""
DEFAULT_OUTPUT_FILES: tuple[str, ...] = ("transform.tfm", ELASTIX_PARAMETER_FILE, "registered.nii.gz", "result.json",
                                          "qc.png")
"""What :func:`write_outputs` writes with its defaults (no DICOM references)."""
TRANSFORM_FORMATS: tuple[str, ...] = ("tfm", "h5")
REG_MODES: tuple[str, ...] = ("auto", "on", "off")
"""``registration.dcm``: ``auto`` where both inputs are DICOM series with their own frames of reference (else a
warning says why not), ``on`` required (refused before registering when it cannot be written), ``off`` never."""


def write_outputs(
    result: RegistrationResult,
    fixed: sitk.Image,
    moving: sitk.Image,
    output_dir: str | Path,
    overwrite: bool = False,
    qc: bool = True,
    names: tuple[str, str] | None = None,
    transform_format: str = "tfm",
    dicom_references: tuple[SeriesReference, SeriesReference] | None = None,
) -> dict[str, Path]:
    """Write :data:`OUTPUT_FILES` for ``result`` into ``output_dir`` (``names``: the inputs' display names for the
    QC figure, e.g. their file names). A result without couch shifts or audit trail (a bare registrar's) gets the
    defaults first, in place (:func:`~monai_rigidreg.export.record.complete_record`), so every ``result.json`` has
    both.

    Everything is written to a hidden sibling folder first and renamed into place at the end, so a failure, Ctrl-C
    or SIGTERM leaves no partial output and no temporary folder (nor the parent folders this call created). An
    existing non-empty ``output_dir`` is refused unless ``overwrite``, a file of that name always
    (:func:`~monai_rigidreg.io.volumes.check_output_dir`). The final rename never replaces a folder that another process
    filled meanwhile (two runs into one new folder: one wins, the other is refused and the winner's files are
    kept); with ``overwrite`` the old folder is renamed aside and removed only once the new one is in place.

    ``TransformParameters.txt`` is the same transform for elastix's ``transformix``: applied to the CBCT it gives
    ``registered.nii.gz`` (linear interpolation, the same fill value: the CBCT's minimum). With
    ``dicom_references`` (the CT's and the CBCT's series, :func:`~monai_rigidreg.export.dicom_reg.series_reference`),
    ``registration.dcm`` stores the inverse matrix (CBCT -> CT coordinates) as DICOM defines it.

    Returns:
        ``{file name: path}`` of the files written.

    Raises:
        OutputExistsError: ``output_dir`` exists (or appeared while this call ran) and is not empty.
    """
    if transform_format not in TRANSFORM_FORMATS:
        raise InputError(f"transform format must be one of {TRANSFORM_FORMATS}, got {transform_format!r}")
    complete_record(result, moving, names=names)  # a result without couch shifts or audit trail gets the defaults
    out = Path(output_dir)
    fill = float(sitk.GetArrayViewFromImage(moving).min())  # io.resample's default: air for a CT
    with staged_output_dir(out, overwrite, replaceable=OUTPUT_FILES) as tmp:
        write_transform(result.transform, tmp / f"transform.{transform_format}")
        step(f"transform.{transform_format}")
        write_elastix_transform(tmp / ELASTIX_PARAMETER_FILE, result.params, result.center, fixed, fill)
        step(ELASTIX_PARAMETER_FILE)
        # the registrar's own resampling where it was made under these parameters (params changed since: again)
        registered = result.registered if result.registered_is_current() else resample(
            moving, fixed, result.transform, default_value=fill)
        # registered.nii.gz is compressed (zlib, outside the GIL) in a worker while the rest is written and the QC
        # figure drawn: 0.142 -> 0.100 s for the two on a bench_speed pair (benchmarks/speed/bench_network_paths.py);
        # the worker is joined before the staged folder is moved into place or removed (with Ctrl-C and SIGTERM
        # held back: an interrupted join would let it write into a folder being removed), and its error is raised
        pool = ThreadPoolExecutor(max_workers=1)
        try:
            saving = pool.submit(save_volume, registered, tmp / "registered.nii.gz")
            step("registered.nii.gz (started)")
            if dicom_references is not None:
                from monai_rigidreg.export.dicom_reg import write_spatial_registration

                write_spatial_registration(tmp / "registration.dcm", *dicom_references,
                                           invert_matrix(result.matrix), software_version=__version__)
                step("registration.dcm")
            (tmp / "result.json").write_text(json.dumps(result.to_dict(), indent=2))
            step("result.json")
            if qc:
                p = result.params
                title = (f"tx={p[0]:.2f} ty={p[1]:.2f} tz={p[2]:.2f} mm   rx={p[3]:.2f} ry={p[4]:.2f} rz={p[5]:.2f} "
                         f"deg   confidence={result.confidence:.2f}{'  FLAGGED' if result.flagged else ''}")
                qc_figure(fixed, moving, registered, tmp / "qc.png", title=title, transform=result.transform,
                          names=names)
                step("qc.png")
            saving.result()
            step("registered.nii.gz")
        finally:
            with signals_deferred():
                pool.shutdown(wait=True)
    return {name: out / name for name in OUTPUT_FILES if (out / name).exists()}


NO_REG_FOR_FILES = ("no DICOM Spatial Registration (registration.dcm) written: it needs both inputs as DICOM series "
                    "(NIfTI and other files carry no UIDs to refer to); build one with "
                    "monai_rigidreg.export.dicom_reg.write_spatial_registration and user-given UIDs")


def dicom_references(fixed: str | Path, moving: str | Path, fixed_series_uid: str | None = None,
                     moving_series_uid: str | None = None, reg: str = "auto"
                     ) -> tuple[tuple[SeriesReference, SeriesReference] | None, str]:
    """The two series a ``registration.dcm`` refers to, read from the DICOM headers before anything is registered.

    Returns:
        ``(references or None, why not)``: with ``reg="auto"`` the reason where two DICOM series cannot get a REG
        (a shared or missing Frame of Reference UID: a warning for the result); inputs that are not DICOM get none,
        said in the log. Never an invented relationship.

    Raises:
        InputError: ``reg="on"`` and the REG cannot be written (naming why), or an unknown ``reg``.
    """
    if reg not in REG_MODES:
        raise InputError(f"reg must be one of {REG_MODES}, got {reg!r}")
    if reg == "off":
        return None, ""
    why = ""
    if not (Path(fixed).is_dir() and Path(moving).is_dir()):
        why = NO_REG_FOR_FILES
        if reg == "auto":  # the ordinary case for file inputs: said in the log once the outputs are written
            return None, ""
    else:
        try:
            from monai_rigidreg.export.dicom_reg import series_reference

            refs = (series_reference(fixed, fixed_series_uid), series_reference(moving, moving_series_uid))
            if refs[0].patient_id and refs[1].patient_id and refs[0].patient_id != refs[1].patient_id:
                raise InputError(f"the CT and the CBCT name different patients (Patient ID {refs[0].patient_id!r} "
                                 f"and {refs[1].patient_id!r})")
            if refs[0].frame_of_reference_uid == refs[1].frame_of_reference_uid:
                raise InputError("the CT and the CBCT share one Frame of Reference UID "
                                 f"({refs[0].frame_of_reference_uid}), so no registration between two frames can be "
                                 "stored")
            return refs, ""
        except InputError as exc:
            why = f"no DICOM Spatial Registration (registration.dcm) written: {exc}"
    if reg == "on":
        raise InputError(why.replace(" written:", " can be written:", 1))
    return None, why


