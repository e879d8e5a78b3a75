"""CT/CBCT pairs with clinical geometry from a real planning CT (issue 15).

The paper protocol (:mod:`.protocols`, :func:`~monai_rigidreg.simulation.simulate_case`) simulates both images
about the CT centre. A physicist's pairs look different: the CBCT is centred on the treatment isocentre somewhere
inside a larger planning CT, the setup error (couch and patient) reaches several centimetres and tens of degrees,
the anatomy may have changed between the scans, and the match is judged on the target region. This module builds
such pairs from a real CT; ``benchmarks/bench_clinical_geometry.py`` registers them.

Frames (LPS mm throughout, one physical frame shared by both images, as a registration system sees them):

* **CT frame.** The planning CT is the real CT itself, on its own grid (the fixed image; :func:`load_planning_ct`
  resamples only very large CTs). ``c`` is its grid centre (:meth:`~monai_rigidreg.geometry.Grid.center`).
* **Isocentre** ``p``: a point inside the body (at least ``min_depth_mm`` deep) at a chosen distance ``|p - c|``
  from the CT centre (:func:`sample_isocenter`).
* **CBCT frame.** The CBCT grid is axis aligned and centred on ``p``: with a perfect setup the CBCT shows the
  CT's anatomy at the same coordinates (identity transform), as a linac's CBCT is exported relative to the planned
  isocentre.
* **Setup error** ``T`` (fixed -> moving, the project's convention): the anatomy at CT point ``x`` sits at
  ``T(x) = R (x - p) + p + t`` in the CBCT: a rotation ``R`` about the isocentre and a translation ``t`` (the
  table shift). Its parameters about ``p`` are ``params_isocenter``; the ground truth of the registration is the
  same transform about the CT centre, ``geometry.recenter_params(params_isocenter, p, c)`` (``params``).
* **Deformation** (deformed pairs): on the day of treatment the anatomy at CT point ``x`` has moved to
  ``phi(x)`` before the setup error, so it sits at ``T(phi(x))`` in the CBCT. ``phi`` is smooth and zero outside a
  region near the isocentre (:class:`SmoothDeformation`); it is stored by its pull-back displacement ``v``: the
  deformed anatomy is ``CT(y - v(y))``, and ``phi`` inverts ``y -> y - v(y)``.
* **Scanner frame** of the projector (:mod:`.scanner`): the CBCT frame shifted by ``-p`` (isocentre at the origin,
  rotation axis ``+z``). The moved (and deformed) patient is resampled once from the CT into it
  (:func:`moved_object`): ``mu(s) = mu_CT(T^-1(s + p) - v(T^-1(s + p)))``, then projected with the cone beam
  (:func:`~monai_rigidreg.simulation.cone_forward`), degraded (noise, scatter, beam hardening:
  :func:`~monai_rigidreg.simulation.apply_cbct_physics`) and reconstructed with FDK
  (:func:`~monai_rigidreg.simulation.fdk`): the building blocks of
  :func:`~monai_rigidreg.simulation.simulate_cbct`, with a detector as wide as the whole patient and only as tall
  as the field of view needs (:func:`simulate_clinical_cbct`).

Beyond its first and last slices the CT is continued by repeating them for ``extension_mm`` (the patient goes on
beyond the scanned range; a cut-off body would throw cone-beam artefacts that no real CBCT has); elsewhere outside
the CT is air. The detector covers the whole patient and the field of view is a cylinder applied in the image
domain, as in the project's simulator (the reconstruction has no truncation correction).
"""

from __future__ import annotations

import json
import math
import os
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch
import torch.nn.functional as F

from monai_rigidreg.device import resolve_device
from monai_rigidreg.geometry import (
    Grid,
    invert_matrix,
    mask_points,
    params_to_matrix,
    recenter_params,
    transform_points,
)
from monai_rigidreg.simulation.phantoms import hu_to_mu, load_ct, mu_to_hu
from monai_rigidreg.simulation.physics import CBCTPhysics, apply_cbct_physics, fov_mask
from monai_rigidreg.simulation.projector import cone_forward, grid_axes
from monai_rigidreg.simulation.reconstruction import fdk
from monai_rigidreg.simulation.scanner import ConeBeamGeometry

__all__ = [
    "CLINICAL_GROUPS",
    "CLINICAL_PHYSICS",
    "ClinicalCBCTSpec",
    "ClinicalCase",
    "ClinicalGroup",
    "PlanningCT",
    "SmoothDeformation",
    "best_rigid_fit",
    "body_mask",
    "case_seed",
    "inside_mask",
    "load_clinical_case",
    "load_planning_ct",
    "make_clinical_case",
    "moved_object",
    "roi_landmarks",
    "sample_deformation",
    "sample_isocenter",
    "sample_motion",
    "save_clinical_case",
    "simulate_clinical_cbct",
    "tre_points",
]

CLINICAL_PHYSICS = CBCTPhysics(photons=3e4, scatter_to_primary=0.5, beam_hardening=0.02)
"""CBCT degradations of the clinical pairs: those of ``benchmarks/bench_real_ct.py`` (noisy on-board imager)."""

_WENDLAND_SLOPE = 20.0 * 0.25 * 0.75**3
"""Largest ``|psi'(r)|`` of the Wendland bump ``psi(r) = (1 - r)^4 (4 r + 1)`` (at ``r = 1/4``)."""


