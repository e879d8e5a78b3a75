"""DICOM series on disk: which series a folder holds, which one is read, reading it at its true slice positions,
and the value formats of DICOM headers (Decimal Strings, UIDs).

:func:`read_dicom_series` is what :func:`monai_rigidreg.io.load_volume` uses for a folder;
:func:`check_distinct_inputs` refuses to register a series to itself, :func:`same_patient_ids` says whether two
headers name one patient; :mod:`monai_rigidreg.export.dicom_reg` writes the
Spatial Registration object with :func:`format_ds` and :func:`is_valid_uid`.
"""

from __future__ import annotations

import contextlib
import logging
import math
import re
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.errors import InputError, first_line

__all__ = [
    "list_dicom_series",
    "select_dicom_series",
    "describe_dicom_series",
    "header_tags",
    "check_distinct_inputs",
    "same_patient_ids",
    "read_dicom_series",
    "SLICE_GAP_TOLERANCE",
    "format_ds",
    "is_valid_uid",
]

logger = logging.getLogger(__name__)

_DS_MAX_CHARS = 16

_UID_PATTERN = re.compile(r"(0|[1-9][0-9]*)(\.(0|[1-9][0-9]*))*")  # PS3.5 section 9.1, at most 64 characters


_ITK_QUIET_LOCK = threading.Lock()
_itk_quiet: list[Any] = [0, True]  # [how many blocks are in itk_warnings_off, the display setting before the first]


@contextlib.contextmanager
def itk_warnings_off() -> Iterator[None]:
    """ITK's warnings (printed to stderr, e.g. GDCM's "No Series were found" for a folder without DICOM files) off
    for the block: this module says what went wrong, in words. Safe from several threads (both inputs are read at
    once): the display setting is restored when the last block ends."""
    with _ITK_QUIET_LOCK:
        if _itk_quiet[0] == 0:
            _itk_quiet[1] = sitk.ProcessObject.GetGlobalWarningDisplay()
            sitk.ProcessObject.SetGlobalWarningDisplay(False)
        _itk_quiet[0] += 1
    try:
        yield
    finally:
        with _ITK_QUIET_LOCK:
            _itk_quiet[0] -= 1
            if _itk_quiet[0] == 0:
                sitk.ProcessObject.SetGlobalWarningDisplay(_itk_quiet[1])


def list_dicom_series(directory: str | Path) -> dict[str, list[str]]:
    """Image series in a DICOM directory: ``{series_uid: [file names sorted by slice position]}``.

    The file lists come from GDCM's ``IPPSorter`` (sorting by image position along the slice normal), not
    from the file names.
    """
    d = Path(directory)
    reader = sitk.ImageSeriesReader()
    with itk_warnings_off():  # a folder without DICOM files: GDCM's warning; select_dicom_series says it in words
        try:
            uids = reader.GetGDCMSeriesIDs(str(d))
        except RuntimeError as exc:  # pragma: no cover - GDCM rarely raises here
            raise InputError(f"could not scan the directory for DICOM series ({exc})", d) from exc
        return {uid: list(reader.GetGDCMSeriesFileNames(str(d), uid)) for uid in uids}


def select_dicom_series(directory: str | Path, series_uid: str | None = None,
                        series: dict[str, list[str]] | None = None) -> str:
    """The UID of the series :func:`load_volume` reads from a DICOM directory: ``series_uid`` if given (and
    present), else the series with the most files.

    Raises:
        InputError: no image series in the directory, or no series with ``series_uid``.
    """
    d = Path(directory)
    series = list_dicom_series(d) if series is None else series
    if not series:
        raise InputError("directory holds no DICOM image series (give a DICOM series folder, or an image file: "
                         "NIfTI, MHA, NRRD)", d)
    if series_uid is None:
        return max(series, key=lambda uid: len(series[uid]))
    if series_uid not in series:
        raise InputError(f"no DICOM series with UID {series_uid!r}; found {sorted(series)}", d)
    return series_uid


