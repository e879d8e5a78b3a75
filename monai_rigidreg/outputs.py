"""The files of a registration: ``transform.tfm`` (or ``.h5``), ``TransformParameters.txt`` (elastix),
``registered.nii.gz``, ``result.json`` (with the couch shifts and the audit trail), ``qc.png`` and, for DICOM
inputs, ``registration.dcm`` (a DICOM Spatial Registration object).

:func:`write_outputs` writes them for a :class:`~monai_rigidreg.registration.RegistrationResult`;
:func:`register_files` reads, registers and writes (the ``register`` command and the bundle's ``inference.json``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import sys
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import SimpleITK as sitk

from monai_rigidreg import __version__
from monai_rigidreg.couch import couch_shifts, lps_to_iec
from monai_rigidreg.elastix_params import ELASTIX_PARAMETER_FILE, write_elastix_transform
from monai_rigidreg.errors import InputError, RigidRegError, Terminated, sigterm_raises
from monai_rigidreg.geometry import PARAM_NAMES, Grid, invert_matrix
from monai_rigidreg.io import (
    check_distinct_inputs,
    check_output_dir,
    load_volume,
    resample,
    save_volume,
    write_transform,
)
from monai_rigidreg.match_region import MATCH_MODES, parse_roi
from monai_rigidreg.provenance import registration_provenance
from monai_rigidreg.qc import qc_figure
from monai_rigidreg.registration import RegistrationResult, RigidRegistrar, _check_steps
from monai_rigidreg.staging import check_replaceable, staged_output_dir

if TYPE_CHECKING:  # pydicom is imported on use: NIfTI inputs do not pay for it (0.08 s, python -X importtime)
    from monai_rigidreg.dicom_reg import SeriesReference

__all__ = [
    "OUTPUT_FILES",
    "DEFAULT_OUTPUT_FILES",
    "TRANSFORM_FORMATS",
    "REG_MODES",
    "write_outputs",
    "staged_output_dir",
    "register_files",
    "dicom_references",
    "check_bundle_options",
    "bundle_evaluate",
    "check_register_inputs",
    "bundle_check_inputs",
    "bundle_errors",
    "bundle_register_files",
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
    QC figure, e.g. their file names).

    Everything is written to a hidden sibling folder first and renamed into place at the end, so a failure, Ctrl-C
    or SIGTERM leaves no partial output and no temporary folder (nor the parent folders this call created). An
    existing non-empty ``output_dir`` is refused unless ``overwrite``, a file of that name always
    (:func:`~monai_rigidreg.io.check_output_dir`). The final rename never replaces a folder that another process
    filled meanwhile (two runs into one new folder: one wins, the other is refused and the winner's files are
    kept); with ``overwrite`` the old folder is renamed aside and removed only once the new one is in place.

    ``TransformParameters.txt`` is the same transform for elastix's ``transformix``: applied to the CBCT it gives
    ``registered.nii.gz`` (linear interpolation, the same fill value: the CBCT's minimum). With
    ``dicom_references`` (the CT's and the CBCT's series, :func:`~monai_rigidreg.dicom_reg.series_reference`),
    ``registration.dcm`` stores the inverse matrix (CBCT -> CT coordinates) as DICOM defines it.

    Returns:
        ``{file name: path}`` of the files written.

    Raises:
        OutputExistsError: ``output_dir`` exists (or appeared while this call ran) and is not empty.
    """
    if transform_format not in TRANSFORM_FORMATS:
        raise InputError(f"transform format must be one of {TRANSFORM_FORMATS}, got {transform_format!r}")
    out = Path(output_dir)
    fill = float(sitk.GetArrayViewFromImage(moving).min())  # io.resample's default: air for a CT
    with staged_output_dir(out, overwrite, replaceable=OUTPUT_FILES) as tmp:
        write_transform(result.transform, tmp / f"transform.{transform_format}")
        write_elastix_transform(tmp / ELASTIX_PARAMETER_FILE, result.params, result.center, fixed, fill)
        registered = result.registered if result.registered is not None else resample(moving, fixed, result.transform,
                                                                                      default_value=fill)
        # registered.nii.gz is compressed (zlib, outside the GIL) in a worker while the rest is written and the QC
        # figure drawn: 0.142 -> 0.100 s for the two on a bench_speed pair (benchmarks/bench_network_paths.py); the
        # pool is joined before the staged folder is moved into place or removed, and the worker's error is raised
        with ThreadPoolExecutor(max_workers=1) as pool:
            saving = pool.submit(save_volume, registered, tmp / "registered.nii.gz")
            if dicom_references is not None:
                from monai_rigidreg.dicom_reg import write_spatial_registration

                write_spatial_registration(tmp / "registration.dcm", *dicom_references,
                                           invert_matrix(result.matrix), software_version=__version__)
            (tmp / "result.json").write_text(json.dumps(result.to_dict(), indent=2))
            if qc:
                p = result.params
                title = (f"tx={p[0]:.2f} ty={p[1]:.2f} tz={p[2]:.2f} mm   rx={p[3]:.2f} ry={p[4]:.2f} rz={p[5]:.2f} "
                         f"deg   confidence={result.confidence:.2f}{'  FLAGGED' if result.flagged else ''}")
                qc_figure(fixed, moving, registered, tmp / "qc.png", title=title, transform=result.transform,
                          names=names)
            saving.result()
    return {name: out / name for name in OUTPUT_FILES if (out / name).exists()}


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
) -> dict[str, Path]:
    """Load both volumes, register them and write the standard outputs.

    The inputs and the output folder are checked (:func:`check_register_inputs`) before anything is read or
    computed, so a refused run costs nothing and writes nothing.

    Args:
        registrar: the loaded network (:meth:`~monai_rigidreg.registration.RigidRegistrar.from_bundle`).
        fixed, moving: CT and CBCT: NIfTI, MHA, NRRD or a DICOM folder.
        output_dir: the folder to write (must not exist or be empty unless ``overwrite``).
        refine, cascade_steps: as for :func:`~monai_rigidreg.registration.register`.
        overwrite, qc: as for :func:`write_outputs`.
        fixed_series_uid, moving_series_uid: DICOM series to read from a folder holding several.
        isocenter: plan isocentre (LPS mm, CT coordinates) of the couch shifts; default: the CBCT's centre (its
            coordinates taken as a CT point: a CBCT is reconstructed about the treatment isocentre), recorded in
            ``result.json`` with where it came from. The CT's DICOM Patient Position orients the couch axes
            (missing: head-first supine is assumed, with a warning, and recorded).
        reg: ``registration.dcm``: one of :data:`REG_MODES`.
        transform_format: ``"tfm"`` or ``"h5"`` (the ITK transform file).
        fine_stage: ``False``: the learned regression alone (see :func:`~monai_rigidreg.registration.register`).
        global_init, roi, match, keep_couch: the global search, the region of interest, the match mode and the
            couches, as for :func:`~monai_rigidreg.registration.register` (the ROI is read and checked before
            registering).
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
    position, position_source, position_problem = _patient_position(provenance["inputs"]["fixed"], patient_position)
    load_warnings: list[str] = []  # e.g. a DICOM series resampled over a slice gap
    fixed_img = load_volume(fixed, series_uid=fixed_series_uid, warnings=load_warnings)
    moving_img = load_volume(moving, series_uid=moving_series_uid, warnings=load_warnings)
    result = registrar(fixed_img, moving_img, refine=refine, cascade_steps=cascade_steps, fine_stage=fine_stage,
                       global_init=global_init, roi=roi, match=match, keep_couch=keep_couch)
    result.provenance = provenance
    if load_warnings:  # in the audit trail too, before the registration's own
        result.details["warnings"] = load_warnings + result.details.get("warnings", [])
    if reg_warning:
        logger.warning("%s", reg_warning)
        result.details.setdefault("warnings", []).append(reg_warning)
    source = "--isocenter" if iso is not None else "CBCT centre (default)"
    if iso is None:
        iso = Grid.from_sitk(moving_img).center()
    if position_problem:
        logger.warning("%s", position_problem)
        result.details.setdefault("warnings", []).append(position_problem)
        result.couch_shift = {"unavailable": position_problem}
    else:
        result.couch_shift = {**couch_shifts(result.matrix, position, iso).to_dict(), "isocentre_source": source,
                              "patient_position_source": position_source}
    paths = write_outputs(result, fixed_img, moving_img, output_dir, overwrite=overwrite, qc=qc,
                          names=(Path(fixed).name, Path(moving).name), transform_format=transform_format,
                          dicom_references=refs)
    if refs is None and reg == "auto" and not reg_warning:
        logger.info("%s", NO_REG_FOR_FILES)
    logger.info("registered %s to %s: %s (confidence %.2f)", moving, fixed,
                ", ".join(f"{n}={v:.2f}" for n, v in zip(PARAM_NAMES, result.params)), result.confidence)
    return paths


NO_REG_FOR_FILES = ("no DICOM Spatial Registration (registration.dcm) written: it needs both inputs as DICOM series "
                    "(NIfTI and other files carry no UIDs to refer to); build one with "
                    "monai_rigidreg.dicom_reg.write_spatial_registration and user-given UIDs")


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
            from monai_rigidreg.dicom_reg import series_reference

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


def _patient_position(fixed_record: dict[str, Any], given: str | None) -> tuple[str | None, str, str]:
    """``(position or None, where it came from, why no couch shifts can be given or "")`` from ``--patient-position``
    or the CT's :func:`~monai_rigidreg.provenance.input_record`, before registering."""
    if given:
        lps_to_iec(given)  # InputError for an unsupported value the user gave: before any work
        return given.strip().upper(), "--patient-position", ""
    if fixed_record.get("format") != "dicom":
        return None, "assumed (no DICOM header)", ""
    header = fixed_record.get("patient_position") or None
    if header is None:
        return None, "assumed (no Patient Position in the CT's header)", ""
    try:
        lps_to_iec(header)
    except InputError as exc:
        return None, "CT DICOM header", f"no couch shifts: the CT's {exc}"
    return header, "CT DICOM header", ""


