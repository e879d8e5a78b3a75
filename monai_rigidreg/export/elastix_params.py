"""The rigid result as an elastix ``TransformParameters.txt`` (for ``transformix``), and as an ITK ``.h5`` file.

``transformix -in cbct.nii.gz -tp TransformParameters.txt -out dir`` with the file of
:func:`write_elastix_transform` gives the CBCT resampled on the CT grid, as ``registered.nii.gz`` is
(``sitk.Resample(moving, fixed, transform, sitk.sitkLinear, fill)``): elastix, like ITK, maps fixed (output grid)
points to moving points, so the transform is written unchanged. What the file holds, checked numerically against
itk-elastix 0.2x (elastix 5) by ``tests/test_elastix_params.py``:

* ``(Transform "EulerTransform")`` with ``TransformParameters rx ry rz tx ty tz`` (radians, mm): the order of
  ``SimpleITK.Euler3DTransform.GetParameters()``; ``(ComputeZYX "false")``, elastix's default, is ITK's
  ``R = Rz @ Rx @ Ry`` (``"true"`` would be ``Rz @ Ry @ Rx``); ``CenterOfRotationPoint`` is the centre.
* The output grid is the fixed image's: ``Size``, ``Index``, ``Spacing``, ``Origin`` and ``Direction``, the
  direction cosines **column by column** (the direction of index axis 0, then 1, then 2: the transpose of
  SimpleITK's row-major ``GetDirection()``), with ``(UseDirectionCosines "true")``.
* ``FinalLinearInterpolator`` (``sitkLinear``; nearest neighbour and cubic B-spline on request),
  ``DefaultPixelValue`` the fill of ``registered.nii.gz``, ``ResultImagePixelType``, and no initial transform
  (``InitialTransformParametersFileName``, the spelling elastix 4 reads; elastix 5 reads it too).
"""

from __future__ import annotations

import math
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import Grid, matrix_to_params, params_to_sitk, sitk_to_matrix
from monai_rigidreg.export.transform_files import write_transform
from monai_rigidreg.io.volumes import check_output_path

__all__ = [
    "ELASTIX_PARAMETER_FILE",
    "elastix_parameter_map",
    "format_parameter_map",
    "write_elastix_transform",
    "read_elastix_transform",
    "write_transform_h5",
]

ELASTIX_PARAMETER_FILE = "TransformParameters.txt"
"""File name elastix gives its own result (``TransformParameters.0.txt`` for the first map)."""

_INTERPOLATORS = {
    "linear": ("FinalLinearInterpolator", 1),
    "nearest": ("FinalNearestNeighborInterpolator", 0),
    "bspline": ("FinalBSplineInterpolator", 3),
}
_PIXEL_TYPES = {
    "char", "unsigned char", "short", "unsigned short", "int", "unsigned int", "long", "unsigned long", "float",
    "double", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float32", "float64",
}


def _num(v: float | int) -> str:
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    f = float(v)
    if not math.isfinite(f):
        raise InputError(f"elastix parameters must be finite, got {f}")
    return repr(f) if f != 0.0 else "0"  # repr: shortest text that reads back to the same double


def _as_params(params_or_matrix: Any, center: np.ndarray) -> np.ndarray:
    """Project parameters ``(tx, ty, tz, rx, ry, rz)`` (mm, degrees) about ``center``."""
    if isinstance(params_or_matrix, sitk.Transform):
        return matrix_to_params(sitk_to_matrix(params_or_matrix), center)
    a = np.asarray(params_or_matrix, dtype=np.float64)
    if a.shape == (4, 4):
        return matrix_to_params(a, center)
    if a.shape == (6,):
        return a
    raise InputError(f"expected 6 parameters, a 4x4 matrix or a SimpleITK transform, got shape {a.shape}")