def describe_dicom_series(directory: str | Path) -> list[dict[str, Any]]:
    """One line of facts per image series of a DICOM directory, largest first: ``uid``, ``modality``,
    ``description`` (Series Description), ``slices`` (number of files), read from each series' first file header."""
    rows = [{"uid": uid, **header_tags(files[0], {"modality": "0008|0060", "description": "0008|103e"}),
             "slices": len(files)} for uid, files in list_dicom_series(directory).items()]
    return sorted(rows, key=lambda r: -r["slices"])


def header_tags(path: str | Path, tags: dict[str, str]) -> dict[str, str]:
    """``{name: value}`` of the DICOM header ``tags`` (``{name: "gggg|eeee"}``) of one file, read without its pixels;
    ``""`` where a tag is absent or the header cannot be read (the series' UID and file count still identify it)."""
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    try:
        reader.ReadImageInformation()
    except RuntimeError:
        return dict.fromkeys(tags, "")
    return {name: reader.GetMetaData(tag).strip() if reader.HasMetaDataKey(tag) else "" for name, tag in tags.items()}


def check_distinct_inputs(fixed: str | Path, moving: str | Path, fixed_series_uid: str | None = None,
                          moving_series_uid: str | None = None) -> None:
    """Refuse to register an image to itself: the same file, or the same DICOM series (a folder holding both the
    CT and the CBCT, where both sides would otherwise pick the largest series).

    Raises:
        InputError: listing the folder's series (UID, modality, slices, description) and how to choose.
    """
    f, m = Path(fixed), Path(moving)
    if not (f.exists() and m.exists()):
        return  # the reader names the missing path
    if f.is_file() and m.is_file():
        if f.samefile(m):
            raise InputError("--fixed and --moving are the same file: give the planning CT and the CBCT", f)
        return
    if not (f.is_dir() and m.is_dir()):
        return
    uid_f, uid_m = select_dicom_series(f, fixed_series_uid), select_dicom_series(m, moving_series_uid)
    if uid_f != uid_m:
        return
    listing = "; ".join(f"{r['uid']} ({r['modality'] or '?'}, {r['slices']} slices, "
                        f"{r['description'] or 'no description'})" for r in describe_dicom_series(f))
    raise InputError(f"the CT (fixed) and the CBCT (moving) resolve to the same DICOM series {uid_f}: the image "
                     f"would be registered to itself. Series in {f}: {listing}. Choose them with "
                     "--fixed-series-uid and --moving-series-uid (fixed_series_uid= / moving_series_uid= in "
                     "Python)", m)


def same_patient_ids(id_a: str, id_b: str, issuer_a: str = "", issuer_b: str = "") -> bool:
    """Whether two DICOM headers name one patient: the same Patient ID (0010,0020), present in both, and the same
    Issuer of Patient ID (0010,0021) where both name one (surrounding spaces ignored). The rule of the DICOM node's
    CT choice (:func:`~monai_rigidreg.serve.rules.same_patient`) and of the ``register`` inputs
    (:func:`~monai_rigidreg.registration.inputs.check_same_patient`).

    >>> same_patient_ids("P1", " P1", "HOSP-A", ""), same_patient_ids("P1", "P1", "HOSP-A", "HOSP-B")
    (True, False)
    """
    a, b = id_a.strip(), id_b.strip()
    if not a or a != b:
        return False
    return not (issuer_a.strip() and issuer_b.strip() and issuer_a.strip() != issuer_b.strip())


