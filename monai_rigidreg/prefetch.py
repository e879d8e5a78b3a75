"""A command's input volumes read while the registration stack is imported.

``monai-rigidreg register`` spends about 0.9 s importing torch (one core, most of it holding the GIL) before it can
read anything; SimpleITK's and nibabel's readers decompress without the GIL, so the two input files can be read on
the other core meanwhile. :func:`prefetch_volumes` starts those reads (this module imports neither torch nor the
package's geometry, so it runs before them); :func:`~monai_rigidreg.io.load_volume` takes a read that was started
for its path (:func:`take_prefetched`) instead of reading again, and applies every check it applies to its own
reads. A read fails the same way in both: where the prefetched one raised, ``load_volume`` reads the file again and
reports the error itself. A file changed after its read started (size, modification time, inode or status-change
time) is read again.
Measured by ``benchmarks/bench_speed.py`` (the command-line rows).

Frames and values are untouched: the image is what ``SimpleITK.ReadImage`` returns.
"""

from __future__ import annotations

import threading
import zlib
from collections.abc import Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.errors import InputError

__all__ = ["check_nifti_finite", "drop_prefetched", "file_suffix", "is_nifti", "needs_nan_check", "prefetch_volumes",
           "take_prefetched"]

_FLOAT_PIXELS = {sitk.sitkFloat32, sitk.sitkFloat64, sitk.sitkVectorFloat32, sitk.sitkVectorFloat64,
                 sitk.sitkComplexFloat32, sitk.sitkComplexFloat64}

_LOCK = threading.Lock()
_PENDING: dict[tuple[str, int, int, int, int], tuple[Future, Future | None]] = {}


def file_suffix(path: Path) -> str:
    """The format suffix of ``path``, lower case: ``.nii.gz`` for a compressed NIfTI, else the last suffix (``.mha``,
    ``.tfm``, ...). The one place file names are read for their format (:mod:`monai_rigidreg.io` too)."""
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def is_nifti(path: Path) -> bool:
    """Whether ``path`` names a NIfTI file (``.nii`` or ``.nii.gz``, any case)."""
    return file_suffix(path) in (".nii", ".nii.gz")


def needs_nan_check(path: Path) -> bool:
    """Whether ``path`` is a NIfTI file that can hold NaN: its header (``SimpleITK.ImageFileReader``'s
    ``ReadImageInformation``, a few ms) reports floating-point voxels, as it does for stored floats and for integers
    with a scaling (``scl_slope``); a header ITK cannot read counts as floating-point. Stored integers cannot be NaN,
    and skipping them spares importing nibabel (0.11 s with pydicom) on the way to a registration."""
    if not is_nifti(path):
        return False
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    try:
        reader.ReadImageInformation()
    except RuntimeError:
        return True
    return reader.GetPixelID() in _FLOAT_PIXELS


def check_nifti_finite(path: Path) -> None:
    """ITK's NIfTI reader silently replaces NaN by 0: look at the stored floats with nibabel instead.

    nibabel (which imports pydicom, 0.11 s in all) is imported here, in a reading thread, while SimpleITK reads.

    Raises:
        InputError: the file stores NaN or infinite voxels.
    """
    import nibabel as nib

    try:
        img = nib.load(str(path))
    except Exception:  # noqa: BLE001 - SimpleITK could read it; nibabel's opinion is only a second check
        return
    if not np.issubdtype(img.get_data_dtype(), np.floating):
        return
    try:
        data = np.asanyarray(img.dataobj)
    except (EOFError, OSError, ValueError, zlib.error) as exc:  # e.g. a truncated .nii.gz that ITK read without error
        raise InputError(f"unreadable or corrupt image file (its voxel data: {type(exc).__name__}: {exc})",
                         path) from exc
    bad = int(np.count_nonzero(~np.isfinite(data)))
    if bad:
        raise InputError(f"volume has {bad} NaN or infinite voxel(s)", path)


def _key(path: Path) -> tuple[str, int, int, int, int] | None:
    """The file's resolved path, modification time (ns), size, inode and status-change time (ns: a file replaced by
    one with the same size and modification time, as ``cp -p`` or ``rsync -t`` make, has another inode or ctime);
    ``None`` for anything but a regular file."""
    try:
        if not path.is_file():
            return None
        stat = path.stat()
        return str(path.resolve()), stat.st_mtime_ns, stat.st_size, stat.st_ino, stat.st_ctime_ns
    except OSError:
        return None


def prefetch_volumes(paths: Iterable[str | Path | None]) -> int:
    """Start reading each regular file of ``paths`` in a worker thread (``SimpleITK.ReadImage``, and where
    :func:`needs_nan_check` says so :func:`check_nifti_finite` beside it); folders (DICOM series), missing paths and
    ``None`` are skipped, as is a file whose read is already pending. Returns the number of reads started."""
    started = 0
    for path in paths:
        if path is None:
            continue
        p = Path(path)
        key = _key(p)
        if key is None:
            continue
        with _LOCK:
            if key in _PENDING:
                continue
            pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="monai-rigidreg-read")
            image = pool.submit(sitk.ReadImage, str(p))
            nifti = pool.submit(check_nifti_finite, p) if needs_nan_check(p) else None
            pool.shutdown(wait=False)
            _PENDING[key] = (image, nifti)
        started += 1
    return started


def take_prefetched(path: str | Path) -> tuple[Future, Future | None] | None:
    """The pending read of ``path`` started by :func:`prefetch_volumes` (removed from the pending reads: a path is
    taken once), as ``(image future, NIfTI check future or None)``; ``None`` where none was started or the file
    changed since it was."""
    p = Path(path)
    key = _key(p)
    if key is None:
        return None
    with _LOCK:
        pending = _PENDING.pop(key, None)
        # a read of an earlier version of the file is dropped (it finishes on its own)
        for stale in [k for k in _PENDING if k[0] == key[0]]:
            _PENDING.pop(stale)
    return pending


def drop_prefetched(paths: Iterable[str | Path | None]) -> int:
    """Forget the pending reads of ``paths`` (any version of the file; a running read finishes on its own and its
    image is freed), e.g. after a command that failed before it loaded them. Returns how many were pending."""
    names = set()
    for path in paths:
        if path is None:
            continue
        try:
            names.add(str(Path(path).resolve()))
        except OSError:
            continue
    with _LOCK:
        stale = [k for k in _PENDING if k[0] in names]
        for key in stale:
            _PENDING.pop(key)
    return len(stale)