def elastix_parameter_map(params_or_matrix: Any, center: Sequence[float] | None, fixed_image: sitk.Image,
                          default_pixel_value: float, result_pixel_type: str = "float", interpolator: str = "linear"
                          ) -> dict[str, tuple[str, ...]]:
    """The elastix transform parameter map (name -> values as text; strings unquoted) of a rigid result.

    Args: as :func:`write_elastix_transform`.
    """
    if not isinstance(fixed_image, sitk.Image) or fixed_image.GetDimension() != 3:
        raise InputError("fixed_image must be a 3D SimpleITK image (the CT whose grid transformix writes)")
    if interpolator not in _INTERPOLATORS:
        raise InputError(f"interpolator must be one of {sorted(_INTERPOLATORS)}, got {interpolator!r}")
    if result_pixel_type not in _PIXEL_TYPES:
        raise InputError(f"result_pixel_type must be one of {sorted(_PIXEL_TYPES)}, got {result_pixel_type!r}")
    grid = Grid.from_sitk(fixed_image)
    c = grid.center() if center is None else np.asarray(center, dtype=np.float64).reshape(-1)
    if c.shape != (3,):
        raise InputError(f"center must have 3 coordinates, got {center!r}")
    try:
        itk_params = params_to_sitk(_as_params(params_or_matrix, c), c).GetParameters()  # rx ry rz (rad) tx ty tz
    except ValueError as exc:  # not rigid, not finite
        raise InputError(f"not a rigid transform: {exc}") from exc
    name, order = _INTERPOLATORS[interpolator]
    return {
        "Transform": ("EulerTransform",),
        "NumberOfParameters": ("6",),
        "TransformParameters": tuple(_num(v) for v in itk_params),
        "CenterOfRotationPoint": tuple(_num(v) for v in c),
        "ComputeZYX": ("false",),
        "InitialTransformParametersFileName": ("NoInitialTransform",),
        "HowToCombineTransforms": ("Compose",),
        "FixedImageDimension": ("3",),
        "MovingImageDimension": ("3",),
        "FixedInternalImagePixelType": ("float",),
        "MovingInternalImagePixelType": ("float",),
        "Size": tuple(_num(int(s)) for s in grid.size),
        "Index": ("0", "0", "0"),
        "Spacing": tuple(_num(v) for v in grid.spacing),
        "Origin": tuple(_num(v) for v in grid.origin),
        "Direction": tuple(_num(v) for v in grid.direction_matrix.T.ravel()),  # column by column
        "UseDirectionCosines": ("true",),
        "ResampleInterpolator": (name,),
        "FinalBSplineInterpolationOrder": (str(order),),
        "Resampler": ("DefaultResampler",),
        "DefaultPixelValue": (_num(default_pixel_value),),
        "ResultImageFormat": ("nii",),
        "ResultImagePixelType": (result_pixel_type,),
        "CompressResultImage": ("false",),
    }


_NUMERIC = {"NumberOfParameters", "TransformParameters", "CenterOfRotationPoint", "FixedImageDimension",
            "MovingImageDimension", "Size", "Index", "Spacing", "Origin", "Direction", "FinalBSplineInterpolationOrder",
            "DefaultPixelValue"}


def write_elastix_transform(
    path: str | Path,
    params_or_matrix: Any,
    center: Sequence[float] | None,
    fixed_image: sitk.Image,
    default_pixel_value: float,
    result_pixel_type: str = "float",
    *,
    interpolator: str = "linear",
    overwrite: bool = False,
) -> Path:
    """Write the rigid result as an elastix transform parameter file for ``transformix``.

    Args:
        path: the file to write (conventionally ``TransformParameters.txt``).
        params_or_matrix: ``(tx, ty, tz, rx, ry, rz)`` (mm, degrees) about ``center``, a 4x4 fixed->moving matrix
            (LPS mm) or a rigid SimpleITK transform.
        center: rotation centre written as ``CenterOfRotationPoint`` (LPS mm); ``None``: the fixed image's centre
            (the project's convention). Parameters are taken about it.
        fixed_image: the CT; its grid becomes transformix's output grid.
        default_pixel_value: value outside the CBCT, the fill ``registered.nii.gz`` uses.
        result_pixel_type: elastix ``ResultImagePixelType`` of the image transformix writes.
        interpolator: ``"linear"`` (as ``registered.nii.gz``), ``"nearest"`` or ``"bspline"`` (cubic).
        overwrite: replace an existing file.

    Returns:
        The path written.

    Raises:
        InputError: a non-rigid transform or bad arguments. OutputExistsError: the file exists.
    """
    pmap = elastix_parameter_map(params_or_matrix, center, fixed_image, default_pixel_value, result_pixel_type,
                                 interpolator)
    p = check_output_path(path, overwrite)
    p.write_text(format_parameter_map(pmap))
    return p