# ---------------------------------------------------------------------------------------------------------------
# Settings
# ---------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ClinicalCBCTSpec:
    """The CBCT acquisition of the clinical pairs.

    Args:
        size: CBCT grid ``(nx, ny, nz)`` voxels (default 128 x 128 x 80: a 256 mm diameter, 160 mm long field of view
            at 2 mm, like a full-fan on-board imager).
        spacing: isotropic voxel size, mm (also the detector pixel back-projected to the isocentre and the spacing
            of the object the projector sees).
        views: projections over 360 degrees.
        sod, sdd: source-isocentre and source-detector distances, mm (a linac's on-board imager: 1000 / 1500).
        window: FDK filter window.
        physics: degradations; its ``fov_diameter_mm`` (``None``: the grid's in-plane width) makes the field of view
            a cylinder.
        extension_mm: how far beyond its end slices the CT is continued (repeated end slices), mm.
    """

    size: tuple[int, int, int] = (128, 128, 80)
    spacing: float = 2.0
    views: int = 180
    sod: float = 1000.0
    sdd: float = 1500.0
    window: str = "shepp-logan"
    physics: CBCTPhysics = CLINICAL_PHYSICS
    extension_mm: float = 100.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "size", tuple(int(s) for s in self.size))
        if len(self.size) != 3 or min(self.size) < 2 or self.spacing <= 0:
            raise ValueError(f"need a 3D size >= 2 and spacing > 0, got {self.size}, {self.spacing}")
        if self.physics.fov_diameter_mm is None:
            object.__setattr__(self, "physics", replace(self.physics, fov_diameter_mm=self.fov_diameter_mm))

    @property
    def fov_diameter_mm(self) -> float:
        """Diameter of the cylindrical field of view, mm."""
        if self.physics.fov_diameter_mm is not None:
            return float(self.physics.fov_diameter_mm)
        return float(min(self.size[:2]) * self.spacing)

    @property
    def length_mm(self) -> float:
        """Axial extent of the CBCT grid, mm."""
        return float(self.size[2] * self.spacing)

    def grid(self, isocenter: Sequence[float] = (0.0, 0.0, 0.0)) -> Grid:
        """The CBCT grid centred on ``isocenter`` (CBCT frame; the origin for the scanner frame)."""
        return Grid.centered(self.size, (self.spacing,) * 3, isocenter)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able description."""
        d = asdict(self)
        d["physics"] = self.physics.to_dict()
        return json.loads(json.dumps(d))


@dataclass(frozen=True)
class ClinicalGroup:
    """How the cases of one benchmark group are drawn.

    Args:
        name: the group's name.
        translation_mm: ``(low, high)`` length of the translation vector ``|t|``, mm (uniform in length, uniform
            direction).
        max_rotation_deg: every rotation angle uniform in ``[-max, max]`` degrees.
        min_peak_rotation_deg: if > 0, one axis (at random) is drawn with ``|angle|`` in ``[min_peak, max]``, so
            that the largest angle of every case is at least this.
        isocenter_distance_mm: ``(low, high)`` distance of the isocentre from the CT centre, mm (uniform).
        deformation_mm: ``(low, high)`` peak of the smooth deformation, mm; ``None``: rigid anatomy.
    """

    name: str
    translation_mm: tuple[float, float] = (0.0, 40.0)
    max_rotation_deg: float = 30.0
    min_peak_rotation_deg: float = 0.0
    isocenter_distance_mm: tuple[float, float] = (0.0, 100.0)
    deformation_mm: tuple[float, float] | None = None

    def describe(self) -> str:
        """One line for tables."""
        t0, t1 = self.translation_mm
        rot = f"|angles| <= {self.max_rotation_deg:g} deg"
        if self.min_peak_rotation_deg > 0:
            rot += f", largest >= {self.min_peak_rotation_deg:g}"
        d0, d1 = self.isocenter_distance_mm
        text = f"|t| {t0:g}-{t1:g} mm, {rot}, isocentre {d0:g}-{d1:g} mm from the CT centre"
        if self.deformation_mm is not None:
            text += f", deformation peak {self.deformation_mm[0]:g}-{self.deformation_mm[1]:g} mm"
        return text


CLINICAL_GROUPS: dict[str, ClinicalGroup] = {
    "small": ClinicalGroup("small", (0.0, 40.0), 30.0),
    "large": ClinicalGroup("large", (40.0, 60.0), 45.0, min_peak_rotation_deg=30.0),
    "deformed": ClinicalGroup("deformed", (0.0, 40.0), 30.0, deformation_mm=(5.0, 15.0)),
}
"""The benchmark's groups: ``small`` (up to 40 mm / 30 degrees), ``large`` (the band beyond it: 40-60 mm and a
largest angle of 30-45 degrees, every angle up to 45), ``deformed`` (``small`` plus a 5-15 mm deformation)."""


def case_seed(seed: int, *keys: int | str) -> int:
    """A 32-bit seed from the master ``seed`` and stream keys (strings hashed with CRC-32, stable across runs)."""
    ints = [int(seed)] + [zlib.crc32(k.encode()) if isinstance(k, str) else int(k) for k in keys]
    return int(np.random.SeedSequence(ints).generate_state(1)[0])


# ---------------------------------------------------------------------------------------------------------------
# The planning CT
# ---------------------------------------------------------------------------------------------------------------
def body_mask(ct: sitk.Image, threshold_hu: float = -400.0, opening_mm: float = 4.0) -> sitk.Image:
    """The patient's body in a CT: above ``threshold_hu``, opened (detaches the couch), the largest connected
    component, holes filled slice by slice (lungs, bowel gas and airways count as body).

    Returns:
        uint8 mask on the CT grid.
    """
    m = sitk.BinaryThreshold(ct, float(threshold_hu), 1e9, 1, 0)
    radius = [max(1, int(round(opening_mm / s))) for s in ct.GetSpacing()]
    m = sitk.BinaryMorphologicalOpening(m, radius)
    labels = sitk.RelabelComponent(sitk.ConnectedComponent(m), sortByObjectSize=True)
    m = sitk.Cast(labels == 1, sitk.sitkUInt8)
    filled = sitk.JoinSeries([sitk.BinaryFillhole(m[:, :, k]) for k in range(m.GetDepth())])
    filled = sitk.Cast(filled, sitk.sitkUInt8)
    filled.CopyInformation(m)
    return filled


@dataclass
class PlanningCT:
    """A real CT used as the planning CT, with what the pair generation needs.

    Attributes:
        image: float32 HU, the fixed image (native grid unless ``resampled_from`` says otherwise).
        body: uint8 body mask (:func:`body_mask`) on the same grid.
        depth: float32 distance into the body, mm (positive inside, negative outside).
        name: file name without extension; path: the file read.
        resampled_from: the native ``(size, spacing)`` when the CT was resampled, else ``None``.
    """

    image: sitk.Image
    body: sitk.Image
    depth: sitk.Image
    name: str
    path: Path | None = None
    resampled_from: tuple[tuple[int, ...], tuple[float, ...]] | None = None
    _mu: dict[tuple[float, str], torch.Tensor] = field(default_factory=dict, repr=False)

    @property
    def grid(self) -> Grid:
        """The CT grid."""
        return Grid.from_sitk(self.image)

    @property
    def center(self) -> np.ndarray:
        """Grid centre ``c`` (LPS mm): the centre of the ground truth's parameters."""
        return self.grid.center()

    def z_range(self) -> tuple[float, float]:
        """Physical ``z`` range (mm) of the CT's voxel centres."""
        lo, hi = self.grid.physical_extent()
        return float(lo[2]), float(hi[2])

    def mu(self, spacing: float, device: torch.device) -> torch.Tensor:
        """Attenuation (1/mm) ``[nk, nj, ni]`` (SimpleITK array order) on the CT grid, smoothed for sampling at
        ``spacing`` mm as :func:`~monai_rigidreg.simulation.ct_to_mu` does (cached)."""
        key = (float(spacing), str(device))
        if key not in self._mu:
            src = self.image
            sigma = [max(0.0, 0.5 * (spacing - s)) for s in src.GetSpacing()]
            if max(sigma) > 0:
                src = sitk.SmoothingRecursiveGaussian(src, [max(s, 1e-3) for s in sigma])
            arr = torch.from_numpy(sitk.GetArrayFromImage(src).astype(np.float32))
            self._mu.clear()
            self._mu[key] = hu_to_mu(arr).to(device)
        return self._mu[key]