def _point(value: Any, name: str) -> tuple[float, float, float]:
    """``"x,y,z"`` or three numbers -> a point (mm); :class:`~monai_rigidreg.errors.InputError` otherwise."""
    parts = value.replace(",", " ").split() if isinstance(value, str) else list(value)
    try:
        point = tuple(float(v) for v in parts)
    except (TypeError, ValueError):
        point = ()
    if len(point) != 3 or not all(abs(v) < 1e6 for v in point):
        raise InputError(f"{name} must be three numbers x,y,z in mm (CT coordinates, LPS), got {value!r}")
    return point  # type: ignore[return-value]


def check_register_inputs(
    fixed: str | Path | None,
    moving: str | Path | None,
    output_dir: str | Path,
    overwrite: bool = False,
    cascade_steps: Any = None,
) -> Path:
    """The checks of a registration run, done once before anything is loaded: both inputs given and present, the
    cascade steps (if given) a whole number >= 1, and an output folder that may be written
    (:func:`~monai_rigidreg.io.check_output_dir`). The ``register`` command and the bundle's ``inference.json``
    both go through it.

    Returns:
        ``output_dir`` as a ``Path``.

    Raises:
        InputError: a missing input (naming it), a bad ``cascade_steps``, an output folder that cannot be made.
        OutputExistsError: the output folder is a file, or not empty and ``overwrite`` is False.
    """
    for name, path in (("fixed", fixed), ("moving", moving)):
        if path is None or not str(path).strip():
            raise InputError(f"no {name} image given: both 'fixed' (the CT) and 'moving' (the CBCT) are needed "
                             "(e.g. --fixed CT.nii.gz --moving CBCT.nii.gz)")
        if not Path(path).exists():
            raise InputError(f"no such file or directory (the {name} image)", path)
    if cascade_steps is not None:
        _check_steps(cascade_steps)
    out = check_output_dir(output_dir, overwrite)
    if overwrite:
        check_replaceable(out, OUTPUT_FILES)  # never delete what this package did not write, e.g. the inputs
    return out