def format_parameter_map(pmap: dict[str, Sequence[str]]) -> str:
    """The text of an elastix parameter file: ``(Name value ...)`` lines, strings quoted, numbers bare."""
    lines = ["// rigid transform written by monai-rigidreg (fixed CT -> moving CBCT, LPS mm)"]
    for key, values in pmap.items():
        text = " ".join(values if key in _NUMERIC else (f'"{v}"' for v in values))
        lines.append(f"({key} {text})")
    return "\n".join(lines) + "\n"


def read_elastix_transform(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read an elastix ``EulerTransform`` parameter file back: project parameters and the centre.

    Returns:
        ``(params, center)``: ``(tx, ty, tz, rx, ry, rz)`` in mm / degrees about ``center`` (LPS mm).

    Raises:
        InputError: missing file, or not a single 3D ``EulerTransform`` with ``ComputeZYX`` false.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError("no such elastix parameter file", p)
    values: dict[str, list[str]] = {}
    for raw in p.read_text().splitlines():
        line = raw.split("//", 1)[0].strip()
        if line.startswith("(") and line.endswith(")"):
            fields = shlex.split(line[1:-1])
            if fields:
                values[fields[0]] = fields[1:]

    def get(key: str, default: list[str] | None = None) -> list[str]:
        if key not in values and default is None:
            raise InputError(f"elastix parameter file without {key}", p)
        return values.get(key, default)

    if get("Transform") != ["EulerTransform"] or get("FixedImageDimension", ["3"]) != ["3"]:
        raise InputError(f"expected a 3D EulerTransform, got {values.get('Transform')}", p)
    if get("ComputeZYX", ["false"]) != ["false"]:
        raise InputError("ComputeZYX \"true\" (R = Rz Ry Rx) is not the Euler3D convention read here", p)
    initial = values.get("InitialTransformParametersFileName", values.get("InitialTransformParameterFileName"))
    if initial not in (None, ["NoInitialTransform"]):
        raise InputError(f"chained initial transforms are not read here ({initial[0]})", p)
    try:
        tp = [float(v) for v in get("TransformParameters")]
        center = np.array([float(v) for v in get("CenterOfRotationPoint")])
    except ValueError as exc:
        raise InputError(f"unreadable number ({exc})", p) from exc
    if len(tp) != 6 or center.shape != (3,):
        raise InputError("expected 6 TransformParameters and a 3D CenterOfRotationPoint", p)
    params = np.concatenate([tp[3:], np.rad2deg(tp[:3])])
    return params, center


def write_transform_h5(transform: sitk.Transform, path: str | Path, overwrite: bool = False) -> Path:
    """Write ``transform`` as an ITK HDF5 transform (``.h5``; SimpleITK, ITK and 3D Slicer read it).

    Raises:
        InputError: ``path`` does not end in ``.h5`` or ``.hdf5``. OutputExistsError: the file exists.
    """
    p = Path(path)
    if p.suffix.lower() not in (".h5", ".hdf5"):
        raise InputError("an HDF5 transform file must end in .h5 or .hdf5", p)
    return write_transform(transform, p, overwrite=overwrite)
