"""The registration as the service runs it: the one module of :mod:`monai_rigidreg.serve` that imports the package's
registration stack (torch, the network, the output writers), and only when the service loads its model.

:func:`load_registrar` loads the shipped bundle's network once; :func:`register_series` registers one CBCT series
folder to one planning-CT series folder into a new result folder (the package's ``register_files``: ``result.json``
with the couch shifts, the QC figure, the transform files) and writes the DICOM Spatial Registration
(``registration.dcm``) with its Content Label ``RIGIDREG`` or, for a flagged result, ``RIGIDREG_FLAGGED``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from monai_rigidreg.serve.config import ServeConfig, Thresholds

__all__ = ["load_registrar", "register_series", "flag_reasons", "REG_LABEL", "REG_LABEL_FLAGGED", "warm_up"]

logger = logging.getLogger("monai_rigidreg.serve")

REG_LABEL = "RIGIDREG"
REG_LABEL_FLAGGED = "RIGIDREG_FLAGGED"
"""Content Label (0070,0080) of a REG whose result is flagged (a CS value: upper case, at most 16 characters)."""
REG_DESCRIPTION = "Rigid CBCT to planning CT registration"


def load_registrar(cfg: ServeConfig) -> Any:
    """The shipped (or ``registration.bundle``) network in a registrar, on ``registration.device``, with
    ``registration.threads`` CPU threads (default: adapted per registration to the cores other work leaves)."""
    import monai_rigidreg
    from monai_rigidreg.core.device import set_cpu_threads

    set_cpu_threads(cfg.threads)
    registrar = monai_rigidreg.RigidRegistrar.from_bundle(cfg.bundle, device=cfg.device)
    registrar.adapt_threads = cfg.threads is None
    return registrar


def warm_up(registrar: Any) -> float:
    """Run one registration on a small generated pair, so that the first patient's does not pay the one-off costs
    (kernel selection, lazily loaded code); returns its seconds."""
    import SimpleITK as sitk

    import monai_rigidreg

    t0 = time.perf_counter()
    z, y, x = np.mgrid[-32:32, -32:32, -32:32].astype(np.float32) * 2.0
    body = (x / 50) ** 2 + (y / 40) ** 2 + (z / 55) ** 2 < 1
    bone = ((x - 15) / 12) ** 2 + ((y + 5) / 9) ** 2 + (z / 30) ** 2 < 1
    ct = np.where(body, 40.0, -1000.0) + np.where(bone, 900.0, 0.0)
    fixed = sitk.GetImageFromArray(ct.astype(np.float32))
    fixed.SetSpacing((2.0, 2.0, 2.0))
    fixed.SetOrigin((-64.0, -64.0, -64.0))
    moving = sitk.Resample(fixed, fixed, sitk.TranslationTransform(3, (-3.0, 2.0, 1.0)), sitk.sitkLinear, -1000.0)
    with tempfile.TemporaryDirectory(prefix="rigidreg-warm-") as tmp:
        result = monai_rigidreg.register(fixed, moving, model=registrar)
        monai_rigidreg.write_outputs(result, fixed, moving, Path(tmp) / "out")
    return time.perf_counter() - t0


def flag_reasons(summary: dict[str, Any], limits: Thresholds) -> list[str]:
    """Why a result (``result.json``) is flagged for review: the package's own flag, a confidence below
    ``limits.confidence``, a correction larger than ``limits.translation_mm`` / ``limits.rotation_deg``."""
    reasons = []
    confidence = summary.get("confidence")
    if summary.get("flagged"):
        reasons.append(f"the registration's own check flagged it (confidence "
                       f"{'not measured' if confidence is None else f'{confidence:.2f}'})")
    elif limits.confidence is not None and (confidence is None or confidence < limits.confidence):
        reasons.append("confidence not measured" if confidence is None
                       else f"confidence {confidence:.2f} below {limits.confidence:g}")
    couch = summary.get("couch_shift", {}).get("3dof")
    if couch:
        shift = math.sqrt(sum(float(couch[k]) ** 2 for k in ("lateral", "longitudinal", "vertical")))
    else:
        shift = float(np.linalg.norm([summary["params"][k] for k in ("tx", "ty", "tz")]))
    if limits.translation_mm is not None and shift > limits.translation_mm:
        reasons.append(f"translation {shift:.1f} mm above {limits.translation_mm:g} mm")
    angle = max(abs(float(summary["params"][k])) for k in ("rx", "ry", "rz"))
    if limits.rotation_deg is not None and angle > limits.rotation_deg:
        reasons.append(f"rotation {angle:.1f} degrees above {limits.rotation_deg:g} degrees")
    return reasons


def series_reference(files: list[tuple[str, str, Path]], folder: Path) -> Any:
    """The REG's reference to one received series: the patient, study and frame facts read from its first file by
    the package (``dicom_reg.series_reference``), every instance from the service's index (``files``: SOP Class UID,
    SOP Instance UID, file; reading every header again cost 0.4 s per registration)."""
    import dataclasses

    from monai_rigidreg.export.dicom_reg import InstanceReference
    from monai_rigidreg.export.dicom_reg import series_reference as read_reference

    first = read_reference(files[0][2])
    instances = tuple(InstanceReference(sop_class or first.instances[0].sop_class_uid, sop_uid)
                      for sop_class, sop_uid, _ in files)
    return dataclasses.replace(first, instances=instances, source=folder)


def register_series(registrar: Any, ct: tuple[Path, list], cbct: tuple[Path, list], output_dir: Path,
                    cfg: ServeConfig, context: dict[str, Any]) -> dict[str, Any]:
    """Register the CBCT series to the planning CT series into ``output_dir`` (which must not exist) and write
    ``registration.dcm`` and ``service.json`` (the service's record: series, CT choice, flags, REG) into it.

    Args:
        ct, cbct: each ``(series folder, [(SOP Class UID, SOP Instance UID, file), ...])`` from the index.

    Returns:
        ``{"summary": result.json, "flags": [...], "reg_path", "reg_sop_uid", "seconds", "label"}``.

    Raises:
        InputError: the series cannot be read, registered or given a REG (the package's message).
    """
    from monai_rigidreg import __version__, register_files
    from monai_rigidreg.core.errors import InputError
    from monai_rigidreg.export.dicom_reg import write_spatial_registration

    t0 = time.perf_counter()
    refs = (series_reference(ct[1], ct[0]), series_reference(cbct[1], cbct[0]))
    if refs[0].frame_of_reference_uid == refs[1].frame_of_reference_uid:  # refused before registering
        raise InputError("the CT and the CBCT share one Frame of Reference UID: no registration between two frames "
                         "can be stored")
    paths = register_files(registrar, ct[0], cbct[0], output_dir, qc=cfg.qc, reg="off")
    summary = json.loads(paths["result.json"].read_text())
    flags = flag_reasons(summary, cfg.thresholds)
    if flags:
        label = REG_LABEL_FLAGGED
        description = ("FLAGGED, review before use: " + "; ".join(flags))[:64]
    else:
        label, description = REG_LABEL, REG_DESCRIPTION
    reg_path = write_spatial_registration(output_dir / "registration.dcm", refs[0], refs[1],
                                          np.asarray(summary["matrix_moving_to_fixed"]), content_label=label,
                                          description=description, software_version=__version__, series_number=900)
    import pydicom

    reg_sop_uid = str(pydicom.dcmread(reg_path, stop_before_pixels=True, specific_tags=["SOPInstanceUID"])
                      .SOPInstanceUID)
    seconds = time.perf_counter() - t0
    record = {**context, "flagged": bool(flags), "flag_reasons": flags, "content_label": label,
              "reg_sop_instance_uid": reg_sop_uid, "seconds": round(seconds, 3),
              "confidence": summary.get("confidence"), "params": summary.get("params"),
              "couch_shift": summary.get("couch_shift")}
    part = output_dir / ".service.json.partial"
    part.write_text(json.dumps(record, indent=2))
    os.replace(part, output_dir / "service.json")
    return {"summary": summary, "flags": flags, "reg_path": reg_path, "reg_sop_uid": reg_sop_uid,
            "seconds": seconds, "label": label}