def read_dicom_series(directory: Path, series_uid: str | None, warnings: list[str] | None = None) -> sitk.Image:
    """The series ``series_uid`` (default: the largest) of ``directory`` with every slice at its true position
    (:func:`_on_true_slice_positions`); the warnings it logs are appended to ``warnings`` too (for an audit trail
    that does not depend on the log level)."""
    series = list_dicom_series(directory)
    chosen = select_dicom_series(directory, series_uid, series)
    if series_uid is None and len(series) > 1:
        logger.info("%s: %d DICOM series, using the largest (%s)", directory, len(series), chosen)
    series_uid, files = chosen, series[chosen]
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    reader.MetaDataDictionaryArrayUpdateOn()
    try:
        with itk_warnings_off():  # ITK's "non uniform sampling" note: handled below, in words
            image = reader.Execute()
    except RuntimeError as exc:
        raise InputError(f"could not read DICOM series {series_uid} ({first_line(exc)})", directory) from exc
    return _on_true_slice_positions(image, reader, files, directory, series_uid,
                                    [] if warnings is None else warnings)


SLICE_GAP_TOLERANCE = 0.01
"""Slice gaps (along the slice normal) that differ by more than this fraction of the median gap are uneven."""


def _slice_origins(reader: sitk.ImageSeriesReader, n: int) -> np.ndarray | None:
    """Image Position (Patient) of each of the ``n`` slices read, ``[n, 3]`` (LPS mm), or ``None`` if one lacks it."""
    out = []
    for i in range(n):
        try:
            ipp = [float(v) for v in reader.GetMetaData(i, "0020|0032").split("\\")]
        except (RuntimeError, ValueError):
            return None
        if len(ipp) != 3:
            return None
        out.append(ipp)
    return np.asarray(out, dtype=np.float64)


def _warn(warnings: list[str], text: str) -> None:
    logger.warning("%s", text)
    warnings.append(text)


