"""The files of a registration: ``transform.tfm``, ``registered.nii.gz``, ``result.json`` and ``qc.png``.

:func:`write_outputs` writes them for a :class:`~monai_rigidreg.registration.RegistrationResult`;
:func:`register_files` reads, registers and writes (the ``register`` command and the bundle's ``inference.json``).
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
from pathlib import Path

import SimpleITK as sitk

from monai_rigidreg.errors import InputError
from monai_rigidreg.geometry import PARAM_NAMES
from monai_rigidreg.io import (
    check_distinct_inputs,
    check_output_dir,
    load_volume,
    resample,
    save_volume,
    write_transform,
)
from monai_rigidreg.qc import qc_figure
from monai_rigidreg.registration import RegistrationResult, RigidRegistrar

__all__ = ["OUTPUT_FILES", "write_outputs", "register_files"]

logger = logging.getLogger(__name__)

OUTPUT_FILES: tuple[str, ...] = ("transform.tfm", "registered.nii.gz", "result.json", "qc.png")
"""The files :func:`write_outputs` writes (``qc.png`` only with ``qc=True``)."""


def write_outputs(
    result: RegistrationResult,
    fixed: sitk.Image,
    moving: sitk.Image,
    output_dir: str | Path,
    overwrite: bool = False,
    qc: bool = True,
) -> dict[str, Path]:
    """Write :data:`OUTPUT_FILES` for ``result`` into ``output_dir``.

    Everything is written to a temporary sibling folder first and moved into place at the end, so a failure
    leaves no partial output; an existing non-empty ``output_dir`` is refused unless ``overwrite``, a file of that
    name always (:func:`~monai_rigidreg.io.check_output_dir`).

    Returns:
        ``{file name: path}`` of the files written.
    """
    out = check_output_dir(output_dir, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        write_transform(result.transform, tmp / "transform.tfm")
        registered = result.registered if result.registered is not None else resample(moving, fixed, result.transform)
        save_volume(registered, tmp / "registered.nii.gz")
        (tmp / "result.json").write_text(json.dumps(result.to_dict(), indent=2))
        if qc:
            p = result.params
            title = (f"tx={p[0]:.2f} ty={p[1]:.2f} tz={p[2]:.2f} mm   rx={p[3]:.2f} ry={p[4]:.2f} rz={p[5]:.2f} deg"
                     f"   confidence={result.confidence:.2f}{'  FLAGGED' if result.flagged else ''}")
            qc_figure(fixed, moving, registered, tmp / "qc.png", title=title)
        if out.is_dir():
            shutil.rmtree(out)
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
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
) -> dict[str, Path]:
    """Load both volumes, register them and write the standard outputs.

    The output folder is checked before anything is read or computed, so a refused folder costs nothing.

    Args:
        registrar: the loaded network (:meth:`~monai_rigidreg.registration.RigidRegistrar.from_bundle`).
        fixed, moving: CT and CBCT: NIfTI, MHA, NRRD or a DICOM folder.
        output_dir: the folder to write (must not exist or be empty unless ``overwrite``).
        refine, cascade_steps: as for :func:`~monai_rigidreg.registration.register`.
        overwrite, qc: as for :func:`write_outputs`.
        fixed_series_uid, moving_series_uid: DICOM series to read from a folder holding several.

    Returns:
        ``{file name: path}`` of the files written (the result itself is in ``result.json``).
    """
    if not fixed or not moving:
        raise InputError("both 'fixed' and 'moving' must be given (e.g. --fixed CT.nii.gz --moving CBCT.nii.gz)")
    check_output_dir(output_dir, overwrite)
    check_distinct_inputs(fixed, moving, fixed_series_uid, moving_series_uid)
    fixed_img = load_volume(fixed, series_uid=fixed_series_uid)
    moving_img = load_volume(moving, series_uid=moving_series_uid)
    result = registrar(fixed_img, moving_img, refine=refine, cascade_steps=cascade_steps)
    paths = write_outputs(result, fixed_img, moving_img, output_dir, overwrite=overwrite, qc=qc)
    logger.info("registered %s to %s: %s (confidence %.2f)", moving, fixed,
                ", ".join(f"{n}={v:.2f}" for n, v in zip(PARAM_NAMES, result.params)), result.confidence)
    return paths

