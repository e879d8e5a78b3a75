"""Phantoms: the 3D modified Shepp-Logan head, an asymmetric variant, a random anthropomorphic family, synthetic
anatomy (random label maps with random contrasts, :mod:`~monai_rigidreg.simulation.synth`) and real CTs.

Every phantom becomes a volume of linear attenuation coefficients ``mu`` (1/mm, at 70 keV) on an axis-aligned
:class:`~monai_rigidreg.core.geometry.Grid` centred on the isocentre, stored ``[nx, ny, nz]`` (MONAI order).
Analytic phantoms are lists of :class:`Shape` whose values are *added* in units of water attenuation
(``mu / mu_water``) and voxelized with supersampling (each voxel is the average over ``k^3`` sub-samples).

Attenuation and Hounsfield units: ``HU = 1000 (mu - mu_w) / mu_w``, ``mu_w = 0.0193 / mm`` (water, 70 keV).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.core.device import resolve_device
from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import Grid, rotation_matrix
from monai_rigidreg.io.volumes import load_volume

# the module, not its names: synth.py uses hu_to_mu from this module (see there)
from monai_rigidreg.simulation import synth as _synth
from monai_rigidreg.simulation.projector import grid_axes

__all__ = [
    "MU_WATER",
    "PHANTOMS",
    "Shape",
    "hu_to_mu",
    "mu_to_hu",
    "shepp_logan_shapes",
    "random_phantom_shapes",
    "voxelize",
    "load_ct",
    "ct_center",
    "ct_to_mu",
    "make_phantom",
]

MU_WATER: float = 0.0193
"""Linear attenuation of water at 70 keV, 1/mm."""

PHANTOMS: tuple[str, ...] = ("shepp-logan", "shepp-logan-asym", "random", "synth")
"""Names of the built-in phantoms (anything else is read as a path to a CT)."""


def hu_to_mu(hu: Any, mu_water: float = MU_WATER) -> Any:
    """Hounsfield units -> linear attenuation (1/mm), clipped at 0 (numpy array, tensor or float)."""
    mu = mu_water * (1.0 + hu / 1000.0)
    if isinstance(mu, torch.Tensor):
        return mu.clamp_min(0.0)
    return np.maximum(mu, 0.0)


def mu_to_hu(mu: Any, mu_water: float = MU_WATER) -> Any:
    """Linear attenuation (1/mm) -> Hounsfield units, ``1000 (mu - mu_w) / mu_w``."""
    return 1000.0 * (mu - mu_water) / mu_water


@dataclass(frozen=True)
class Shape:
    """An analytic solid whose value is added where it is.

    Args:
        kind: ``"ellipsoid"``, or ``"cylinder"`` (elliptic cross-section in the local x-y plane, axis along the
            local z, half-length ``semi_axes[2]``).
        value: added attenuation in units of water (``mu / mu_water``; 1 = water, negative carves).
        center: LPS position of the centre, mm.
        semi_axes: semi-axes along the local x, y, z axes, mm.
        angles: orientation ``(rx, ry, rz)`` in degrees: local axes are the columns of
            :func:`monai_rigidreg.core.geometry.rotation_matrix`.
    """

    kind: str
    value: float
    center: tuple[float, float, float]
    semi_axes: tuple[float, float, float]
    angles: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.kind not in ("ellipsoid", "cylinder"):
            raise ValueError(f"Shape kind must be 'ellipsoid' or 'cylinder', got {self.kind!r}")
        if min(self.semi_axes) <= 0:
            raise ValueError(f"semi-axes must be > 0 mm, got {self.semi_axes}")

    def rotation(self) -> np.ndarray:
        """3x3 local-to-world rotation."""
        return rotation_matrix(*np.deg2rad(self.angles))

    def half_extent(self) -> np.ndarray:
        """Half-size (mm) of the axis-aligned bounding box."""
        r = self.rotation()
        a = np.asarray(self.semi_axes)
        if self.kind == "ellipsoid":
            return np.sqrt(((r * a[None, :]) ** 2).sum(1))
        return np.abs(r * a[None, :]).sum(1)


# (value, semi-axes a b c, centre x y z, rotation about z in degrees), unit head of half-size 1.
_SHEPP_LOGAN_3D = (
    (1.0, (0.69, 0.92, 0.81), (0.0, 0.0, 0.0), 0.0),
    (-0.8, (0.6624, 0.874, 0.78), (0.0, -0.0184, 0.0), 0.0),
    (-0.2, (0.11, 0.31, 0.22), (0.22, 0.0, 0.0), -18.0),
    (-0.2, (0.16, 0.41, 0.28), (-0.22, 0.0, 0.0), 18.0),
    (0.1, (0.21, 0.25, 0.41), (0.0, 0.35, -0.15), 0.0),
    (0.1, (0.046, 0.046, 0.05), (0.0, 0.1, 0.25), 0.0),
    (0.1, (0.046, 0.046, 0.05), (0.0, -0.1, 0.25), 0.0),
    (0.1, (0.046, 0.023, 0.05), (-0.08, -0.605, 0.0), 0.0),
    (0.1, (0.023, 0.023, 0.02), (0.0, -0.606, 0.0), 0.0),
    (0.1, (0.023, 0.046, 0.02), (0.06, -0.605, 0.0), 0.0),
)


def shepp_logan_shapes(
    radius_mm: float = 128.0, asymmetric: bool = False, z_scale: float = 0.87, x_scale: float = 0.87
) -> list[Shape]:
    """The 3D modified Shepp-Logan head (Kak & Slaney / Toft ellipsoids), ``radius_mm`` = phantom half-size.

    Values are in units of water so the phantom looks like a CT: the stock intensities are kept except the
    skull (1.0 in the stock phantom), set to 1.8 (about +800 HU), so that the brain is water (0 HU), the
    ventricles -200 HU and the small features +100 HU.

    Args:
        radius_mm: physical half-size of the unit phantom, mm (the skull's largest semi-axis is 0.92 of it).
        asymmetric: scale the skull's z and x semi-axes by ``z_scale`` and ``x_scale``. The stock skull is
            nearly symmetric under rotations about x (y and z semi-axes 0.92 / 0.81), where classical registration
            fails; shortening z alone by 13 % breaks that but makes z (0.705) equal to x (0.69), a symmetry under
            rotations about y. With both shortened by 13 % the semi-axes (0.60, 0.92, 0.70) differ by >= 15 %.
        z_scale: factor of the skull's z semi-axes in the asymmetric variant (0.87: 13 % shorter).
        x_scale: factor of the skull's x semi-axes in the asymmetric variant (0.87: 13 % shorter).
    """
    shapes = []
    for k, (val, axes, ctr, rz) in enumerate(_SHEPP_LOGAN_3D):
        axes = tuple(radius_mm * a for a in axes)
        if asymmetric and k < 2:
            axes = (axes[0] * x_scale, axes[1], axes[2] * z_scale)
        value = 1.8 if k == 0 else val
        shapes.append(Shape("ellipsoid", value, tuple(radius_mm * c for c in ctr), axes, (0.0, 0.0, rz)))
    return shapes


def random_phantom_shapes(seed: int, radius_mm: float = 128.0) -> list[Shape]:
    """A random anthropomorphic phantom: a trunk or head of soft tissue with organs, bones and air cavities.

    Sizes, positions, orientations and contrasts are drawn from ``seed`` (``numpy`` PCG64), so a model sees
    many objects. Everything stays inside a sphere of ``0.95 radius_mm`` (rotations of the object keep it in a
    grid of half-size ``radius_mm``).

    Args:
        seed: random seed (any int >= 0).
        radius_mm: half-size of the region the phantom lives in, mm.
    """
    rng = np.random.default_rng(seed)
    r = radius_mm
    shapes: list[Shape] = []
    tissue = 1.0 + rng.normal(0.0, 0.01)
    a, b = rng.uniform(0.6, 0.85) * r, rng.uniform(0.45, 0.7) * r
    if rng.random() < 0.6:  # trunk: elliptic cylinder
        h = rng.uniform(0.4 * r, math.sqrt(max((0.95 * r) ** 2 - max(a, b) ** 2, (0.41 * r) ** 2)))
        body = Shape("cylinder", tissue, (0.0, 0.0, 0.0), (a, b, h), (0.0, 0.0, rng.uniform(-8, 8)))
    else:  # head-like ellipsoid
        body = Shape("ellipsoid", tissue, (0.0, 0.0, 0.0), (a, b, rng.uniform(0.6, 0.9) * r))
    shapes.append(body)
    ha, hb, hc = (0.75 * s for s in body.semi_axes)

    def inside_point(scale: float = 1.0) -> tuple[float, float, float]:
        while True:
            p = rng.uniform(-1, 1, 3)
            if (p**2).sum() <= 1:
                return (float(p[0] * ha * scale), float(p[1] * hb * scale), float(p[2] * hc * scale))

    def rand_angles(max_deg: float) -> tuple[float, float, float]:
        return tuple(float(x) for x in rng.uniform(-max_deg, max_deg, 3))  # type: ignore[return-value]

    if rng.random() < 0.4:  # lungs: two large low-density regions (about -750 HU)
        for side in (-1, 1):
            c = (side * rng.uniform(0.3, 0.4) * a, rng.uniform(-0.1, 0.1) * b, rng.uniform(-0.1, 0.2) * hc)
            ax = (rng.uniform(0.2, 0.3) * a, rng.uniform(0.45, 0.6) * b, rng.uniform(0.4, 0.6) * hc)
            shapes.append(Shape("ellipsoid", -0.75 * tissue, c, ax, rand_angles(10)))
    for _ in range(rng.integers(3, 8)):  # organs: +-20..90 HU
        ax = tuple(float(x) for x in rng.uniform(0.08, 0.25, 3) * r)
        val = float(rng.choice([-1, 1]) * rng.uniform(0.02, 0.09))
        shapes.append(Shape("ellipsoid", val, inside_point(0.8), ax, rand_angles(60)))  # type: ignore[arg-type]
    # spine: a cylinder along z, posterior (LPS +y)
    sp_r = rng.uniform(0.05, 0.09) * r
    sp_half = 0.95 * body.semi_axes[2]
    if body.kind == "ellipsoid":  # keep the spine inside the curved ends of a head-like body
        sp_half *= math.sqrt(max(1.0 - ((0.7 * b + sp_r) / b) ** 2, 0.04))
    shapes.append(
        Shape(
            "cylinder",
            rng.uniform(0.5, 0.9),
            (rng.uniform(-0.05, 0.05) * a, 0.7 * b - sp_r, 0.0),
            (sp_r, sp_r * rng.uniform(0.8, 1.2), sp_half),
            (rng.uniform(-5, 5), rng.uniform(-5, 5), 0.0),
        )
    )
    for _ in range(rng.integers(1, 4)):  # other bones (pelvis, femoral heads, sternum...)
        ax = tuple(float(x) for x in rng.uniform(0.04, 0.14, 3) * r)
        shapes.append(Shape("ellipsoid", float(rng.uniform(0.4, 1.0)), inside_point(0.9), ax, rand_angles(45)))
    for _ in range(rng.integers(1, 4)):  # air cavities (bowel gas, sinuses)
        ax = tuple(float(x) for x in rng.uniform(0.03, 0.1, 3) * r)
        shapes.append(Shape("ellipsoid", -tissue, inside_point(0.8), ax, rand_angles(45)))  # type: ignore[arg-type]
    return shapes


def voxelize(
    shapes: list[Shape],
    grid: Grid,
    supersample: int = 2,
    mu_water: float = MU_WATER,
    device: str | torch.device | None = "cpu",
    max_elements: int = 1 << 23,
) -> torch.Tensor:
    """Voxelize shapes: each voxel holds the sub-sample average of the summed values, times ``mu_water``.

    Args:
        shapes: the solids.
        grid: axis-aligned output grid.
        supersample: sub-samples per voxel and axis (1 = voxel centres).
        mu_water: attenuation of value 1, 1/mm.
        device: torch device.
        max_elements: work in x-slabs of about this many voxels.

    Returns:
        ``[nx, ny, nz]`` float32 attenuation (1/mm), clipped at 0.
    """
    dev = resolve_device(device)
    axes = grid_axes(grid, dev)
    out = torch.zeros(grid.size, dtype=torch.float32, device=dev)
    k = max(1, int(supersample))
    offs = [((j + 0.5) / k - 0.5) for j in range(k)]
    for shape in shapes:
        ext = shape.half_extent()
        lo, hi = [], []
        for d in range(3):
            o, s, n = grid.origin[d], grid.spacing[d], grid.size[d]
            lo.append(max(0, int(math.floor((shape.center[d] - ext[d] - o) / s)) - 1))
            hi.append(min(n, int(math.ceil((shape.center[d] + ext[d] - o) / s)) + 2))
        if any(h <= lo_ for lo_, h in zip(lo, hi)):
            continue
        rt = torch.as_tensor(shape.rotation().T, dtype=torch.float64, device=dev)
        inv_axes = [1.0 / a for a in shape.semi_axes]
        slab = max(1, max_elements // ((hi[1] - lo[1]) * (hi[2] - lo[2])))
        for x0 in range(lo[0], hi[0], slab):
            x1 = min(hi[0], x0 + slab)
            rel = [axes[0][x0:x1] - shape.center[0], axes[1][lo[1] : hi[1]] - shape.center[1]]
            rel.append(axes[2][lo[2] : hi[2]] - shape.center[2])
            frac = torch.zeros(x1 - x0, hi[1] - lo[1], hi[2] - lo[2], dtype=torch.float32, device=dev)
            for ox in offs:
                for oy in offs:
                    for oz in offs:
                        px = (rel[0] + ox * grid.spacing[0])[:, None, None]
                        py = (rel[1] + oy * grid.spacing[1])[None, :, None]
                        pz = (rel[2] + oz * grid.spacing[2])[None, None, :]
                        loc = [(rt[i, 0] * px + rt[i, 1] * py + rt[i, 2] * pz) * inv_axes[i] for i in range(3)]
                        if shape.kind == "ellipsoid":
                            inside = loc[0] ** 2 + loc[1] ** 2 + loc[2] ** 2 <= 1.0
                        else:
                            inside = (loc[0] ** 2 + loc[1] ** 2 <= 1.0) & (loc[2].abs() <= 1.0)
                        frac += inside
            out[x0:x1, lo[1] : hi[1], lo[2] : hi[2]] += (shape.value * mu_water / k**3) * frac
    return out.clamp_min_(0.0)


def load_ct(path: str | Path) -> sitk.Image:
    """Read a CT (NIfTI/NRRD/MHA file or a DICOM series directory) as a float32 ``SimpleITK.Image`` in HU.

    Reads with :func:`monai_rigidreg.io.load_volume`.

    Raises:
        InputError: missing or unreadable file, not 3D, or non-finite values.
    """
    p = Path(path)
    if not p.exists():
        raise InputError("CT file or DICOM directory not found", p)
    img = load_volume(p)  # the package's reader: DICOM series, corrupt files and NaN named as InputError
    if img.GetDimension() != 3 or img.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"expected a 3D scalar CT, got a {img.GetDimension()}D image", p)
    img = sitk.Cast(img, sitk.sitkFloat32)
    arr = sitk.GetArrayViewFromImage(img)
    if not np.isfinite(arr).all():
        raise InputError("the CT holds NaN or infinite values", p)
    return img


def image_center(image: sitk.Image) -> np.ndarray:
    """Physical centre (LPS mm) of an image: the point half-way between its first and last voxel centres."""
    size = np.asarray(image.GetSize(), dtype=np.float64)
    return np.asarray(image.TransformContinuousIndexToPhysicalPoint(((size - 1) / 2).tolist()))


_CENTERS: dict[tuple, np.ndarray] = {}


def ct_center(path: str | Path) -> np.ndarray:
    """Physical centre (LPS mm) of the CT at ``path`` as :func:`load_ct` reads it: the point a simulation from that CT
    is centred on (:func:`ct_to_mu`). A file's header alone is read; a DICOM folder is read whole (once per folder
    and modification time in a process)."""
    p = Path(path)
    key = (str(p.resolve()), p.stat().st_mtime_ns)
    if key not in _CENTERS:
        if p.is_dir():
            _CENTERS[key] = image_center(load_ct(p))
        else:
            reader = sitk.ImageFileReader()
            reader.SetFileName(str(p))
            reader.ReadImageInformation()
            if reader.GetDimension() != 3:
                raise InputError(f"expected a 3D scalar CT, got a {reader.GetDimension()}D image", p)
            half = np.asarray(reader.GetSpacing()) * (np.asarray(reader.GetSize(), dtype=np.float64) - 1) / 2
            direction = np.asarray(reader.GetDirection(), dtype=np.float64).reshape(3, 3)
            _CENTERS[key] = np.asarray(reader.GetOrigin(), dtype=np.float64) + direction @ half
    return _CENTERS[key].copy()


def ct_to_mu(image: sitk.Image, grid: Grid, device: str | torch.device | None = "cpu") -> torch.Tensor:
    """Attenuation volume of a CT (HU) on ``grid``, the CT's physical centre placed at the grid centre.

    The CT is smoothed before downsampling (Gaussian, sigma half the spacing ratio) and resampled linearly;
    outside it is air (-1000 HU). HU are converted with :func:`hu_to_mu` (clipped at 0).

    Returns:
        ``[nx, ny, nz]`` float32 attenuation (1/mm).
    """
    src = sitk.Cast(image, sitk.sitkFloat32)
    sigma = [max(0.0, 0.5 * (g - s)) for g, s in zip(grid.spacing, src.GetSpacing())]
    if max(sigma) > 0:
        src = sitk.SmoothingRecursiveGaussian(src, [max(s, 1e-3) for s in sigma])
    shift = sitk.TranslationTransform(3, (image_center(image) - grid.center()).tolist())
    res = sitk.Resample(src, grid.to_sitk(), shift, sitk.sitkLinear, -1000.0, sitk.sitkFloat32)
    arr = sitk.GetArrayFromImage(res).transpose(2, 1, 0).copy()  # [z, y, x] -> [x, y, z]
    return hu_to_mu(torch.from_numpy(arr)).to(resolve_device(device))


def make_phantom(
    phantom: str | Path,
    grid: Grid,
    seed: int = 0,
    supersample: int = 2,
    radius_mm: float | None = None,
    device: str | torch.device | None = "cpu",
) -> tuple[torch.Tensor, dict[str, Any]]:
    """Attenuation volume ``[nx, ny, nz]`` (1/mm) of a named phantom or a CT file, and a JSON-able description.

    Args:
        phantom: ``"shepp-logan"``, ``"shepp-logan-asym"``, ``"random"``, ``"synth"`` (synthetic anatomy,
            :func:`~monai_rigidreg.simulation.synth.synth_phantom`, defined in mm so that every grid shows the
            same object; ``supersample`` does not apply) or a path to a CT.
        grid: object grid (axis-aligned, centred on the isocentre).
        seed: seed of the random and synthetic families.
        supersample: sub-samples per voxel and axis for analytic phantoms.
        radius_mm: half-size of analytic phantoms, mm (default: half the smallest extent of ``grid``).
        device: torch device.
    """
    name = str(phantom)
    if radius_mm is None:
        radius_mm = 0.5 * min(n * s for n, s in zip(grid.size, grid.spacing))
    if name in ("shepp-logan", "shepp-logan-asym"):
        shapes = shepp_logan_shapes(radius_mm, asymmetric=name.endswith("asym"))
        desc: dict[str, Any] = {"phantom": name, "radius_mm": radius_mm}
    elif name == "random":
        shapes = random_phantom_shapes(seed, radius_mm)
        desc = {"phantom": name, "seed": int(seed), "radius_mm": radius_mm}
    elif name == "synth":
        desc = {"phantom": name, "seed": int(seed), "radius_mm": radius_mm}
        return _synth.synth_phantom(grid, seed, radius_mm=radius_mm, device=device), desc
    else:
        img = load_ct(name)
        desc = {"phantom": "ct", "path": str(Path(name).resolve())}
        return ct_to_mu(img, grid, device), desc
    desc["shapes"] = [asdict(s) for s in shapes]
    return voxelize(shapes, grid, supersample, device=device), desc
