"""The ITK transform file of a result (``transform.tfm``, ``transform.h5``), written and read back.

The file holds the ``Euler3DTransform`` that maps fixed (CT) points to moving (CBCT) points, LPS mm
(``docs/conventions.md``): ``Parameters: rx ry rz tx ty tz`` (radians, mm) and ``FixedParameters: cx cy cz 0``
(the centre). 3D Slicer, ITK and elastix read it.

>>> import tempfile, pathlib
>>> from monai_rigidreg.core.geometry import params_to_sitk, sitk_to_params
>>> path = pathlib.Path(tempfile.mkdtemp()) / "transform.tfm"
>>> _ = write_transform(params_to_sitk([5, 0, 0, 10, 0, 0], (1, 2, 3)), path)
>>> [round(float(v), 6) + 0.0 for v in sitk_to_params(read_transform(path))]  # tx ty tz mm, rx ry rz degrees
[5.0, 0.0, 0.0, 10.0, 0.0, 0.0]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.errors import InputError, first_line
from monai_rigidreg.core.geometry import matrix_to_sitk, sitk_to_matrix
from monai_rigidreg.io.prefetch import file_suffix
from monai_rigidreg.io.volumes import check_output_path

__all__ = ["TRANSFORM_SUFFIXES", "RIGID_TRANSFORM_TYPES", "write_transform", "read_transform"]

TRANSFORM_SUFFIXES = (".tfm", ".txt", ".h5", ".hdf5", ".mat")
"""File suffixes ITK reads and writes transforms in (text ``.tfm``/``.txt``, HDF5 ``.h5``/``.hdf5``, MATLAB
``.mat``)."""
RIGID_TRANSFORM_TYPES = ("Euler3DTransform", "VersorRigid3DTransform", "Similarity3DTransform", "IdentityTransform")


def write_transform(transform: sitk.Transform, path: str | Path, overwrite: bool = False) -> Path:
    """Write an ITK transform file (``.tfm``/``.txt`` text or ``.h5`` HDF5) that ITK, 3D Slicer and elastix read."""
    p = check_output_path(path, overwrite)
    if file_suffix(p) not in TRANSFORM_SUFFIXES:
        raise InputError(f"unsupported transform suffix {file_suffix(p)!r}; use one of {TRANSFORM_SUFFIXES}", p)
    sitk.WriteTransform(transform, str(p))
    return p


def read_transform(path: str | Path, rigid: bool = True) -> sitk.Transform:
    """Read an ITK transform file; with ``rigid=True`` return it as an ``Euler3DTransform``.

    Raises:
        InputError: missing/corrupt file, or (``rigid=True``) a transform that is not a 3D rigid transform
            (e.g. a B-spline, or an affine with scaling or shear).
    """
    p = Path(path)
    if not p.is_file():
        raise InputError("no such transform file", p)
    try:
        tfm = sitk.ReadTransform(str(p))
    except RuntimeError as exc:
        raise InputError(f"unreadable or corrupt transform file ({first_line(exc)})", p) from exc
    if not rigid:
        return tfm
    if tfm.GetDimension() != 3:
        raise InputError(f"expected a 3D transform, got a {tfm.GetDimension()}D one", p)
    names = _leaf_names(tfm)
    try:
        matrix = sitk_to_matrix(tfm)
    except ValueError as exc:
        raise InputError(f"expected a rigid transform, got {'+'.join(names)} ({exc})", p) from exc
    r = matrix[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or np.linalg.det(r) <= 0:
        raise InputError(f"expected a rigid transform, got {'+'.join(names)} with scaling or shear", p)
    typed = tfm.Downcast()
    center = typed.GetCenter() if hasattr(typed, "GetCenter") else (0.0, 0.0, 0.0)
    return matrix_to_sitk(matrix, center)


def _leaf_names(tfm: sitk.Transform) -> list[str]:
    if tfm.GetName() == "CompositeTransform":
        comp = sitk.CompositeTransform(tfm)
        return [n for i in range(comp.GetNumberOfTransforms()) for n in _leaf_names(comp.GetNthTransform(i))]
    return [tfm.GetName()]