def load_planning_ct(
    source: str | Path | sitk.Image,
    name: str | None = None,
    max_voxels: int = 1 << 24,
    large_spacing_mm: float = 1.5,
) -> PlanningCT:
    """Read a real CT as the planning CT of clinical pairs.

    The CT keeps its grid unless it has more than ``max_voxels`` voxels (default 2^24, a 256^3 CT); then it is
    smoothed and resampled to at least ``large_spacing_mm`` per axis (recorded in ``resampled_from``).

    Args:
        source: a CT file / DICOM folder (HU) or a ``SimpleITK.Image`` in HU.
        name: label (default: the file name without extension, or ``"ct"``).
        max_voxels, large_spacing_mm: the resampling rule.
    """
    path = None
    if isinstance(source, sitk.Image):
        img = sitk.Cast(source, sitk.sitkFloat32)
    else:
        path = Path(source)
        img = load_ct(path)
    if name is None:
        name = "ct" if path is None else path.name.split(".nii")[0].split(".mh")[0].split(".nrrd")[0]
    resampled_from = None
    if int(np.prod(img.GetSize())) > max_voxels:
        sp0 = np.asarray(img.GetSpacing())
        sp = np.maximum(sp0, large_spacing_mm)
        size = np.ceil(np.asarray(img.GetSize()) * sp0 / sp).astype(int)
        sigma = [max(1e-3, 0.5 * (a - b)) for a, b in zip(sp, sp0)]
        smooth = sitk.SmoothingRecursiveGaussian(img, sigma)
        ref = sitk.Image([int(s) for s in size], sitk.sitkFloat32)
        ref.SetSpacing(sp.tolist())
        ref.SetDirection(img.GetDirection())
        # same physical centre
        c0 = np.asarray(img.TransformContinuousIndexToPhysicalPoint(((np.asarray(img.GetSize()) - 1) / 2).tolist()))
        d = np.asarray(img.GetDirection()).reshape(3, 3)
        ref.SetOrigin((c0 - d @ ((size - 1) / 2 * sp)).tolist())
        resampled_from = (tuple(img.GetSize()), tuple(img.GetSpacing()))
        img = sitk.Resample(smooth, ref, sitk.Transform(), sitk.sitkLinear, -1000.0, sitk.sitkFloat32)
    body = body_mask(img)
    depth = sitk.SignedMaurerDistanceMap(body, insideIsPositive=True, squaredDistance=False, useImageSpacing=True)
    return PlanningCT(img, body, sitk.Cast(depth, sitk.sitkFloat32), name, path, resampled_from)


