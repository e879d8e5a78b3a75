"""The audit trail of a registration: what was registered, with which software and weights, where and when.

``result.json`` carries it under ``"provenance"`` so that a clinic can trace a couch correction back to the input
series, the package and bundle versions and the exact weights (SHA-256) that produced it.
"""

from __future__ import annotations

import datetime
import hashlib
import importlib.metadata
import json
import platform
import shlex
import sys
from pathlib import Path
from typing import Any

import SimpleITK as sitk

import monai_rigidreg
from monai_rigidreg.io.dicom_series import header_tags, list_dicom_series, select_dicom_series

__all__ = ["DICOM_TAGS", "IN_MEMORY", "input_record", "bundle_record", "software_versions",
           "registration_provenance", "sha256_of"]

DICOM_TAGS: dict[str, str] = {
    "study_uid": "0020|000d",
    "series_uid": "0020|000e",
    "frame_of_reference_uid": "0020|0052",
    "modality": "0008|0060",
    "series_description": "0008|103e",
    "patient_position": "0018|5100",
    "patient_id": "0010|0020",
    "issuer_of_patient_id": "0010|0021",
}
"""Header fields recorded for a DICOM input (read from the first file of the series that was registered)."""


def sha256_of(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


def input_record(path: str | Path, series_uid: str | None = None) -> dict[str, Any]:
    """``{"path": absolute path, "format": "dicom" | suffix, ...}``; for a DICOM folder also the chosen series'
    header fields of :data:`DICOM_TAGS` (empty strings where a tag is absent) and its number of files."""
    p = Path(path).resolve()
    record: dict[str, Any] = {"path": str(p)}
    if not p.is_dir():
        record["format"] = "".join(p.suffixes[-2:]) if p.name.endswith(".gz") else p.suffix
        return record
    series = list_dicom_series(p)
    uid = select_dicom_series(p, series_uid, series)
    record.update({"format": "dicom", "files": len(series[uid]), **header_tags(series[uid][0], DICOM_TAGS)})
    record["series_uid"] = record["series_uid"] or uid
    return record


def bundle_record(bundle: str | Path, weights: str | Path | None = None) -> dict[str, Any]:
    """The bundle's folder, version (``configs/metadata.json``), weights file and its SHA-256."""
    b = Path(bundle).resolve()
    w = Path(weights).resolve() if weights is not None else b / "models" / "model.pt"
    meta = b / "configs" / "metadata.json"
    version = json.loads(meta.read_text(encoding="utf-8")).get("version", "") if meta.is_file() else ""
    return {"path": str(b), "version": version, "weights": str(w),
            "weights_sha256": sha256_of(w) if w.is_file() else ""}


def software_versions() -> dict[str, str]:
    """Versions of this package and of what computes with it (read from the installed distributions)."""
    versions = {"monai_rigidreg": monai_rigidreg.__version__, "python": platform.python_version(),
                "SimpleITK": sitk.Version.VersionString()}
    for dist in ("torch", "monai", "numpy"):
        try:
            versions[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:  # pragma: no cover - a dependency is always present
            versions[dist] = ""
    return versions


IN_MEMORY = {"path": None, "format": "image in memory"}
"""The input record of an image given as a ``SimpleITK.Image`` (no file to name)."""


def registration_provenance(fixed: str | Path | None, moving: str | Path | None, fixed_series_uid: str | None = None,
                            moving_series_uid: str | None = None, bundle: dict[str, Any] | None = None,
                            device: str = "") -> dict[str, Any]:
    """The ``"provenance"`` record of ``result.json``: inputs (:func:`input_record`; ``None``: an image in memory,
    :data:`IN_MEMORY`), bundle (:func:`bundle_record`), software versions, device, UTC time stamp and the command
    line."""
    def record(path: str | Path | None, series_uid: str | None) -> dict[str, Any]:
        return dict(IN_MEMORY) if path is None else input_record(path, series_uid)

    return {
        "inputs": {"fixed": record(fixed, fixed_series_uid), "moving": record(moving, moving_series_uid)},
        "bundle": bundle or {},
        "software": software_versions(),
        "device": device,
        "timestamp_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command_line": shlex.join(sys.argv),
        "host": platform.node(),
    }
