"""Reading, writing and resampling volumes with SimpleITK, output-folder checks, and conversion to MONAI ``MetaTensor``.

Everything here raises :class:`~monai_rigidreg.core.errors.InputError` (naming the file) for bad input, instead of
letting a bare SimpleITK/GDCM traceback through, and refuses to overwrite outputs unless ``overwrite=True``.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.core.errors import InputError, OutputExistsError, read_error_reason
from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.io.dicom_series import read_dicom_series
from monai_rigidreg.io.prefetch import InLine, file_suffix, start_nifti_checks, take_prefetched

__all__ = [
    "VOLUME_SUFFIXES",
    "load_volume",
    "save_volume",
    "check_volume",
    "resample",
    "sitk_to_metatensor",
    "metatensor_to_sitk",
    "check_output_path",
    "check_output_dir",
    "make_dirs",
    "remove_made_dirs",
    "grids_overlap",
    "grid_within",
    "as_image",
]

logger = logging.getLogger(__name__)

VOLUME_SUFFIXES = (".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".nhdr", ".dcm")

_INTERPOLATORS = {
    "linear": sitk.sitkLinear,
    "nearest": sitk.sitkNearestNeighbor,
    "bspline": sitk.sitkBSpline,
    "bspline3": sitk.sitkBSpline3,
    "lanczos": sitk.sitkLanczosWindowedSinc,
}


def check_output_path(path: str | Path, overwrite: bool = False) -> Path:
    """Return ``path`` as a ``Path`` after checking it may be written (parent created, no clobbering)."""
    p = Path(path)
    if p.exists() and not overwrite:
        raise OutputExistsError(p)
    p.parent.mkdir(parents=True, exist_ok=True)
    return p


def check_output_dir(path: str | Path, overwrite: bool = False, allow_existing: bool = False) -> Path:
    """Return ``path`` as a ``Path`` after checking that a command may write its output folder there.

    The one check of every command that writes a folder (register, simulate, evaluate, demo, train): a path that
    is a file, or whose parent is a file, is refused whatever ``overwrite`` says (it would take a file away, or
    cannot be made); an existing non-empty folder is refused unless ``overwrite`` or ``allow_existing`` (a caller
    that resumes or adds to a folder checks its content itself). Nothing is created or removed here.

    Raises:
        OutputExistsError: ``path`` is a file, or a non-empty folder and neither flag is set.
        InputError: a parent of ``path`` is a file, the name is too long for the file system, the folder above it
            that exists is not writable, or ``path`` is an existing folder that is not writable.
    """
    p = Path(path)
    for parent in p.parents:
        if parent.exists() and not parent.is_dir():
            raise InputError("cannot create the output folder: this parent of it is a file", parent)
    if any(len(part.encode()) > 255 for part in p.parts):
        raise InputError("an output folder name is longer than 255 bytes", p)
    if p.exists() and not p.is_dir():
        raise OutputExistsError(p, "it is a file, not a folder; choose another --output-dir")
    if p.resolve() in (Path.cwd().resolve(), Path(p.resolve().anchor)):
        raise InputError("the output folder is the current folder (or the file-system root): name a sub-folder, "
                         "e.g. --output-dir reg_out", p)
    if p.is_dir() and any(p.iterdir()) and not (overwrite or allow_existing):
        raise OutputExistsError(p)
    # the folder is written aside, next to it, and renamed into place (monai_rigidreg.io.staging): its parent (or the
    # nearest folder above that exists) must take new entries, and an existing folder must be writable, found here
    # rather than after the work (access(2) also sees read-only mounts and immutable folders, even for root)
    target = p.resolve() if p.is_symlink() else p  # staging replaces a linked folder where it lies
    above = next((d for d in target.absolute().parents if d.exists()), None)
    if above is not None and not os.access(above, os.W_OK | os.X_OK):
        raise InputError(f"cannot create the output folder: {above} is not writable", p)
    if target.is_dir() and not os.access(target, os.W_OK | os.X_OK):
        raise InputError("the output folder is not writable", p)
    return p


def make_dirs(folder: str | Path) -> list[Path]:
    """Create ``folder`` and its missing parents; return the folders created, deepest first (for
    :func:`remove_made_dirs` after a failure, so that a failed command leaves no empty folders behind)."""
    folder = Path(folder)
    missing = []
    for d in (folder, *folder.parents):
        if d.exists():
            break
        missing.append(d)
    folder.mkdir(parents=True, exist_ok=True)
    return missing


def remove_made_dirs(made: list[Path]) -> None:
    """Remove the folders :func:`make_dirs` created, deepest first, where they are still empty."""
    for d in made:
        try:
            d.rmdir()
        except OSError:  # something else has written into it meanwhile: it stays
            pass


# ---------------------------------------------------------------------------------------------------------------
# Volumes
# ---------------------------------------------------------------------------------------------------------------
def check_volume(image: sitk.Image, path: str | Path | None = None, check_finite: bool = True) -> sitk.Image:
    """Check that ``image`` is a scalar 3D volume with finite voxels; returns it.

    Raises:
        InputError: for 2D/4D images, vector pixels, a dimension of size 1 (a single slice) or NaN/inf voxels.
    """
    dim = image.GetDimension()
    if dim != 3:
        raise InputError(f"expected a 3D volume, got a {dim}D image of size {image.GetSize()}", path)
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(
            f"expected a scalar volume, got {image.GetNumberOfComponentsPerPixel()} components per voxel "
            "(a 4D or multi-channel image?)",
            path,
        )
    if min(image.GetSize()) < 2:
        raise InputError(f"expected a 3D volume, got size {image.GetSize()} (a single slice?)", path)
    if check_finite and image.GetPixelID() in (sitk.sitkFloat32, sitk.sitkFloat64):
        arr = sitk.GetArrayViewFromImage(image)
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        if bad:
            raise InputError(f"volume has {bad} NaN or infinite voxel(s)", path)
    return image


def load_volume(
    path: str | Path,
    series_uid: str | None = None,
    pixel_type: int | None = sitk.sitkFloat32,
    check_finite: bool = True,
    warnings: list[str] | None = None,
) -> sitk.Image:
    """Read a 3D volume: NIfTI (``.nii``, ``.nii.gz``), MetaImage, NRRD, or a DICOM series directory.

    Args:
        path: file, or directory holding a DICOM series.
        series_uid: for a DICOM directory with several series, the one to read (default: the largest).
        pixel_type: SimpleITK pixel type to cast to (default float32); ``None`` keeps the stored type.
        check_finite: raise for NaN/inf voxels.
        warnings: a list the warnings of the read are appended to (they are logged too), e.g. a DICOM series
            resampled across a slice gap.

    Returns:
        the volume as a ``SimpleITK.Image`` (LPS geometry as SimpleITK reads it). A DICOM series whose slice gaps
        are uneven (a missing or unreadable slice, mixed spacing) is resampled onto a regular grid at its smallest
        gap, every slice at its true position, with a logged warning.

    Raises:
        InputError: missing, unreadable or corrupt file, no DICOM series, not a scalar 3D volume, NaN voxels, a
            DICOM series with two slices at one position or with sideways-drifting slice origins (gantry tilt).
    """
    p = Path(path)
    if not p.exists():
        raise InputError("no such file or directory", p)
    nifti_check = complete_check = None
    folder = p.is_dir()
    prefetched = None if folder else take_prefetched(p)  # a read the command started while it imported
    if folder:
        image = read_dicom_series(p, series_uid, warnings)
    elif prefetched is not None and prefetched[0].exception() is None:
        image, nifti_check, complete_check = prefetched
        image = image.result()
        nifti_check = nifti_check if check_finite else None
    else:
        # the second reads (nibabel's NaN check, the NIfTI completeness check) run while SimpleITK reads: all
        # decompress without holding the GIL (benchmarks/speed/bench_inference_speed.py; with the NaN check alone: a
        # 256^3 float32 CT in 0.20 s instead of 0.31 s on 2 cores)
        pool = ThreadPoolExecutor(max_workers=2)
        try:
            nifti_check, complete_check = start_nifti_checks(pool, p, check_finite)
        except RuntimeError:  # no thread to be had (a process limit): the checks run here, before the read
            nifti_check, complete_check = start_nifti_checks(InLine(), p, check_finite)
        pool.shutdown(wait=False)
        try:
            image = sitk.ReadImage(str(p))
        except RuntimeError as exc:
            raise InputError(f"unreadable or corrupt image file ({read_error_reason(exc, p)})", p) from exc
        finally:
            for check in (nifti_check, complete_check):
                if check is not None:
                    check.exception()  # wait for it either way: no stray reader left behind
    if complete_check is not None:
        complete_check.result()  # a truncated or corrupt NIfTI file, which ITK reads without an error
    check_volume(image, p, check_finite=False)
    if nifti_check is not None:
        nifti_check.result()  # raises the NaN error found by the second read
    if pixel_type is not None and image.GetPixelID() != pixel_type:
        image = sitk.Cast(image, pixel_type)
    if check_finite:
        check_volume(image, p, check_finite=True)
    return image


def save_volume(image: sitk.Image, path: str | Path, overwrite: bool = False, compress: bool = True) -> Path:
    """Write a volume (format from the suffix, e.g. ``.nii.gz``, ``.mha``, ``.nrrd``); refuses to overwrite."""
    p = check_output_path(path, overwrite)
    if file_suffix(p) not in VOLUME_SUFFIXES:
        raise InputError(f"unsupported volume suffix {file_suffix(p)!r}; use one of {VOLUME_SUFFIXES}", p)
    sitk.WriteImage(image, str(p), compress)
    return p


def resample(
    moving: sitk.Image,
    reference: sitk.Image | Grid,
    transform: sitk.Transform | None = None,
    interpolator: str = "linear",
    default_value: float | None = None,
    pixel_type: int | None = None,
) -> sitk.Image:
    """Resample ``moving`` onto the grid of ``reference`` under a fixed->moving ``transform`` (ITK convention).

    Args:
        moving: the image to resample.
        reference: image (or :class:`~monai_rigidreg.core.geometry.Grid`) whose grid the output takes.
        transform: maps reference points to moving points; identity if ``None``.
        interpolator: ``"linear"``, ``"nearest"``, ``"bspline"``, ``"bspline3"`` or ``"lanczos"``.
        default_value: value outside the moving image (default: the moving image's minimum, e.g. air for CT).
        pixel_type: output pixel type (default: the moving image's).
    """
    if interpolator not in _INTERPOLATORS:
        raise ValueError(f"interpolator must be one of {sorted(_INTERPOLATORS)}, got {interpolator!r}")
    ref = reference.to_sitk() if isinstance(reference, Grid) else reference
    if default_value is None:
        stats = sitk.MinimumMaximumImageFilter()
        stats.Execute(moving)
        default_value = stats.GetMinimum()
    tfm = sitk.Transform(3, sitk.sitkIdentity) if transform is None else transform
    return sitk.Resample(
        moving,
        ref,
        tfm,
        _INTERPOLATORS[interpolator],
        float(default_value),
        moving.GetPixelID() if pixel_type is None else pixel_type,
    )


# ---------------------------------------------------------------------------------------------------------------
# SimpleITK <-> MONAI MetaTensor
# ---------------------------------------------------------------------------------------------------------------
def sitk_to_metatensor(image: sitk.Image, dtype: torch.dtype = torch.float32, meta: dict[str, Any] | None = None):
    """Channel-first MONAI ``MetaTensor`` ``[1, x, y, z]`` of a 3D image, with its RAS affine (MONAI's default).

    The meta dict carries ``space="RAS"``, ``spatial_shape`` and ``original_affine`` as MONAI's ``LoadImage``
    would, so MONAI transforms and :meth:`Grid.from_metatensor` see the right geometry.
    """
    check_volume(image, check_finite=False)
    arr = sitk.GetArrayFromImage(image)  # [z, y, x]
    data = torch.from_numpy(np.ascontiguousarray(arr.transpose(2, 1, 0))).to(dtype)[None]
    grid = Grid.from_sitk(image)
    affine = torch.as_tensor(grid.affine("RAS"), dtype=torch.float64)
    m: dict[str, Any] = {
        "space": "RAS",
        "spatial_shape": np.asarray(grid.size),
        "original_affine": affine.clone(),
        "original_channel_dim": "no_channel",
    }
    if meta:
        m.update(meta)
    from monai.data import MetaTensor  # here: reading and writing files must not import MONAI (grid_sampling)

    return MetaTensor(data, affine=affine, meta=m)


def metatensor_to_sitk(tensor: Any, pixel_type: int | None = None) -> sitk.Image:
    """``SimpleITK.Image`` of a single-channel MONAI ``MetaTensor`` ``[1, x, y, z]`` (or ``[x, y, z]``)."""
    t = tensor
    if t.ndim == 4:
        if t.shape[0] != 1:
            raise ValueError(f"expected one channel, got shape {tuple(t.shape)}")
        spatial = t[0]
    elif t.ndim == 3:
        spatial = t
    else:
        raise ValueError(f"expected [1, x, y, z] or [x, y, z], got shape {tuple(t.shape)}")
    grid = Grid.from_metatensor(t)
    arr = torch.as_tensor(spatial).detach().cpu().numpy()
    image = sitk.GetImageFromArray(np.ascontiguousarray(arr.transpose(2, 1, 0)))
    grid.apply_to(image)
    if pixel_type is not None:
        image = sitk.Cast(image, pixel_type)
    return image


def grids_overlap(a: Grid, b: Grid, min_fraction: float = 0.05) -> bool:
    """Whether the physical bounding boxes of two grids overlap by at least ``min_fraction`` of the smaller."""
    amin, amax = a.physical_extent()
    bmin, bmax = b.physical_extent()
    inter = np.clip(np.minimum(amax, bmax) - np.maximum(amin, bmin), 0, None)
    vol = lambda lo, hi: float(np.prod(np.maximum(hi - lo, 1e-6)))  # noqa: E731
    return float(np.prod(inter)) >= min_fraction * min(vol(amin, amax), vol(bmin, bmax))


def grid_within(a: Grid, b: Grid, max_share: float = 0.5) -> bool:
    """Whether the physical bounding box of ``a`` lies inside that of ``b`` and covers at most ``max_share`` of its
    volume: a planning CT (``a``, the fixed image) that does so is more likely a CBCT given in its place."""
    amin, amax = a.physical_extent()
    bmin, bmax = b.physical_extent()
    inside = bool(np.all(amin >= bmin) and np.all(amax <= bmax))
    return inside and float(np.prod(amax - amin)) <= max_share * float(np.prod(bmax - bmin))


def as_image(image_or_path: sitk.Image | str | Path, name: str = "image") -> sitk.Image:
    """A checked float32 3D ``SimpleITK.Image`` from an image or a path (see :func:`load_volume`)."""
    if isinstance(image_or_path, sitk.Image):
        check_volume(image_or_path, name)
        return sitk.Cast(image_or_path, sitk.sitkFloat32)
    if isinstance(image_or_path, (str, Path)):
        return load_volume(image_or_path)
    raise TypeError(f"{name}: expected a path or a SimpleITK.Image, got {type(image_or_path).__name__}")