def _nearest_values(image: sitk.Image, points: np.ndarray, outside: float = 0.0) -> np.ndarray:
    """Values of ``image`` at the nearest voxel of each ``[N, 3]`` point (``outside`` beyond the grid)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    idx = np.rint(transform_points(Grid.from_sitk(image).physical_to_index(), pts)).astype(np.int64)
    size = np.asarray(image.GetSize())
    ok = np.all((idx >= 0) & (idx < size), axis=1)
    out = np.full(len(pts), outside, dtype=np.float64)
    arr = sitk.GetArrayViewFromImage(image)
    out[ok] = arr[idx[ok, 2], idx[ok, 1], idx[ok, 0]]
    return out


def inside_mask(mask: sitk.Image, points: np.ndarray) -> np.ndarray:
    """Whether each ``[N, 3]`` point (LPS mm) falls in a non-zero voxel of ``mask`` (nearest voxel)."""
    return _nearest_values(mask, points) > 0


# ---------------------------------------------------------------------------------------------------------------
# Sampling: isocentre, setup error, deformation, landmarks
# ---------------------------------------------------------------------------------------------------------------
def _unit_vector(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / max(float(np.linalg.norm(v)), 1e-12)


def sample_isocenter(
    ct: PlanningCT,
    rng: np.random.Generator,
    distance_mm: tuple[float, float] = (0.0, 100.0),
    min_depth_mm: float = 10.0,
    cbct_length_mm: float | None = None,
    max_tries: int = 20000,
) -> tuple[np.ndarray, float]:
    """An isocentre inside the body at a distance from the CT centre drawn uniformly in ``distance_mm``.

    A distance is drawn, then directions (uniform on the sphere) until the point is at least ``min_depth_mm``
    inside the body and, with ``cbct_length_mm``, the CBCT's axial extent about it lies within the CT's slices (the
    CBCT inside a larger planning CT); a distance without such a direction after 100 tries is drawn again (so
    distances the body cannot hold are skipped).

    Returns:
        ``(p, |p - c|)``: the isocentre (LPS mm) and its distance from the CT centre (mm).

    Raises:
        ValueError: when no point qualifies.
    """
    c = ct.center
    z0, z1 = ct.z_range()
    half = 0.0 if cbct_length_mm is None else 0.5 * float(cbct_length_mm)
    if half and (z1 - z0) < 2 * half:
        raise ValueError(f"the CT ({z1 - z0:.0f} mm long) is shorter than the CBCT ({2 * half:.0f} mm)")
    d = 0.0
    for attempt in range(max_tries):
        if attempt % 100 == 0:
            d = float(rng.uniform(*distance_mm))
        p = c + d * _unit_vector(rng)
        if half and not (z0 <= p[2] - half and p[2] + half <= z1):
            continue
        if _nearest_values(ct.depth, p[None], outside=-1.0)[0] >= min_depth_mm:
            return p, float(np.linalg.norm(p - c))
    raise ValueError(f"no isocentre {distance_mm} mm from the CT centre {min_depth_mm} mm inside the body of {ct.name}")


def sample_motion(
    rng: np.random.Generator,
    translation_mm: tuple[float, float] = (0.0, 40.0),
    max_rotation_deg: float = 30.0,
    min_peak_rotation_deg: float = 0.0,
) -> np.ndarray:
    """A setup error ``(tx, ty, tz, rx, ry, rz)`` (mm, degrees) about the isocentre.

    ``|t|`` is uniform in ``translation_mm`` with a uniform direction; every angle is uniform in
    ``[-max_rotation_deg, max_rotation_deg]``; with ``min_peak_rotation_deg`` one axis (at random) has
    ``|angle|`` uniform in ``[min_peak_rotation_deg, max_rotation_deg]``.
    """
    t = float(rng.uniform(*translation_mm)) * _unit_vector(rng)
    angles = rng.uniform(-max_rotation_deg, max_rotation_deg, 3)
    if min_peak_rotation_deg > 0:
        axis = int(rng.integers(3))
        angles[axis] = float(rng.choice([-1.0, 1.0])) * float(rng.uniform(min_peak_rotation_deg, max_rotation_deg))
    return np.concatenate([t, angles])


@dataclass(frozen=True)
class SmoothDeformation:
    """A smooth, compactly supported displacement: a sum of Wendland bumps.

    ``v(y) = sum_k a_k psi(|y - c_k| / R_k)`` with ``psi(r) = (1 - r)^4 (4 r + 1)`` for ``r < 1``, else 0 (C2, exactly
    zero beyond ``R_k``). ``v`` is the *pull-back* displacement: the deformed anatomy is ``CT(y - v(y))``; the
    anatomy at CT point ``x`` goes to ``phi(x)``, the solution of ``phi - v(phi) = x`` (:meth:`forward`), so
    ``phi(x) - x = v(phi(x))`` and both have the same peak. ``phi`` is a diffeomorphism while
    :meth:`lipschitz_bound` < 1.

    Args:
        centers: ``[K, 3]`` bump centres (LPS mm, CT frame). radii: ``[K]`` support radii, mm.
        amplitudes: ``[K, 3]`` displacement vectors at the centres, mm.
    """

    centers: tuple[tuple[float, float, float], ...]
    radii: tuple[float, ...]
    amplitudes: tuple[tuple[float, float, float], ...]

    def __post_init__(self) -> None:
        c = np.asarray(self.centers, dtype=np.float64).reshape(-1, 3)
        a = np.asarray(self.amplitudes, dtype=np.float64).reshape(-1, 3)
        r = np.asarray(self.radii, dtype=np.float64).reshape(-1)
        if not (len(c) == len(a) == len(r)) or np.any(r <= 0):
            raise ValueError("need as many centres, amplitudes and (positive) radii")
        object.__setattr__(self, "centers", tuple(tuple(float(v) for v in row) for row in c))
        object.__setattr__(self, "amplitudes", tuple(tuple(float(v) for v in row) for row in a))
        object.__setattr__(self, "radii", tuple(float(v) for v in r))

    def _arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return np.asarray(self.centers), np.asarray(self.radii), np.asarray(self.amplitudes)

    def displacement(self, points: np.ndarray) -> np.ndarray:
        """``v`` at ``[N, 3]`` points (mm), ``[N, 3]`` mm."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.zeros_like(pts)
        for c, r, a in zip(*self._arrays()):
            q = np.linalg.norm(pts - c, axis=1) / r
            w = np.where(q < 1.0, (1.0 - np.minimum(q, 1.0)) ** 4 * (4.0 * q + 1.0), 0.0)
            out += w[:, None] * a
        return out

    def displacement_torch(self, points: torch.Tensor) -> torch.Tensor:
        """``v`` at ``[..., 3]`` points (torch, dtype and device of ``points``)."""
        out = torch.zeros_like(points)
        for c, r, a in zip(*self._arrays()):
            ct = torch.as_tensor(c, dtype=points.dtype, device=points.device)
            at = torch.as_tensor(a, dtype=points.dtype, device=points.device)
            q = torch.linalg.vector_norm(points - ct, dim=-1) / float(r)
            qc = q.clamp(max=1.0)
            out += ((1.0 - qc) ** 4 * (4.0 * qc + 1.0))[..., None] * at
        return out

    def lipschitz_bound(self) -> float:
        """An upper bound of the Lipschitz constant of ``v`` (``sum_k |a_k| max|psi'| / R_k``)."""
        _, r, a = self._arrays()
        return float(np.sum(np.linalg.norm(a, axis=1) * _WENDLAND_SLOPE / r))

    def forward(self, points: np.ndarray, tol: float = 1e-6, max_iter: int = 500) -> np.ndarray:
        """``phi(x)``: where the anatomy at CT points ``x`` ``[N, 3]`` is after the deformation (fixed-point
        iteration ``y <- x + v(y)``, a contraction while :meth:`lipschitz_bound` < 1)."""
        x = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        y = x + self.displacement(x)
        for _ in range(max_iter):
            y_new = x + self.displacement(y)
            if np.max(np.abs(y_new - y), initial=0.0) < tol:
                return y_new
            y = y_new
        return y

    def peak(self) -> float:
        """``max |v|`` (mm): a 4 mm grid over the supports, refined twice around its maximum (to 0.05 mm)."""
        c, r, _ = self._arrays()
        lo, hi = (c - r[:, None]).min(0), (c + r[:, None]).max(0)
        pts = np.stack(np.meshgrid(*[np.arange(a, b + 4.0, 4.0) for a, b in zip(lo, hi)], indexing="ij"), -1)
        mags = np.linalg.norm(self.displacement(pts.reshape(-1, 3)), axis=1)
        best, best_val = pts.reshape(-1, 3)[int(np.argmax(mags))], float(mags.max())
        for half, step in ((4.0, 0.5), (0.5, 0.05)):
            off = np.arange(-half, half + step / 2, step)
            local = best + np.stack(np.meshgrid(off, off, off, indexing="ij"), -1).reshape(-1, 3)
            mags = np.linalg.norm(self.displacement(local), axis=1)
            if float(mags.max()) > best_val:
                best, best_val = local[int(np.argmax(mags))], float(mags.max())
        return best_val

    def scaled(self, factor: float) -> SmoothDeformation:
        """The same bumps with amplitudes times ``factor``."""
        return SmoothDeformation(self.centers, self.radii, tuple(tuple(factor * v for v in a) for a in self.amplitudes))

    def to_dict(self) -> dict[str, Any]:
        """JSON-able description."""
        return {"centers": [list(c) for c in self.centers], "radii": list(self.radii),
                "amplitudes": [list(a) for a in self.amplitudes]}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SmoothDeformation:
        """Inverse of :meth:`to_dict`."""
        return cls(tuple(map(tuple, d["centers"])), tuple(d["radii"]), tuple(map(tuple, d["amplitudes"])))


