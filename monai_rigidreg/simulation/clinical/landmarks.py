"""Where a clinical-geometry pair is measured: landmarks in the region of interest (:func:`roi_landmarks`), the best
rigid fit of a deformation at them (:func:`best_rigid_fit`) and the CT points of the TRE (:func:`tre_points`).

Frames and units: :mod:`monai_rigidreg.simulation.clinical`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.geometry import (
    Grid,
    mask_points,
    transform_points,
)
from monai_rigidreg.simulation.clinical.planning_ct import PlanningCT, inside_mask

__all__ = ["roi_landmarks", "best_rigid_fit", "tre_points"]


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