@contextlib.contextmanager
def bundle_errors() -> Iterator[None]:
    """``python -m monai.bundle run`` prints a traceback for anything raised in a config expression, ending with
    MONAI's "Failed to evaluate ConfigExpression"; the package's own errors end the run instead with their message
    on one line and the exit status of the command line (2; 130 for Ctrl-C, 143 for SIGTERM)."""
    try:
        with sigterm_raises(only_if_default=True):
            yield
    except RigidRegError as exc:
        print(f"monai-rigidreg bundle: error: {exc}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None
    except KeyboardInterrupt as exc:
        print("monai-rigidreg bundle: " + ("terminated" if isinstance(exc, Terminated) else "interrupted"),
              file=sys.stderr, flush=True)
        raise SystemExit(143 if isinstance(exc, Terminated) else 130) from None


def check_bundle_options(flags: dict[str, Any] | None = None, device: Any = None) -> None:
    """The bundle's switches and device as ``python -m monai.bundle run`` hands them over: its command line reads
    ``--refine False`` as the boolean but ``--refine false`` as the text ``"false"``, which Python takes as true (the
    refinement ran). Each of ``flags`` must be a boolean (or 0 / 1); ``device`` a ``torch.device`` or a name torch
    knows on this machine (``cpu``, ``cuda``, ``cuda:N``).

    Raises:
        InputError: the first value that is neither, naming the option.
    """
    for name, value in (flags or {}).items():
        if not (isinstance(value, (bool, np.bool_)) or (isinstance(value, int) and value in (0, 1))):
            raise InputError(f"--{name} must be True or False (with capitals on monai.bundle's command line: it "
                             f"reads 'true' or 'false' as text), got {value!r}")
    if device is not None and not hasattr(device, "type"):
        from monai_rigidreg.device import resolve_device

        if str(device) == "auto":
            raise InputError("--device auto: leave --device out for the automatic choice, or give cpu, cuda or "
                             "cuda:N")
        resolve_device(device)


def bundle_check_inputs(fixed: str | Path | None, moving: str | Path | None, output_dir: str | Path,
                        overwrite: bool = False, cascade_steps: Any = None, datalist: str | Path | None = None,
                        flags: dict[str, Any] | None = None, device: Any = None) -> None:
    """:func:`check_register_inputs` for the bundle's ``inference.json`` (its first ``initialize`` step, before the
    network is built): a bad input ends the run with one line naming the problem and exit status 2. With a
    ``datalist`` of pairs (batch registration) the datalist must exist and each pair is checked when its turn
    comes (:class:`~monai_rigidreg.batch.RegistrationEvaluator`). ``flags`` and ``device``: as
    :func:`check_bundle_options`.

    For ``python -m monai.bundle run``: it raises ``SystemExit`` rather than an exception.
    """
    with bundle_errors():
        check_bundle_options(flags, device)
        if not datalist:
            check_register_inputs(fixed, moving, output_dir, overwrite, cascade_steps)
            return
        if fixed or moving:
            raise InputError("give either --fixed/--moving (one pair) or --datalist (pairs), not both")
        if not Path(datalist).is_file():
            raise InputError("no such datalist file", datalist)
        if cascade_steps is not None:
            _check_steps(cascade_steps)
        check_output_dir(output_dir, overwrite, allow_existing=True)


def bundle_evaluate(datalist: str | Path, methods: Any, output_dir: str | Path, registrar: RigidRegistrar,
                    max_cases: Any = None, overwrite: Any = False) -> dict[str, Any]:
    """:func:`~monai_rigidreg.evaluation.evaluate.evaluate_datalist` for the bundle's ``evaluate.json``: prints the
    report; a bad datalist, method or output folder ends the run with one line and exit status 2 (was a traceback)."""
    from monai_rigidreg.evaluation.evaluate import evaluate_datalist

    with bundle_errors():
        check_bundle_options({"overwrite": overwrite})
        if isinstance(methods, str) or not isinstance(methods, (list, tuple)):
            raise InputError(f"--methods must be a list, e.g. \"['network']\", got {methods!r}")
        out = evaluate_datalist(datalist, list(methods), output_dir, registrar=registrar, max_cases=max_cases,
                                overwrite=bool(overwrite))
        print(out["report"])
        return out


def bundle_register_files(registrar: RigidRegistrar, fixed: str | Path, moving: str | Path, output_dir: str | Path,
                          **kwargs: Any) -> dict[str, Path]:
    """:func:`register_files` for the bundle's ``inference.json`` (``run``): errors as in :func:`bundle_check_inputs`
    (an unreadable image, for example, ends the run with one line and exit status 2)."""
    with bundle_errors():
        return register_files(registrar, fixed, moving, output_dir, **kwargs)