def sample_deformation(
    rng: np.random.Generator,
    near: Sequence[float],
    peak_mm: float,
    num_bumps: tuple[int, int] = (1, 3),
    radius_mm: tuple[float, float] = (60.0, 100.0),
    offset_mm: float = 30.0,
    max_lipschitz: float = 0.7,
    max_tries: int = 200,
) -> SmoothDeformation:
    """A local smooth deformation of peak ``peak_mm`` near a point (the isocentre): a different breathing state or
    organ filling around the target, zero outside the bumps.

    ``num_bumps`` Wendland bumps (uniform count in the closed range), centres within ``offset_mm`` of ``near``, support
    radii uniform in ``radius_mm``, random amplitude vectors scaled so that the peak of ``|v|`` is ``peak_mm``;
    redrawn until :meth:`SmoothDeformation.lipschitz_bound` <= ``max_lipschitz`` (a smooth, invertible map).
    """
    near = np.asarray(near, dtype=np.float64)
    for _ in range(max_tries):
        k = int(rng.integers(num_bumps[0], num_bumps[1] + 1))
        dirs = np.stack([_unit_vector(rng) for _ in range(k)])
        centers = near + offset_mm * np.cbrt(rng.uniform(0, 1, (k, 1))) * dirs
        radii = rng.uniform(*radius_mm, k)
        amps = np.stack([_unit_vector(rng) * rng.uniform(0.5, 1.0) for _ in range(k)])
        d = SmoothDeformation(tuple(map(tuple, centers)), tuple(radii), tuple(map(tuple, amps)))
        d = d.scaled(peak_mm / max(d.peak(), 1e-9))
        if d.lipschitz_bound() <= max_lipschitz:
            return d
    raise ValueError(f"no deformation of peak {peak_mm} mm with Lipschitz bound <= {max_lipschitz}")


def roi_landmarks(
    ct: PlanningCT,
    center: Sequence[float],
    box_mm: float = 70.0,
    num_points: int = 200,
    seed: int = 0,
    gradient_quantile: float = 0.75,
) -> np.ndarray:
    """Landmarks of the target region: body voxels of the CT with a high gradient (edges of organs and bones) in a
    cube of ``box_mm`` centred on ``center``.

    Candidates are the body voxels of the box whose gradient magnitude (Gaussian, sigma 1.5 mm) is above the box's
    ``gradient_quantile``; ``num_points`` of them are drawn (seeded). Falls back to any body voxel of the box.

    Returns:
        ``[N, 3]`` LPS points (mm, CT frame), ``N <= num_points``.
    """
    grid = ct.grid
    c = np.asarray(center, dtype=np.float64)
    corners = np.array(np.meshgrid(*[[-0.5, 0.5]] * 3, indexing="ij")).reshape(3, -1).T * box_mm + c
    idx = transform_points(grid.physical_to_index(), corners)
    lo = np.clip(np.floor(idx.min(0)).astype(int), 0, np.asarray(grid.size) - 1)
    hi = np.clip(np.ceil(idx.max(0)).astype(int), 0, np.asarray(grid.size) - 1)
    size = (hi - lo + 1).tolist()
    sub = sitk.RegionOfInterest(ct.image, size, lo.tolist())
    body = sitk.RegionOfInterest(ct.body, size, lo.tolist())
    grad = sitk.GetArrayFromImage(sitk.GradientMagnitudeRecursiveGaussian(sub, 1.5))
    zyx = np.argwhere(sitk.GetArrayViewFromImage(body) > 0)
    if len(zyx) == 0:
        raise ValueError(f"no body voxel in the {box_mm} mm box about {c.tolist()}")
    pts = transform_points(Grid.from_sitk(sub).index_to_physical(), zyx[:, ::-1].astype(np.float64))
    in_box = np.all(np.abs(pts - c) <= box_mm / 2, axis=1)
    zyx, pts = zyx[in_box], pts[in_box]
    g = grad[zyx[:, 0], zyx[:, 1], zyx[:, 2]]
    strong = g >= np.quantile(g, gradient_quantile) if len(g) else np.zeros(0, bool)
    cand = pts[strong] if strong.sum() >= min(num_points, 20) else pts
    rng = np.random.default_rng(seed)
    if len(cand) > num_points:
        cand = cand[rng.choice(len(cand), num_points, replace=False)]
    return cand