def _on_true_slice_positions(image: sitk.Image, reader: sitk.ImageSeriesReader, files: list[str], directory: Path,
                             series_uid: str, warnings: list[str]) -> sitk.Image:
    """``image`` (a series read by ITK, which spaces the slices evenly at their mean gap) with every slice at its
    true position.

    The slice positions along the normal come from each file's Image Position (Patient). Even gaps: the image as
    read. Uneven gaps (a missing or unreadable slice, mixed slice thicknesses): resampled onto a regular grid at the
    smallest gap, each voxel interpolated linearly between the two slices around it, with a warning that names the
    gaps. Refused: slices at the same position, origins that drift sideways (gantry tilt), or gaps so uneven that
    the regular grid would need more than four times the slices.
    """
    n = len(files)
    if n < 3 or image.GetSize()[2] != n or image.GetNumberOfComponentsPerPixel() != 1:
        return image
    ipp = _slice_origins(reader, n)
    if ipp is None:
        _warn(warnings, f"{directory}: DICOM series {series_uid}: a slice has no Image Position (Patient); the slices "
                        f"are taken as evenly spaced ({image.GetSpacing()[2]:.4g} mm)")
        return image
    normal = np.asarray(image.GetDirection(), dtype=np.float64).reshape(3, 3)[:, 2]
    rel = ipp - ipp[0]
    pos = rel @ normal
    spacing = image.GetSpacing()
    drift = float(np.linalg.norm(rel - np.outer(pos, normal), axis=1).max())
    if drift > max(1e-3, 0.1 * min(spacing[:2])):
        raise InputError(f"DICOM series {series_uid}: the slice origins drift sideways by up to {drift:.2f} mm "
                         "across the series (a tilted gantry or a sheared volume), which this reader cannot place "
                         "correctly; resample the series onto a regular grid first (e.g. 3D Slicer's acquisition "
                         "geometry regularization)", directory)
    order = np.argsort(pos, kind="stable")
    tol = max(1e-3, SLICE_GAP_TOLERANCE * float(np.median(np.diff(pos[order]))))
    same = np.flatnonzero(np.diff(pos[order]) <= tol)
    if same.size:  # GDCM cannot sort such a series by position either
        a, b = order[same[0]], order[same[0] + 1]
        raise InputError(f"DICOM series {series_uid}: two slices lie at the same position ({pos[a]:.3f} mm along the "
                         f"slice normal): {Path(files[a]).name} and {Path(files[b]).name} ({same.size} such pair(s)): "
                         "duplicated files, or two acquisitions in one series; remove the extra files or choose "
                         "another series", directory)
    gaps = np.diff(pos)
    if np.any(gaps <= 0):  # pragma: no cover - GDCM sorts distinct positions along the normal ITK uses
        raise InputError(f"DICOM series {series_uid}: the slices are not ordered by position along the slice normal",
                         directory)
    if gaps.max() - gaps.min() <= tol:
        return image
    step = float(gaps.min())
    m = int(round(pos[-1] / step)) + 1
    uneven = [k for k in range(n - 1) if gaps[k] - step > tol]
    multiple = np.abs(gaps / step - np.round(gaps / step)) < 0.05  # a whole number of regular gaps
    listed = "; ".join(f"{gaps[k]:.4g} mm between slices {k} and {k + 1} (at {pos[k]:.3f} and {pos[k + 1]:.3f} mm"
                       f"{', a missing or unreadable slice?' if multiple[k] else ''})"
                       for k in uneven[:3]) + (f"; and {len(uneven) - 3} more" if len(uneven) > 3 else "")
    if m > 4 * n:
        raise InputError(f"DICOM series {series_uid}: slice gaps range from {step:.4g} to {gaps.max():.4g} mm "
                         f"({listed}); a regular grid at the smallest gap would need {m} slices for {n}: remove the "
                         "stray slice(s) or choose another series", directory)
    dz = float(pos[-1]) / (m - 1)
    arr = sitk.GetArrayViewFromImage(image)  # [z, y, x], slices in position order
    at = np.arange(m) * dz
    k = np.clip(np.searchsorted(pos, at, side="right") - 1, 0, n - 2)
    w = np.clip((at - pos[k]) / gaps[k], 0.0, 1.0).astype(np.float32)
    out = np.empty((m, *arr.shape[1:]), dtype=np.float32)
    for j in range(m):
        out[j] = (1.0 - w[j]) * arr[k[j]] + w[j] * arr[k[j] + 1]
    regular = sitk.GetImageFromArray(out)
    regular.SetOrigin(image.GetOrigin())
    regular.SetDirection(image.GetDirection())
    regular.SetSpacing((spacing[0], spacing[1], dz))
    _warn(warnings, f"{directory}: DICOM series {series_uid}: the slices are unevenly spaced ({listed}); resampled "
                    f"from {n} slices onto a regular grid of {m} slices at {dz:.4g} mm, each interpolated linearly "
                    "between the slices around it")
    return regular


def format_ds(value: float) -> str:
    """A number as a DICOM Decimal String of at most 16 characters, with as many significant digits as fit.

    ``-0.12345678901234567`` becomes ``"-0.1234567890123"``, ``1e-20`` stays ``"1e-20"``; negative zero is
    written ``"0"``. Every finite float fits: 16 characters keep at least 9 significant digits (relative error
    below 5e-9), and for numbers below 1e5 in magnitude, such as the entries of a registration matrix (rotation
    entries and translations in mm), the absolute error is below 1e-9.

    Raises:
        ValueError: ``value`` is NaN or infinite (DS has no spelling for them).
    """
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"a DICOM Decimal String cannot hold {v}")
    if v == 0.0:
        return "0"
    for digits in range(17, 0, -1):
        text = f"{v:.{digits}g}"
        if len(text) <= _DS_MAX_CHARS:
            return text
    raise AssertionError("unreachable: one significant digit always fits")  # pragma: no cover


def is_valid_uid(value: str) -> bool:
    """A DICOM UID: dot-separated numbers without leading zeros, at most 64 characters (PS3.5 section 9.1)."""
    return len(value) <= 64 and _UID_PATTERN.fullmatch(value) is not None
