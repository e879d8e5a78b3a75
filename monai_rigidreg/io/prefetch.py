"""A command's input volumes read while the registration stack is imported.

``monai-rigidreg register`` spends about 0.9 s importing torch (one core, most of it holding the GIL) before it can
read anything; SimpleITK's and nibabel's readers decompress without the GIL, so the two input files can be read on
the other core meanwhile. :func:`prefetch_volumes` starts those reads (this module imports neither torch nor the
package's geometry, so it runs before them); :func:`~monai_rigidreg.io.load_volume` takes a read that was started
for its path (:func:`take_prefetched`) instead of reading again, and applies every check it applies to its own
reads. A read fails the same way in both: where the prefetched one raised, ``load_volume`` reads the file again and
reports the error itself. A file changed after its read started (size, modification time, inode or status-change
time) is read again.
Measured by ``benchmarks/speed/bench_speed.py`` (the command-line rows).

Frames and values are untouched: the image is what ``SimpleITK.ReadImage`` returns.
"""

from __future__ import annotations

import struct
import threading
import zlib
from collections.abc import Callable, Iterable
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.errors import InputError

__all__ = ["InLine", "check_nifti_complete", "check_nifti_finite", "drop_prefetched", "file_suffix", "is_nifti",
           "needs_nan_check", "prefetch_volumes", "start_nifti_checks", "take_prefetched"]

_FLOAT_PIXELS = {sitk.sitkFloat32, sitk.sitkFloat64, sitk.sitkVectorFloat32, sitk.sitkVectorFloat64,
                 sitk.sitkComplexFloat32, sitk.sitkComplexFloat64}

_LOCK = threading.Lock()
_PENDING: dict[tuple[str, int, int, int, int], tuple[Future, Future | None, Future | None]] = {}
_CHUNK = 1 << 20
_GZIP_MAGIC = b"\x1f\x8b"


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


_NIFTI_BYTES = {2: 1, 4: 2, 8: 4, 16: 4, 32: 8, 64: 8, 128: 3, 256: 1, 512: 2, 768: 4, 1024: 8, 1280: 8, 1536: 16,
                1792: 16, 2048: 32, 2304: 4}
"""Bytes per voxel of each NIfTI ``datatype`` code (the readers size the data by it, not by ``bitpix``)."""


_NIFTI_LAYOUTS = (
    # sizeof_hdr, magic offset and value, datatype offset, dim format and offset, vox_offset format and offset,
    # the smallest data offset of a single file (header + extension flags)
    (348, 344, b"n+1\0", 70, "8h", 40, "f", 108, 352),  # NIfTI-1
    (540, 4, b"n+2\0", 12, "8q", 16, "q", 168, 544),  # NIfTI-2
)
"""Where the single-file NIfTI-1 and NIfTI-2 headers keep what :func:`_nifti_voxel_bytes` reads (the standards'
byte offsets, as nibabel's header classes lay them out)."""


def _nifti_voxel_bytes(header: bytes) -> tuple[int, int] | None:
    """``(offset of the voxel data, bytes of voxel data)`` a single-file NIfTI-1 or NIfTI-2 header declares (either
    byte order; the offset at least the header's size, as nifti1_io reads it); ``None`` where the header is not one
    or declares something unreadable (ITK refuses or reads it on its own terms)."""
    for order in "<>":
        for size, magic_at, magic, type_at, dim_fmt, dim_at, offset_fmt, offset_at, minimum in _NIFTI_LAYOUTS:
            if len(header) < size or struct.unpack(order + "i", header[:4])[0] != size:
                continue
            if header[magic_at: magic_at + 4] != magic:
                return None
            datatype = struct.unpack_from(order + "h", header, type_at)[0]
            dim = struct.unpack_from(order + dim_fmt, header, dim_at)
            offset = struct.unpack_from(order + offset_fmt, header, offset_at)[0]
            ndim, nbytes = dim[0], _NIFTI_BYTES.get(datatype)
            if nbytes is None or not 1 <= ndim <= 7 or any(d <= 0 for d in dim[1: ndim + 1]) or not (
                    0 <= offset < 2**62):
                return None  # also a NaN or infinite vox_offset
            count = 1
            for d in dim[1: ndim + 1]:
                count *= int(d)
            return max(int(offset), minimum), count * nbytes
    return None