def best_rigid_fit(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares rigid transform ``target ~ R source + t`` (Kabsch, reflections excluded).

    Returns:
        ``(4x4 matrix, mean residual distance in mm)``: the floor of any rigid registration's landmark error.
    """
    p = np.asarray(source, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    pc, qc = p.mean(0), q.mean(0)
    h = (p - pc).T @ (q - qc)
    u, _, vt = np.linalg.svd(h)
    s = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(vt.T @ u.T)) or 1.0)])
    r = vt.T @ s @ u.T
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = qc - r @ pc
    return m, float(np.linalg.norm(transform_points(m, p) - q, axis=1).mean())


def tre_points(ct: PlanningCT, matrix: np.ndarray, fov: sitk.Image, max_points: int = 20000) -> np.ndarray:
    """The CT body points whose true position ``T(x)`` lies in the CBCT's field of view (``[N, 3]``, CT frame):
    where the target registration error of a pair is measured."""
    pts = mask_points(ct.body, max_points=max_points)
    return pts[inside_mask(fov, transform_points(matrix, pts))]


# ---------------------------------------------------------------------------------------------------------------
# The CBCT
# ---------------------------------------------------------------------------------------------------------------
def _detector_half_height(spec: ClinicalCBCTSpec) -> float:
    """Half-height (mm on the detector) that covers the field of view's slab: every voxel of the CBCT grid within
    the cylinder, seen from the nearest source position (the project's ``ConeBeamGeometry.fitted`` margin)."""
    half_h = 0.5 * spec.length_mm + spec.spacing
    return spec.sdd * half_h / (spec.sod - 0.5 * spec.fov_diameter_mm) * 1.05


def _object_grid(ct: PlanningCT, matrix: np.ndarray, isocenter: np.ndarray, spec: ClinicalCBCTSpec,
                 margin_mm: float) -> Grid:
    """The scanner-frame grid the projector needs: the whole moved patient in ``x, y`` (every ray through the field
    of view crosses it) and, axially, as far as the cone reaches at the far side of the patient."""
    body_pts = mask_points(sitk.BinaryThreshold(ct.image, -900.0, 1e9, 1, 0), max_points=40000, seed=1)
    # the continuation beyond the end slices: the first and last slices' content, repeated
    grid = ct.grid
    idx = transform_points(grid.physical_to_index(), body_pts)
    axis = grid.direction_matrix[:, 2] * grid.spacing[2]
    ends = []
    for k_end, sign in ((0.0, -1.0), (grid.size[2] - 1.0, 1.0)):
        near_end = body_pts[np.abs(idx[:, 2] - k_end) <= 2.0]
        for step in np.linspace(0.0, spec.extension_mm / grid.spacing[2], 6):
            ends.append(near_end + sign * step * axis)
    pts = transform_points(matrix, np.concatenate([body_pts, *ends])) - isocenter
    rho = np.linalg.norm(pts[:, :2], axis=1)
    r_all = min(float(rho.max()) + margin_mm, 0.9 * spec.sod)
    z_reach = _detector_half_height(spec) * (spec.sod + r_all) / spec.sdd + 2 * spec.spacing
    in_slab = np.abs(pts[:, 2]) <= z_reach + margin_mm
    r = float(rho[in_slab].max(initial=0.0)) + margin_mm
    r = max(min(r, 0.9 * spec.sod), 0.5 * spec.fov_diameter_mm + spec.spacing)
    sp = spec.spacing
    return Grid.centered((2 * math.ceil(r / sp), 2 * math.ceil(r / sp), 2 * math.ceil(z_reach / sp)), (sp, sp, sp))


def moved_object(
    ct: PlanningCT,
    matrix: np.ndarray,
    isocenter: Sequence[float],
    object_grid: Grid,
    deformation: SmoothDeformation | None = None,
    extension_mm: float = 100.0,
    device: str | torch.device | None = "cpu",
    chunk_slices: int = 8,
) -> torch.Tensor:
    """The patient as the CBCT scanner sees it: attenuation ``[nx, ny, nz]`` (1/mm) on ``object_grid`` (scanner
    frame, isocentre at the origin).

    ``mu(s) = mu_CT(x)`` with ``x = y - v(y)``, ``y = T^-1(s + p)`` (``T = matrix``, fixed -> moving; ``v`` the
    deformation's pull-back displacement, or 0): one trilinear resampling of the CT. Beyond the CT's first and last
    slices the end slices continue for ``extension_mm``; elsewhere outside the CT is air.
    """
    dev = resolve_device(device)
    mu = ct.mu(min(object_grid.spacing), dev)
    nk, nj, ni = mu.shape
    grid = ct.grid
    inv = torch.as_tensor(invert_matrix(matrix), dtype=torch.float64, device=dev)
    to_index = torch.as_tensor(grid.physical_to_index(), dtype=torch.float64, device=dev)
    p = torch.as_tensor(np.asarray(isocenter, dtype=np.float64), device=dev)
    xs, ys, zs = (o + s * torch.arange(n, dtype=torch.float64, device=dev)
                  for o, s, n in zip(object_grid.origin, object_grid.spacing, object_grid.size))
    ext = float(extension_mm) / grid.spacing[2]
    out = torch.empty(tuple(object_grid.size), dtype=torch.float32, device=dev)
    vol = mu[None, None]
    for z0 in range(0, len(zs), chunk_slices):
        zc = zs[z0 : z0 + chunk_slices]
        s = torch.stack(torch.meshgrid(xs, ys, zc, indexing="ij"), -1)  # [nx, ny, c, 3] scanner frame
        y = (s + p) @ inv[:3, :3].T + inv[:3, 3]  # CT frame of the day of treatment
        x = y - deformation.displacement_torch(y) if deformation is not None else y
        idx = x @ to_index[:3, :3].T + to_index[:3, 3]  # continuous (i, j, k)
        k = idx[..., 2]
        beyond = (k < -ext) | (k > nk - 1 + ext)
        k = torch.where(beyond, torch.full_like(k, -4.0), k.clamp(0.0, nk - 1.0))
        norm = torch.stack([
            idx[..., 0] * (2.0 / max(ni - 1, 1)) - 1.0,
            idx[..., 1] * (2.0 / max(nj - 1, 1)) - 1.0,
            torch.where(beyond, torch.full_like(k, -4.0), k * (2.0 / max(nk - 1, 1)) - 1.0),
        ], -1).to(torch.float32)
        out[:, :, z0 : z0 + len(zc)] = F.grid_sample(vol, norm[None], mode="bilinear", padding_mode="zeros",
                                                     align_corners=True)[0, 0]
    return out


def simulate_clinical_cbct(
    ct: PlanningCT,
    isocenter: Sequence[float],
    params_isocenter: Sequence[float],
    deformation: SmoothDeformation | None = None,
    spec: ClinicalCBCTSpec | None = None,
    seed: int = 0,
    device: str | torch.device | None = "cpu",
) -> tuple[sitk.Image, sitk.Image, dict[str, Any]]:
    """The CBCT of the (deformed and) moved patient, centred on the isocentre.

    Args:
        ct: the planning CT.
        isocenter: ``p`` (LPS mm, CT frame).
        params_isocenter: the setup error ``T`` (fixed -> moving) ``(tx, ty, tz, rx, ry, rz)`` about ``p``.
        deformation: the anatomy's change before the setup error, or ``None``.
        spec: the acquisition (default :class:`ClinicalCBCTSpec`).
        seed: noise seed.
        device: torch device of the projector.

    Returns:
        ``(cbct, fov, info)``: the CBCT (float32 HU, grid centred on ``p``, CBCT frame), its field-of-view mask
        (uint8, same grid) and ``{"object_grid": size, "detector": ...}``.
    """
    spec = ClinicalCBCTSpec() if spec is None else spec
    dev = resolve_device(device)
    p = np.asarray(isocenter, dtype=np.float64)
    m = params_to_matrix(params_isocenter, p)
    margin = spec.spacing * 2 + (0.0 if deformation is None else deformation.peak())
    obj_grid = _object_grid(ct, m, p, spec, margin)
    obj = moved_object(ct, m, p, obj_grid, deformation, spec.extension_mm, dev)
    # the detector: wide enough for the whole patient (no truncation), tall enough for the field of view's slab
    xs, ys, _ = grid_axes(obj_grid, dev)
    occupied = (obj > 1e-5).any(2)
    r_obj = float(torch.sqrt(xs[:, None] ** 2 + ys[None, :] ** 2)[occupied].max()) if bool(occupied.any()) else 0.0
    r_obj = max(r_obj + spec.spacing, 0.5 * spec.fov_diameter_mm + spec.spacing)
    geom = ConeBeamGeometry(sod=spec.sod, sdd=spec.sdd, num_views=spec.views).fitted(r_obj, 0.0, spec.spacing)
    pitch = geom.pixel_pitch[1]
    geom = replace(geom, detector_shape=(geom.detector_shape[0],
                                         2 * math.ceil(_detector_half_height(spec) / pitch) + 2))
    proj = cone_forward(obj, obj_grid, geom, dev)
    del obj
    gen = torch.Generator(device=dev).manual_seed(int(seed))
    proj = apply_cbct_physics(proj, geom, spec.physics, gen)
    scanner_grid = spec.grid()
    fov = fov_mask(scanner_grid, geom, spec.physics, dev)
    rec = fdk(proj, geom, scanner_grid, spec.window, dev, columns=fov.any(2))  # the rest is masked to 0 below
    del proj
    rec = torch.where(fov, rec, torch.zeros_like(rec))
    out_grid = spec.grid(p)
    arr = mu_to_hu(rec.detach().to("cpu", torch.float32)).numpy().transpose(2, 1, 0)
    cbct = out_grid.apply_to(sitk.GetImageFromArray(np.ascontiguousarray(arr.astype(np.float32))))
    fov_img = out_grid.apply_to(sitk.GetImageFromArray(
        np.ascontiguousarray(fov.cpu().numpy().transpose(2, 1, 0).astype(np.uint8))))
    info = {"object_grid": list(obj_grid.size), "object_spacing_mm": spec.spacing,
            "detector": [int(v) for v in geom.detector_shape], "detector_pitch_mm": list(geom.pixel_pitch)}
    return cbct, fov_img, info


# ---------------------------------------------------------------------------------------------------------------
# One case
# ---------------------------------------------------------------------------------------------------------------
@dataclass
class ClinicalCase:
    """One clinical pair: the CBCT (moving), its field of view, and the ground truth record.

    ``record`` (JSON-able) holds ``case_id``, ``ct``, ``group``, ``isocenter`` and ``isocenter_distance_mm``,
    ``params_isocenter`` (the setup error about the isocentre), ``center`` (the CT centre) with ``params`` (the
    ground truth about it) and ``matrix`` (4x4, fixed -> moving), ``deformation`` (or ``None``), ``roi``
    (``center`` and ``size_mm`` of the target region), ``landmarks`` (CT frame) and ``landmarks_moving`` (their
    true CBCT positions ``T(phi(x))``; only landmarks inside the field of view are kept), ``rigid_floor_mm`` (the
    mean landmark error of the best rigid fit), ``seed``, ``cbct`` (the acquisition) and ``simulation`` (object
    grid and detector).
    """

    cbct: sitk.Image
    fov: sitk.Image
    record: dict[str, Any]

    @property
    def matrix(self) -> np.ndarray:
        """Ground truth 4x4 (fixed -> moving, LPS mm)."""
        return np.asarray(self.record["matrix"], dtype=np.float64)


def make_clinical_case(
    ct: PlanningCT,
    group: ClinicalGroup,
    seed: int,
    case_id: str = "case",
    spec: ClinicalCBCTSpec | None = None,
    roi_box_mm: float = 70.0,
    num_landmarks: int = 200,
    min_depth_mm: float = 10.0,
    device: str | torch.device | None = "cpu",
) -> ClinicalCase:
    """Draw and simulate one clinical pair of ``group`` (deterministic in ``seed``).

    Draws, in this order from ``numpy.random.default_rng(seed)``: the isocentre (:func:`sample_isocenter`, the CBCT
    inside the CT's slices), the setup error about it (:func:`sample_motion`), for a deformed group the peak and the
    deformation about the isocentre (:func:`sample_deformation`); then picks the landmarks of the ``roi_box_mm``
    cube about the isocentre (:func:`roi_landmarks`) and simulates the CBCT (:func:`simulate_clinical_cbct`).
    """
    spec = ClinicalCBCTSpec() if spec is None else spec
    rng = np.random.default_rng(seed)
    p, dist = sample_isocenter(ct, rng, group.isocenter_distance_mm, min_depth_mm, spec.length_mm)
    params_iso = sample_motion(rng, group.translation_mm, group.max_rotation_deg, group.min_peak_rotation_deg)
    deformation = None
    if group.deformation_mm is not None:
        deformation = sample_deformation(rng, p, float(rng.uniform(*group.deformation_mm)))
    c = ct.center
    m = params_to_matrix(params_iso, p)
    landmarks = roi_landmarks(ct, p, roi_box_mm, num_landmarks, seed=int(rng.integers(1 << 31)))
    noise_seed = int(rng.integers(1 << 31))
    cbct, fov, info = simulate_clinical_cbct(ct, p, params_iso, deformation, spec, noise_seed, device)
    moved = landmarks if deformation is None else deformation.forward(landmarks)
    truth = transform_points(m, moved)
    keep = inside_mask(fov, truth)
    landmarks, truth = landmarks[keep], truth[keep]
    floor = best_rigid_fit(landmarks, truth)[1] if len(landmarks) >= 3 else float("nan")
    record = {
        "case_id": case_id,
        "ct": ct.name,
        "group": group.name,
        "label": group.describe(),
        "seed": int(seed),
        "isocenter": p.tolist(),
        "isocenter_distance_mm": dist,
        "params_isocenter": [float(v) for v in params_iso],
        "center": c.tolist(),
        "params": [float(v) for v in recenter_params(params_iso, p, c)],
        "matrix": m.tolist(),
        "deformation": None if deformation is None else deformation.to_dict(),
        "deformation_peak_mm": None if deformation is None else deformation.peak(),
        "roi": {"center": p.tolist(), "size_mm": [roi_box_mm] * 3},
        "landmarks": landmarks.tolist(),
        "landmarks_moving": truth.tolist(),
        "rigid_floor_mm": floor,
        "cbct": spec.to_dict(),
        "simulation": info,
    }
    return ClinicalCase(cbct, fov, json.loads(json.dumps(record)))  # plain JSON types, as read back from disk


def save_clinical_case(case: ClinicalCase, folder: str | Path, fixed: str | Path | None = None) -> dict[str, Any]:
    """Write ``cbct.nii.gz`` (int16 HU), ``cbct_fov.nii.gz`` and, last (it marks a finished case), ``case.json``
    (the record plus ``fixed``/``moving``/``moving_fov`` paths: a MONAI datalist item) into ``folder``.

    Returns:
        the written record.
    """
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    _write_image(sitk.Cast(case.fov > 0, sitk.sitkUInt8), out / "cbct_fov.nii.gz")
    hu = np.clip(np.rint(sitk.GetArrayFromImage(case.cbct)), -32768, 32767).astype(np.int16)
    img = sitk.GetImageFromArray(hu)
    img.CopyInformation(case.cbct)
    _write_image(img, out / "cbct.nii.gz")
    record = dict(case.record)
    record["moving"] = "cbct.nii.gz"
    record["moving_fov"] = "cbct_fov.nii.gz"
    if fixed is not None:
        record["fixed"] = str(Path(fixed).resolve())
    tmp = out / f".tmp-{os.getpid()}-case.json"
    tmp.write_text(json.dumps(record, indent=1))
    os.replace(tmp, out / "case.json")
    return record


def _write_image(img: sitk.Image, path: Path) -> None:
    """Write atomically (a temporary sibling renamed into place)."""
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    try:
        sitk.WriteImage(img, str(tmp), True)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def load_clinical_case(folder: str | Path) -> ClinicalCase | None:
    """Read a case written by :func:`save_clinical_case` (``None`` if it is not complete)."""
    folder = Path(folder)
    if not (folder / "case.json").is_file():
        return None
    record = json.loads((folder / "case.json").read_text())
    cbct = sitk.Cast(sitk.ReadImage(str(folder / record["moving"])), sitk.sitkFloat32)
    fov = sitk.Cast(sitk.ReadImage(str(folder / record["moving_fov"])), sitk.sitkUInt8)
    return ClinicalCase(cbct, fov, record)
