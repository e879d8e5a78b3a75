"""The planning CT of a clinical-geometry pair (:class:`PlanningCT`): the real CT on its own grid, its body
(:func:`planning_ct_body`) and the depth inside it, in LPS mm.

Frames and units: :mod:`monai_rigidreg.simulation.clinical`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.core.geometry import (
    Grid,
    transform_points,
)
from monai_rigidreg.simulation.phantoms import hu_to_mu, load_ct

__all__ = ["planning_ct_body", "PlanningCT", "load_planning_ct", "nearest_values", "inside_mask"]


def planning_ct_body(ct: sitk.Image, threshold_hu: float = -400.0, opening_mm: float = 4.0) -> sitk.Image:
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
        body: uint8 body mask (:func:`planning_ct_body`) on the same grid.
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
    body = planning_ct_body(img)
    depth = sitk.SignedMaurerDistanceMap(body, insideIsPositive=True, squaredDistance=False, useImageSpacing=True)
    return PlanningCT(img, body, sitk.Cast(depth, sitk.sitkFloat32), name, path, resampled_from)


def nearest_values(image: sitk.Image, points: np.ndarray, outside: float = 0.0) -> np.ndarray:
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
    return nearest_values(mask, points) > 0