def _gunzip_length(path: Path, keep: int) -> tuple[int, bytes]:
    """Decompress a gzip file (every member) without keeping it: ``(decompressed length, its first ``keep``
    bytes)``. zlib checks each member's CRC-32 and length and the deflate stream itself; data after the last member
    that is not another member (e.g. zero padding) is ignored, as gzip does.

    Raises:
        InputError: the compressed data is corrupt or ends before a member does (a truncated file).
    """
    total, head = 0, b""
    inflater = zlib.decompressobj(zlib.MAX_WBITS | 16)
    with open(path, "rb") as f:
        pending = b""
        while True:
            if not pending:
                pending = f.read(_CHUNK)
                if not pending:
                    break
            try:
                out = inflater.decompress(pending, 16 * _CHUNK)  # bounded: a very compressible volume stays small
            except zlib.error as exc:
                raise InputError(f"unreadable or corrupt image file (its compressed data: {exc})", path) from exc
            pending = inflater.unconsumed_tail
            total += len(out)
            if len(head) < keep:
                head += out[: keep - len(head)]
            if inflater.eof:  # a member ended: another one may follow
                rest = inflater.unused_data
                if len(rest) < len(_GZIP_MAGIC):
                    rest += f.read(_CHUNK)
                if not rest.startswith(_GZIP_MAGIC):
                    return total, head  # the end, or padding after the last member
                inflater = zlib.decompressobj(zlib.MAX_WBITS | 16)
                pending = rest
    if not inflater.eof:
        raise InputError("unreadable or corrupt image file (its compressed data ends early: the file is truncated)",
                         path)
    return total, head


def check_nifti_complete(path: Path) -> None:
    """ITK's NIfTI reader fills the voxels a truncated file lacks with zeros and reports nothing (SimpleITK 2.5: a
    ``.nii`` or ``.nii.gz`` cut to 75 % reads as a whole volume, and a registration on it ends with a confident,
    wrong result): check that the file holds the whole voxel block its header declares and, compressed, that the gzip
    stream is whole and its checksums hold. Reads the file once more (0.1 s for an 18 MB CT on one core; run beside
    SimpleITK's read, which decompresses without holding the GIL too).

    Raises:
        InputError: truncated or corrupt; the message says which.
    """
    with open(path, "rb") as f:
        header = f.read(544)
    if header.startswith(_GZIP_MAGIC):  # by content: ITK reads an uncompressed file named .nii.gz too
        total, header = _gunzip_length(path, 544)
    else:
        total = path.stat().st_size
    declared = _nifti_voxel_bytes(header)
    if declared is None:
        return
    offset, needed = declared
    if total < offset + needed:
        raise InputError(f"unreadable or corrupt image file (truncated: {max(total - offset, 0)} bytes of voxel data "
                         f"where its header declares {needed})", path)


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


def start_nifti_checks(pool: Executor, path: Path, nan_check: bool = True) -> tuple[Future | None, Future | None]:
    """The second reads of a NIfTI file that run beside SimpleITK's (all decompress without holding the GIL), as
    ``(NaN check, completeness check)`` futures of ``pool``: :func:`check_nifti_finite` where ``nan_check`` and
    :func:`needs_nan_check` say so, :func:`check_nifti_complete` for every NIfTI file; ``None`` for those not
    started. The one list of them, for :func:`prefetch_volumes` and :func:`~monai_rigidreg.io.load_volume`.

    Raises:
        RuntimeError: ``pool`` could not start a thread (a process limit).
    """
    nifti = pool.submit(check_nifti_finite, path) if nan_check and needs_nan_check(path) else None
    complete = pool.submit(check_nifti_complete, path) if is_nifti(path) else None
    return nifti, complete


class InLine(Executor):
    """An executor that runs each call at once in the calling thread (where no thread can be started): its futures
    are finished, an error kept for ``result()`` as a worker's would be."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as exc:  # noqa: BLE001 - kept for the caller, who raises it where a worker's would be
            future.set_exception(exc)
        return future


def prefetch_volumes(paths: Iterable[str | Path | None]) -> int:
    """Start reading each regular file of ``paths`` in a worker thread (``SimpleITK.ReadImage``, and beside it
    :func:`check_nifti_finite` where :func:`needs_nan_check` says so and :func:`check_nifti_complete` for a NIfTI
    file); folders (DICOM series), missing paths and ``None`` are skipped, as is a file whose read is already
    pending. Returns the number of reads started."""
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
            pool = ThreadPoolExecutor(max_workers=3, thread_name_prefix="monai-rigidreg-read")
            image = pool.submit(sitk.ReadImage, str(p))
            nifti, complete = start_nifti_checks(pool, p)
            pool.shutdown(wait=False)
            _PENDING[key] = (image, nifti, complete)
        started += 1
    return started


def take_prefetched(path: str | Path) -> tuple[Future, Future | None, Future | None] | None:
    """The pending read of ``path`` started by :func:`prefetch_volumes` (removed from the pending reads: a path is
    taken once), as ``(image future, NIfTI NaN check future or None, NIfTI completeness check future or None)``;
    ``None`` where none was started or the file changed since it was."""
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
