"""The one place where rigid-transform conventions are implemented.

Every conversion between the project's six parameters, 4x4 matrices, ``SimpleITK.Euler3DTransform``,
MONAI ``MetaTensor`` affines and the normalized ``theta`` that ``torch.nn.functional.affine_grid`` needs
lives here. Nothing else in the package re-derives them (see ``docs/conventions.md``).

Conventions
-----------
* Physical space: ITK/SimpleITK **LPS**, millimetres.
* A rigid transform ``T`` maps a point of the **fixed** image to the **moving** image,
  ``T(x) = R (x - c) + c + t`` (ITK's resampling direction), ``c`` the rotation centre (default the
  physical centre of the fixed image).
* ``R = Rz(rz) @ Rx(rx) @ Ry(ry)``: exactly ``SimpleITK.Euler3DTransform`` with default settings.
* User-facing parameters: ``(tx, ty, tz, rx, ry, rz)`` in mm and **degrees** (``PARAM_NAMES``).
  ITK stores ``(rx, ry, rz, tx, ty, tz)`` in radians; only :func:`params_to_sitk` / :func:`sitk_to_params`
  translate between the two.
* Arrays follow MONAI: channel first, spatial axes in ITK index order ``(x, y, z)``; SimpleITK's
  ``GetArrayFromImage`` order ``(z, y, x)`` is supported where stated via ``array_order="zyx"``.

Examples (the worked examples of ``docs/conventions.md``; mm and degrees, LPS):

>>> import numpy as np
>>> params = [5, 0, 0, 10, 0, 0]  # tx ty tz (mm), rx ry rz (degrees), about the centre (0, 0, 0)
>>> np.round(params_to_matrix(params) @ [0, 10, 0, 1], 3).tolist()  # maps the point (0, 10, 0)
[5.0, 9.848, 1.736, 1.0]
>>> np.round(params_to_sitk(params, (0, 0, 0)).TransformPoint((0, 10, 0)), 3).tolist()  # the same, by SimpleITK
[5.0, 9.848, 1.736]
>>> (np.round(matrix_to_params(params_to_matrix(params)), 6) + 0.0).tolist()  # + 0.0: no -0.0
[5.0, 0.0, 0.0, 10.0, 0.0, 0.0]
>>> (np.round(recenter_params(params, (0, 0, 0), (0, 10, 0)), 4) + 0.0).tolist()  # another centre: t changes
[5.0, -0.1519, 1.7365, 10.0, 0.0, 0.0]
>>> params_to_sitk(params, (1, 2, 3)).GetParameters()  # ITK's order: rx ry rz (radians), tx ty tz
(0.17453292519943295, 0.0, 0.0, 5.0, 0.0, 0.0)
>>> (lps_to_ras_affine(np.eye(4)) @ [10, 20, 30, 1]).tolist()  # LPS -> RAS flips x and y
[-10.0, -20.0, 30.0, 1.0]
>>> parameter_errors([1, 2, 3, 179, 0, -1], [0, 2, 5, -179, 0, 1]).tolist()  # angles wrapped: 179 vs -179 is 2
[1.0, 0.0, 2.0, 2.0, 0.0, 2.0]
>>> float(target_registration_error([3, 4, 0, 0, 0, 0], np.zeros(6), np.zeros((1, 3))))  # mm
5.0
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Union

import numpy as np
import SimpleITK as sitk
import torch

__all__ = [
    "PARAM_NAMES",
    "LPS_TO_RAS",
    "Grid",
    "rotation_matrix",
    "params_to_matrix",
    "matrix_to_params",
    "params_to_sitk",
    "sitk_to_params",
    "sitk_to_matrix",
    "matrix_to_sitk",
    "compose_matrices",
    "invert_matrix",
    "recenter_params",
    "params_to_matrix_torch",
    "matrix_to_params_torch",
    "index_to_normalized",
    "normalized_theta",
    "voxel_matrix",
    "lps_to_ras_affine",
    "ras_to_lps_affine",
    "ras_to_lps_transform",
    "transform_points",
    "target_registration_error",
    "point_distances_torch",
    "wrap_degrees",
    "parameter_errors",
    "grid_points",
    "mask_points",
]

PARAM_NAMES: tuple[str, ...] = ("tx", "ty", "tz", "rx", "ry", "rz")
"""User-facing parameter order: translations in mm, then rotations in degrees."""

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
"""Homogeneous flip between LPS and RAS (it is its own inverse)."""

ArrayLike = Union[np.ndarray, Sequence[float]]  # noqa: UP007 (runtime alias, Python 3.10 safe)


# ---------------------------------------------------------------------------------------------------------------
# Image grids
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Grid:
    """Geometry of a 3D image grid in ITK terms (LPS, mm).

    Args:
        size: number of voxels along the index axes ``(nx, ny, nz)``.
        spacing: voxel spacing in mm along ``(x, y, z)`` index axes.
        origin: physical LPS position (mm) of voxel index ``(0, 0, 0)``.
        direction: 3x3 direction cosines as 9 numbers, row-major (``sitk.Image.GetDirection()`` order);
            column ``j`` is the physical direction of index axis ``j``.
    """

    size: tuple[int, int, int]
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    direction: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "size", tuple(int(s) for s in self.size))
        object.__setattr__(self, "spacing", tuple(float(s) for s in self.spacing))
        object.__setattr__(self, "origin", tuple(float(s) for s in self.origin))
        object.__setattr__(self, "direction", tuple(float(s) for s in np.asarray(self.direction).ravel()))
        if len(self.size) != 3 or len(self.spacing) != 3 or len(self.origin) != 3 or len(self.direction) != 9:
            raise ValueError(f"Grid needs 3D size/spacing/origin and 9 direction cosines, got {self}.")
        if min(self.size) < 1 or min(self.spacing) <= 0:
            raise ValueError(f"Grid size must be >= 1 and spacing > 0, got size={self.size} spacing={self.spacing}.")

    # -- constructors ------------------------------------------------------------------------------------------
    @classmethod
    def from_sitk(cls, image: sitk.Image) -> Grid:
        """Grid of a 3D ``SimpleITK.Image``."""
        if image.GetDimension() != 3:
            raise ValueError(f"expected a 3D image, got a {image.GetDimension()}D image")
        return cls(image.GetSize(), image.GetSpacing(), image.GetOrigin(), image.GetDirection())

    @classmethod
    def from_affine(cls, affine: Any, spatial_shape: Sequence[int], space: str = "RAS") -> Grid:
        """Grid from a 4x4 index-to-physical affine (MONAI/nibabel style) and the spatial shape ``(nx, ny, nz)``.

        Args:
            affine: 4x4 matrix mapping array index ``(i, j, k, 1)`` to physical coordinates.
            spatial_shape: number of voxels along the array axes.
            space: ``"RAS"`` (MONAI's default) or ``"LPS"``: the space the affine maps into.
        """
        a = np.asarray(affine.detach().cpu() if isinstance(affine, torch.Tensor) else affine, dtype=np.float64)
        if a.shape != (4, 4):
            raise ValueError(f"expected a 4x4 affine, got shape {a.shape}")
        if str(space).upper() == "RAS":
            a = ras_to_lps_affine(a)
        elif str(space).upper() != "LPS":
            raise ValueError(f"space must be 'RAS' or 'LPS', got {space!r}")
        linear = a[:3, :3]
        spacing = np.linalg.norm(linear, axis=0)
        if np.any(spacing <= 0):
            raise ValueError("affine has a zero-length axis")
        direction = linear / spacing
        return cls(tuple(int(s) for s in spatial_shape), tuple(spacing), tuple(a[:3, 3]), tuple(direction.ravel()))

    @classmethod
    def from_metatensor(cls, tensor: Any) -> Grid:
        """Grid of a channel-first MONAI ``MetaTensor`` ``[C, x, y, z]`` (affine in the space its meta names)."""
        space = "RAS"
        meta = getattr(tensor, "meta", None) or {}
        if "space" in meta:
            space = str(meta["space"]).upper()
        shape = tuple(tensor.shape[-3:])
        return cls.from_affine(tensor.affine, shape, space=space)

    @classmethod
    def centered(cls, size: Sequence[int], spacing: Sequence[float], center: ArrayLike = (0.0, 0.0, 0.0)) -> Grid:
        """Axis-aligned grid of ``size`` voxels and ``spacing`` mm whose physical centre is ``center`` (LPS)."""
        size_a = np.asarray(size, dtype=np.float64)
        spacing_a = np.asarray(spacing, dtype=np.float64)
        origin = np.asarray(center, dtype=np.float64) - (size_a - 1) / 2.0 * spacing_a
        return cls(tuple(int(s) for s in size), tuple(spacing_a), tuple(origin))

    # -- derived quantities ------------------------------------------------------------------------------------
    @property
    def direction_matrix(self) -> np.ndarray:
        """3x3 direction cosine matrix (columns are index-axis directions)."""
        return np.asarray(self.direction, dtype=np.float64).reshape(3, 3)

    def index_to_physical(self) -> np.ndarray:
        """4x4 matrix mapping continuous index ``(i, j, k, 1)`` (ITK order) to LPS mm."""
        m = np.eye(4)
        m[:3, :3] = self.direction_matrix @ np.diag(self.spacing)
        m[:3, 3] = self.origin
        return m

    def physical_to_index(self) -> np.ndarray:
        """4x4 inverse of :meth:`index_to_physical`."""
        return np.linalg.inv(self.index_to_physical())

    def center(self) -> np.ndarray:
        """Physical LPS centre (mm) of the grid: the centre of the voxel block, index ``(size - 1) / 2``."""
        idx = (np.asarray(self.size, dtype=np.float64) - 1.0) / 2.0
        return (self.index_to_physical() @ np.append(idx, 1.0))[:3]

    def affine(self, space: str = "RAS") -> np.ndarray:
        """4x4 index-to-physical affine for MONAI/nibabel (``space="RAS"``, MONAI's default) or LPS."""
        a = self.index_to_physical()
        if space.upper() == "RAS":
            return lps_to_ras_affine(a)
        if space.upper() == "LPS":
            return a
        raise ValueError(f"space must be 'RAS' or 'LPS', got {space!r}")

    def corners(self) -> np.ndarray:
        """The 8 corner voxel centres ``[8, 3]`` in LPS mm (index ``(0 | size - 1)`` per axis, the last axis
        fastest). Any affine map's displacement over the grid's box is largest at one of them."""
        idx = np.array(np.meshgrid(*[[0, s - 1] for s in self.size], indexing="ij")).reshape(3, -1).T
        return transform_points(self.index_to_physical(), idx.astype(np.float64))

    def physical_extent(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (min, max) in LPS mm of the voxel centres."""
        pts = self.corners()
        return pts.min(axis=0), pts.max(axis=0)

    def to_sitk(self, pixel_type: int = sitk.sitkFloat32) -> sitk.Image:
        """An empty ``SimpleITK.Image`` with this grid."""
        img = sitk.Image([int(s) for s in self.size], pixel_type)
        self.apply_to(img)
        return img

    def apply_to(self, image: sitk.Image) -> sitk.Image:
        """Set spacing, origin and direction of ``image`` (in place) to this grid's; returns it."""
        image.SetSpacing(self.spacing)
        image.SetOrigin(self.origin)
        image.SetDirection(self.direction)
        return image


# ---------------------------------------------------------------------------------------------------------------
# Parameters <-> matrices <-> SimpleITK (numpy, float64)
# ---------------------------------------------------------------------------------------------------------------
def rotation_matrix(rx: float, ry: float, rz: float) -> np.ndarray:
    """3x3 rotation ``Rz(rz) @ Rx(rx) @ Ry(ry)`` for angles in **radians** (ITK Euler3D, ``ComputeZYX`` off)."""
    cx, sx = math.cos(rx), math.sin(rx)
    cy, sy = math.cos(ry), math.sin(ry)
    cz, sz = math.cos(rz), math.sin(rz)
    r_x = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    r_y = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    r_z = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return r_z @ r_x @ r_y


def _as_params(params: ArrayLike) -> np.ndarray:
    p = np.asarray(params, dtype=np.float64).reshape(-1)
    if p.shape != (6,):
        raise ValueError(f"expected 6 parameters (tx, ty, tz, rx, ry, rz), got shape {np.shape(params)}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"rigid parameters must be finite, got {p}")
    return p


def _as_center(center: ArrayLike | None) -> np.ndarray:
    c = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64).reshape(-1)
    if c.shape != (3,):
        raise ValueError(f"expected a 3D centre, got shape {np.shape(center)}")
    return c


def params_to_matrix(params: ArrayLike, center: ArrayLike | None = None) -> np.ndarray:
    """4x4 homogeneous matrix of the rigid transform (fixed -> moving, LPS mm).

    Args:
        params: ``(tx, ty, tz, rx, ry, rz)``, mm and degrees.
        center: rotation centre ``c`` in LPS mm (default the origin).

    Returns:
        ``M`` (4x4 float64) with ``M @ [x, 1] = R (x - c) + c + t``.
    """
    p = _as_params(params)
    c = _as_center(center)
    r = rotation_matrix(*np.deg2rad(p[3:]))
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = c + p[:3] - r @ c
    return m


def matrix_to_params(matrix: ArrayLike, center: ArrayLike | None = None) -> np.ndarray:
    """Inverse of :func:`params_to_matrix`: ``(tx, ty, tz, rx, ry, rz)`` in mm / degrees about ``center``.

    Raises:
        ValueError: if the 3x3 block is not a proper rotation (tolerance 1e-6).
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"expected a 4x4 matrix, got shape {m.shape}")
    r = m[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) <= 0:
        raise ValueError("matrix is not rigid: its 3x3 block is not a proper rotation")
    c = _as_center(center)
    rx = math.asin(float(np.clip(r[2, 1], -1.0, 1.0)))
    if abs(math.cos(rx)) > 1e-12:
        ry = math.atan2(-r[2, 0], r[2, 2])
        rz = math.atan2(-r[0, 1], r[1, 1])
    else:  # gimbal lock: rx = +-90 deg, set rz = 0 (as ITK does)
        ry = math.atan2(r[0, 2], r[0, 0])
        rz = 0.0
    t = m[:3, 3] - c + r @ c
    return np.concatenate([t, np.rad2deg([rx, ry, rz])])


def params_to_sitk(params: ArrayLike, center: ArrayLike | None = None) -> sitk.Euler3DTransform:
    """``SimpleITK.Euler3DTransform`` of user parameters ``(tx, ty, tz, rx, ry, rz)`` (mm / degrees)."""
    p = _as_params(params)
    tfm = sitk.Euler3DTransform()
    tfm.SetCenter([float(v) for v in _as_center(center)])
    rx, ry, rz = (float(v) for v in np.deg2rad(p[3:]))
    tfm.SetRotation(rx, ry, rz)
    tfm.SetTranslation([float(v) for v in p[:3]])
    return tfm


def sitk_to_matrix(transform: sitk.Transform) -> np.ndarray:
    """4x4 matrix of any SimpleITK transform with a matrix and an offset (Euler3D, Versor, Affine...).

    Composite transforms are flattened if every part is linear.
    """
    if not isinstance(transform, sitk.Transform):
        raise TypeError(f"expected a SimpleITK transform, got {type(transform).__name__}")
    if transform.GetDimension() != 3:
        raise ValueError(f"expected a 3D transform, got {transform.GetDimension()}D")
    name = transform.GetName()
    if name == "CompositeTransform":
        comp = sitk.CompositeTransform(transform)
        total = np.eye(4)
        # ITK applies the *last added* transform first
        for i in range(comp.GetNumberOfTransforms()):
            total = total @ sitk_to_matrix(comp.GetNthTransform(i))
        return total
    if name == "IdentityTransform":
        return np.eye(4)
    if name == "TranslationTransform":
        m = np.eye(4)
        m[:3, 3] = sitk.TranslationTransform(transform).GetOffset()
        return m
    typed = transform.Downcast()
    if not hasattr(typed, "GetMatrix"):
        raise ValueError(f"transform of type {name} is not linear and has no 4x4 matrix")
    mat = np.asarray(typed.GetMatrix(), dtype=np.float64).reshape(3, 3)
    offset_pt = np.asarray(typed.TransformPoint((0.0, 0.0, 0.0)), dtype=np.float64)
    m = np.eye(4)
    m[:3, :3] = mat
    m[:3, 3] = offset_pt
    return m


def matrix_to_sitk(matrix: ArrayLike, center: ArrayLike | None = None) -> sitk.Euler3DTransform:
    """``Euler3DTransform`` about ``center`` equal to a rigid 4x4 matrix."""
    c = _as_center(center)
    return params_to_sitk(matrix_to_params(matrix, c), c)


def sitk_to_params(transform: sitk.Transform, center: ArrayLike | None = None) -> np.ndarray:
    """User parameters ``(tx, ty, tz, rx, ry, rz)`` (mm / degrees) of a rigid SimpleITK transform.

    Args:
        transform: any rigid 3D SimpleITK transform (``Euler3DTransform``, ``VersorRigid3DTransform``, a
            composite of those...).
        center: centre to express the parameters about. Default: the transform's own centre where it has one
            (so ``sitk_to_params(params_to_sitk(p, c))`` returns ``p``), else the origin.
    """
    if center is None:
        typed = transform.Downcast()
        center = typed.GetCenter() if hasattr(typed, "GetCenter") else (0.0, 0.0, 0.0)
    return matrix_to_params(sitk_to_matrix(transform), center)


def compose_matrices(*matrices: ArrayLike) -> np.ndarray:
    """Composition of 4x4 transforms applied **right to left**: ``compose(A, B)(x) = A(B(x))``."""
    out = np.eye(4)
    for m in matrices:
        out = out @ np.asarray(m, dtype=np.float64)
    return out


def invert_matrix(matrix: ArrayLike) -> np.ndarray:
    """Inverse of a 4x4 rigid/affine matrix."""
    return np.linalg.inv(np.asarray(matrix, dtype=np.float64))


def recenter_params(params: ArrayLike, old_center: ArrayLike, new_center: ArrayLike) -> np.ndarray:
    """The same transform expressed about ``new_center`` (rotations unchanged, translation adjusted)."""
    return matrix_to_params(params_to_matrix(params, old_center), new_center)


# ---------------------------------------------------------------------------------------------------------------
# Differentiable torch versions (batched)
# ---------------------------------------------------------------------------------------------------------------
def _as_center_torch(center: Any, ref: torch.Tensor) -> torch.Tensor:
    if center is None:
        return torch.zeros(ref.shape[0], 3, dtype=ref.dtype, device=ref.device)
    c = torch.as_tensor(center, dtype=ref.dtype, device=ref.device)
    if c.ndim == 1:
        c = c.unsqueeze(0).expand(ref.shape[0], 3)
    if c.shape != (ref.shape[0], 3):
        raise ValueError(f"center must be [3] or [B, 3], got {tuple(c.shape)} for batch {ref.shape[0]}")
    return c


def params_to_matrix_torch(params: torch.Tensor, center: Any = None) -> torch.Tensor:
    """Batched, differentiable :func:`params_to_matrix`.

    Args:
        params: ``[B, 6]`` ``(tx, ty, tz, rx, ry, rz)`` in mm / degrees.
        center: ``[3]`` or ``[B, 3]`` rotation centre in LPS mm (default origin).

    Returns:
        ``[B, 4, 4]`` matrices (fixed -> moving, LPS mm), same dtype/device as ``params``.
    """
    if params.ndim != 2 or params.shape[-1] != 6:
        raise ValueError(f"params must be [B, 6], got {tuple(params.shape)}")
    b = params.shape[0]
    c = _as_center_torch(center, params)
    ang = torch.deg2rad(params[:, 3:])
    cx, cy, cz = torch.cos(ang).unbind(-1)
    sx, sy, sz = torch.sin(ang).unbind(-1)
    one, zero = torch.ones_like(cx), torch.zeros_like(cx)
    r_x = torch.stack([one, zero, zero, zero, cx, -sx, zero, sx, cx], -1).view(b, 3, 3)
    r_y = torch.stack([cy, zero, sy, zero, one, zero, -sy, zero, cy], -1).view(b, 3, 3)
    r_z = torch.stack([cz, -sz, zero, sz, cz, zero, zero, zero, one], -1).view(b, 3, 3)
    r = r_z @ r_x @ r_y
    offset = c + params[:, :3] - (r @ c.unsqueeze(-1)).squeeze(-1)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=params.dtype, device=params.device).expand(b, 1, 4)
    return torch.cat([torch.cat([r, offset.unsqueeze(-1)], -1), bottom], 1)


def matrix_to_params_torch(matrix: torch.Tensor, center: Any = None) -> torch.Tensor:
    """Batched :func:`matrix_to_params` for ``[B, 4, 4]`` rigid matrices (away from gimbal lock)."""
    if matrix.ndim != 3 or matrix.shape[-2:] != (4, 4):
        raise ValueError(f"matrix must be [B, 4, 4], got {tuple(matrix.shape)}")
    r = matrix[:, :3, :3]
    c = _as_center_torch(center, matrix)
    rx = torch.asin(r[:, 2, 1].clamp(-1.0, 1.0))
    ry = torch.atan2(-r[:, 2, 0], r[:, 2, 2])
    rz = torch.atan2(-r[:, 0, 1], r[:, 1, 1])
    t = matrix[:, :3, 3] - c + (r @ c.unsqueeze(-1)).squeeze(-1)
    return torch.cat([t, torch.rad2deg(torch.stack([rx, ry, rz], -1))], -1)


def _norm_to_index(size: Sequence[int], array_order: str) -> np.ndarray:
    """4x4 map from torch normalized coords (align_corners=True, last tensor axis first) to ITK index (x, y, z)."""
    if array_order not in ("xyz", "zyx"):
        raise ValueError(f"array_order must be 'xyz' (MONAI) or 'zyx' (SimpleITK arrays), got {array_order!r}")
    m = np.zeros((4, 4))
    m[3, 3] = 1.0
    # torch grid component g indexes tensor axis -(g+1); tensor axes are (x,y,z) or (z,y,x)
    axes = (2, 1, 0) if array_order == "xyz" else (0, 1, 2)  # index axis addressed by grid component g
    for g, ax in enumerate(axes):
        half = max(size[ax] - 1, 1) / 2.0
        m[ax, g] = half
        m[ax, 3] = half
    return m


def voxel_matrix(matrix: Any, fixed: Grid, moving: Grid) -> Any:
    """Index-space form of a physical transform: fixed index ``(i, j, k)`` -> moving index (ITK order).

    Accepts a numpy ``4x4`` or a torch ``[B, 4, 4]`` matrix and returns the same kind.
    """
    pf = fixed.index_to_physical()
    pm_inv = moving.physical_to_index()
    if isinstance(matrix, torch.Tensor):
        pf_t = torch.as_tensor(pf, dtype=matrix.dtype, device=matrix.device)
        pm_t = torch.as_tensor(pm_inv, dtype=matrix.dtype, device=matrix.device)
        return pm_t @ matrix @ pf_t
    return pm_inv @ np.asarray(matrix, dtype=np.float64) @ pf


def index_to_normalized(size: Sequence[int], array_order: str = "xyz") -> np.ndarray:
    """4x4 map from a grid's ITK voxel index ``(i, j, k, 1)`` to torch's normalized sampling coordinates
    (``grid_sample`` / ``affine_grid`` with ``align_corners=True``, the last tensor axis first), for tensors laid out
    in ``array_order``: the inverse of the map :func:`normalized_theta` is built from."""
    return np.linalg.inv(_norm_to_index(size, array_order))


def normalized_theta(matrix: torch.Tensor, fixed: Grid, moving: Grid, array_order: str = "xyz") -> torch.Tensor:
    """``theta`` (``[B, 3, 4]``) for ``F.affine_grid(..., align_corners=True)`` that resamples the moving volume
    onto the fixed grid under a physical fixed->moving transform, like ``SimpleITK.Resample(moving, fixed, T)``.

    Args:
        matrix: ``[B, 4, 4]`` physical transforms (fixed -> moving, LPS mm), e.g. from
            :func:`params_to_matrix_torch`; gradients flow through.
        fixed: grid of the output (the fixed image or the network grid).
        moving: grid of the moving tensor being sampled.
        array_order: spatial order of the tensors' last three axes: ``"xyz"`` for MONAI ``[B, C, x, y, z]``
            (default), ``"zyx"`` for arrays from ``sitk.GetArrayFromImage``.
    """
    if matrix.ndim != 3 or matrix.shape[-2:] != (4, 4):
        raise ValueError(f"matrix must be [B, 4, 4], got {tuple(matrix.shape)}")
    n_f = torch.as_tensor(_norm_to_index(fixed.size, array_order), dtype=matrix.dtype, device=matrix.device)
    n_m_inv = torch.as_tensor(
        np.linalg.inv(_norm_to_index(moving.size, array_order)), dtype=matrix.dtype, device=matrix.device
    )
    vox = voxel_matrix(matrix, fixed, moving)
    return (n_m_inv @ vox @ n_f)[:, :3, :]


# ---------------------------------------------------------------------------------------------------------------
# LPS <-> RAS
# ---------------------------------------------------------------------------------------------------------------
def lps_to_ras_affine(affine: ArrayLike) -> np.ndarray:
    """Index-to-LPS affine -> index-to-RAS affine (what MONAI ``MetaTensor`` carries by default)."""
    return LPS_TO_RAS @ np.asarray(affine, dtype=np.float64)


def ras_to_lps_affine(affine: ArrayLike) -> np.ndarray:
    """Index-to-RAS affine -> index-to-LPS affine."""
    return LPS_TO_RAS @ np.asarray(affine, dtype=np.float64)


def ras_to_lps_transform(matrix: ArrayLike) -> np.ndarray:
    """A point-to-point 4x4 transform written in RAS coordinates (greedy's and ITK-SNAP's matrices, NIfTI tools)
    -> the same transform in LPS: ``F @ M @ F`` with ``F = LPS_TO_RAS`` (its own inverse, so the same call converts
    back). Unlike an image affine (:func:`ras_to_lps_affine`), a transform's input is flipped too.

    >>> ras_to_lps_transform(params_to_matrix([5, 0, 0, 0, 0, 0]))[:3, 3].tolist()
    [-5.0, 0.0, 0.0]
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"expected a 4x4 matrix, got shape {m.shape}")
    return LPS_TO_RAS @ m @ LPS_TO_RAS


# ---------------------------------------------------------------------------------------------------------------
# Errors
# ---------------------------------------------------------------------------------------------------------------
def _as_matrix(t: Any, center: ArrayLike | None = None) -> np.ndarray:
    if isinstance(t, sitk.Transform):
        return sitk_to_matrix(t)
    a = np.asarray(t, dtype=np.float64)
    if a.shape == (6,):
        return params_to_matrix(a, center)
    if a.shape == (4, 4):
        return a
    raise ValueError(f"expected a 4x4 matrix, 6 parameters or a SimpleITK transform, got shape {a.shape}")


def transform_points(matrix: ArrayLike, points: ArrayLike) -> np.ndarray:
    """Apply a 4x4 transform to ``[N, 3]`` points (mm)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    m = np.asarray(matrix, dtype=np.float64)
    return pts @ m[:3, :3].T + m[:3, 3]


def grid_points(grid: Grid, step: int = 4) -> np.ndarray:
    """Physical LPS points (``[N, 3]``, mm) of every ``step``-th voxel of a grid."""
    idx = np.stack(np.meshgrid(*[np.arange(0, s, step) for s in grid.size], indexing="ij"), -1).reshape(-1, 3)
    return transform_points(grid.index_to_physical(), idx.astype(np.float64))


def mask_points(mask: sitk.Image, max_points: int = 20000, seed: int = 0) -> np.ndarray:
    """Physical LPS points (mm) of the non-zero voxels of a 3D mask, subsampled to ``max_points``."""
    arr = sitk.GetArrayViewFromImage(mask)
    zyx = np.argwhere(arr != 0)
    if zyx.size == 0:
        raise ValueError("mask has no non-zero voxel")
    if len(zyx) > max_points:
        zyx = zyx[np.random.default_rng(seed).choice(len(zyx), max_points, replace=False)]
    return transform_points(Grid.from_sitk(mask).index_to_physical(), zyx[:, ::-1].astype(np.float64))


def target_registration_error(
    t_pred: Any,
    t_true: Any,
    points: ArrayLike | sitk.Image,
    center: ArrayLike | None = None,
    reduction: str = "mean",
) -> float | np.ndarray:
    """Target registration error in mm: ``|T_pred(x) - T_true(x)|`` over points ``x``.

    Args:
        t_pred, t_true: 4x4 matrices, SimpleITK transforms, or 6 parameters (then ``center`` applies).
        points: ``[N, 3]`` LPS points (mm), or a 3D mask image whose non-zero voxels are the points.
        center: rotation centre for parameter inputs.
        reduction: ``"mean"``, ``"max"``, ``"median"`` or ``"none"`` (per-point distances).
    """
    pts = mask_points(points) if isinstance(points, sitk.Image) else np.asarray(points, dtype=np.float64)
    d = np.linalg.norm(
        transform_points(_as_matrix(t_pred, center), pts) - transform_points(_as_matrix(t_true, center), pts), axis=1
    )
    if reduction == "none":
        return d
    reducers = {"mean": np.mean, "max": np.max, "median": np.median}
    if reduction not in reducers:
        raise ValueError(f"reduction must be one of {sorted(reducers) + ['none']}, got {reduction!r}")
    return float(reducers[reduction](d))


def point_distances_torch(params_pred: torch.Tensor, params_true: torch.Tensor, points: torch.Tensor,
                          center: Any = None) -> torch.Tensor:
    """Batched, differentiable :func:`target_registration_error` per point: ``|T_pred(x) - T_true(x)|`` (mm).

    Args:
        params_pred, params_true: ``[B, 6]`` (mm, degrees) about ``center``.
        points: ``[N, 3]`` LPS points (mm).
        center: ``[3]`` or ``[B, 3]`` rotation centre (mm; default origin).

    Returns:
        ``[B, N]`` distances in the dtype of ``params_pred`` promoted to at least float32; exactly 0 with a zero
        (finite) gradient where the transforms agree.
    """
    dt = torch.promote_types(params_pred.dtype, torch.float32)
    m_pred = params_to_matrix_torch(params_pred.to(dt), center)
    m_true = params_to_matrix_torch(params_true.to(device=params_pred.device, dtype=dt), center)
    diff = m_pred - m_true  # [B, 4, 4]; (T_pred - T_true)(x) = diff[:3, :3] x + diff[:3, 3]
    pts = points.to(device=params_pred.device, dtype=dt)
    d = pts @ diff[:, :3, :3].transpose(1, 2) + diff[:, None, :3, 3]  # [B, N, 3]
    d2 = (d * d).sum(-1)
    return d2 / torch.sqrt(d2.clamp_min(1e-12))  # = sqrt(d2), but 0 with a finite (zero) gradient at d2 = 0


def wrap_degrees(angles: Any) -> Any:
    """Angles in degrees wrapped to ``[-180, 180)``: a number, numpy array or torch tensor (floor modulo)."""
    return (angles + 180.0) % 360.0 - 180.0


def parameter_errors(pred: ArrayLike, true: ArrayLike) -> np.ndarray:
    """Per-axis absolute errors ``|pred - true|`` of ``(tx, ty, tz, rx, ry, rz)`` (mm, degrees).

    Angle differences are wrapped to ``[-180, 180)`` before the absolute value. Works on ``[6]`` or ``[N, 6]``.
    Both must be expressed about the same centre.
    """
    p = np.asarray(pred, dtype=np.float64)
    t = np.asarray(true, dtype=np.float64)
    if p.shape != t.shape or p.shape[-1] != 6:
        raise ValueError(f"pred and true must both be [..., 6], got {p.shape} and {t.shape}")
    d = p - t
    d[..., 3:] = wrap_degrees(d[..., 3:])
    return np.abs(d)
