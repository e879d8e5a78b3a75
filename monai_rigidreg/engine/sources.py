"""What training samples are drawn from: simulated pairs (``cbct`` sources) and real CTs (``ct`` sources) kept in
memory on the grids the sampler reads (:class:`~monai_rigidreg.engine.RigidPairSampler`).

A source's CT is kept twice, smoothed for the network grid and for the context grid, with its body mask and the body
points an isocentre may be drawn from; a ``cbct`` source adds its CBCT, field-of-view mask and ground truth ``T0``.

>>> from monai_rigidreg.engine.sources import AIR_HU
>>> AIR_HU
-1000.0
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.core.geometry import Grid, params_to_matrix
from monai_rigidreg.core.warp import warp_volume

__all__ = ["AIR_HU", "PairSource", "load_sources", "sources_from_cts", "sources_from_datalist"]

AIR_HU = -1000.0
"""The HU of air: what a sample shows outside a volume, and the floor CTs are clipped to."""


@dataclass
class _Volume:
    """A volume in memory: ``[1, 1, x, y, z]`` float32 (HU or a mask) on ``grid``."""

    data: torch.Tensor
    grid: Grid

    @classmethod
    def from_sitk(cls, image: sitk.Image, smooth_to_mm: float | None = None) -> _Volume:
        img = sitk.Cast(image, sitk.sitkFloat32)
        if smooth_to_mm is not None:
            sigma = [max(0.0, 0.5 * (smooth_to_mm - s)) for s in img.GetSpacing()]
            if max(sigma) > 0.05:
                img = sitk.SmoothingRecursiveGaussian(img, [max(s, 1e-3) for s in sigma])
        arr = torch.from_numpy(sitk.GetArrayFromImage(img)).permute(2, 1, 0).contiguous()
        return cls(arr[None, None], Grid.from_sitk(img))

    def to(self, device: torch.device) -> _Volume:
        return _Volume(self.data.to(device), self.grid)

    def sample(self, out_grid: Grid, matrix: np.ndarray, fill: float = 0.0, mode: str = "bilinear") -> torch.Tensor:
        """``[1, *out_grid.size]`` values at ``matrix @ y`` for every point ``y`` of ``out_grid`` (``fill`` outside)."""
        m = torch.as_tensor(matrix, dtype=torch.float64, device=self.data.device)[None]
        if fill == 0.0:
            return warp_volume(self.data, m, out_grid, self.grid, mode=mode)[0]
        return warp_volume(self.data - fill, m, out_grid, self.grid, mode=mode)[0] + fill


@dataclass
class PairSource:
    """What samples are drawn from (see the module doc).

    Attributes:
        name: a label (the CT's name for real CTs).
        kind: ``"cbct"`` or ``"ct"``.
        fixed: the CT, smoothed for the network grid; context: the CT smoothed for the context grid.
        body: the CT's body mask (float 0/1; the couch is outside it).
        moving, moving_fov: the simulated CBCT and its field of view (``cbct`` sources).
        matrix: ``T0`` (4x4, fixed -> moving, LPS mm; the identity for ``ct`` sources).
        isocenter: the simulated case's isocentre (CT frame), or ``None`` (drawn from ``body_points``).
        body_points: ``[M, 3]`` candidate isocentres (LPS mm): body voxels up to the sampler's reach from the centre.
        center: the CT's grid centre (LPS mm).
    """

    name: str
    kind: str
    fixed: _Volume
    context: _Volume
    body: _Volume
    moving: _Volume | None = None
    moving_fov: _Volume | None = None
    matrix: np.ndarray = field(default_factory=lambda: np.eye(4))
    isocenter: np.ndarray | None = None
    body_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def to(self, device: torch.device) -> PairSource:
        moved = {k: getattr(self, k).to(device) for k in ("fixed", "context", "body")}
        for k in ("moving", "moving_fov"):
            moved[k] = None if getattr(self, k) is None else getattr(self, k).to(device)
        return PairSource(self.name, self.kind, matrix=self.matrix, isocenter=self.isocenter,
                          body_points=self.body_points, center=self.center, **moved)


def _body_mask(ct: sitk.Image) -> sitk.Image:
    from monai_rigidreg.simulation.clinical import planning_ct_body as body_mask

    return body_mask(ct)


def _body_points(body: sitk.Image, reach_mm: float, min_depth_mm: float = 10.0, stride: int = 2) -> np.ndarray:
    """Body voxel centres (LPS mm, every ``stride``-th voxel per axis) at least ``min_depth_mm`` inside the body and
    within ``reach_mm`` of the grid centre."""
    depth = sitk.SignedMaurerDistanceMap(body, insideIsPositive=True, squaredDistance=False, useImageSpacing=True)
    arr = sitk.GetArrayFromImage(depth)[::stride, ::stride, ::stride]  # [z, y, x]
    kk, jj, ii = np.nonzero(arr >= min_depth_mm)
    index = np.stack([ii, jj, kk], 1).astype(np.float64) * stride
    grid = Grid.from_sitk(body)
    to_mm = grid.index_to_physical()
    pts = index @ to_mm[:3, :3].T + to_mm[:3, 3]
    keep = np.linalg.norm(pts - grid.center(), axis=1) <= reach_mm
    return pts[keep] if keep.any() else grid.center()[None]


def _read(path: str | Path) -> sitk.Image:
    return sitk.ReadImage(str(path))


def _ct_volumes(ct: sitk.Image, network_spacing: float, context_spacing: float
                ) -> tuple[_Volume, _Volume, _Volume, sitk.Image]:
    ct = sitk.Cast(ct, sitk.sitkFloat32)
    ct = sitk.Threshold(ct, lower=AIR_HU, upper=1e9, outsideValue=AIR_HU)
    body = _body_mask(ct)
    return (_Volume.from_sitk(ct, network_spacing), _Volume.from_sitk(ct, context_spacing),
            _Volume.from_sitk(body), body)


def sources_from_datalist(path: str | Path, network_spacing: float = 2.0, context_spacing: float = 4.0,
                          isocenter_max: float = 100.0, key: str = "training") -> list[PairSource]:
    """``cbct`` sources from a datalist of simulated pairs (``fixed``, ``moving``, ``moving_fov`` paths relative to
    the datalist, and ``matrix`` or ``params``/``center``; an ``isocenter`` where the case has one)."""
    path = Path(path)
    items = json.loads(path.read_text())[key]
    cache: dict[str, tuple] = {}
    out = []
    for item in items:
        fixed_path = str((path.parent / item["fixed"]).resolve())
        if fixed_path not in cache:
            ct = _read(fixed_path)
            fixed, context, body, body_img = _ct_volumes(ct, network_spacing, context_spacing)
            cache[fixed_path] = (fixed, context, body, _body_points(body_img, isocenter_max),
                                 Grid.from_sitk(ct).center())
        fixed, context, body, points, center = cache[fixed_path]
        if "matrix" in item and item["matrix"] is not None:
            matrix = np.asarray(item["matrix"], dtype=np.float64)
        else:
            matrix = params_to_matrix(item["params"], item.get("center"))
        moving = _Volume.from_sitk(_read(path.parent / item["moving"]))
        fov = _Volume.from_sitk(_read(path.parent / item["moving_fov"])) if item.get("moving_fov") else None
        iso = item.get("isocenter")
        out.append(PairSource(
            name=str(item.get("ct") or Path(fixed_path).name.split(".")[0]), kind="cbct", fixed=fixed,
            context=context, body=body, moving=moving, moving_fov=fov, matrix=matrix,
            isocenter=None if iso is None else np.asarray(iso, dtype=np.float64), body_points=points,
            center=center))
    return out


def sources_from_cts(paths: Sequence[str | Path], network_spacing: float = 2.0, context_spacing: float = 4.0,
                     isocenter_max: float = 100.0) -> list[PairSource]:
    """``ct`` sources from CT files (HU)."""
    out = []
    for p in paths:
        ct = _read(p)
        fixed, context, body, body_img = _ct_volumes(ct, network_spacing, context_spacing)
        out.append(PairSource(name=Path(p).name.split(".")[0], kind="ct", fixed=fixed, context=context, body=body,
                              body_points=_body_points(body_img, isocenter_max), center=Grid.from_sitk(ct).center()))
    return out


def load_sources(datalists: Sequence[str | Path] = (), cts: Sequence[str | Path] = (), network_spacing: float = 2.0,
                 context_spacing: float = 4.0, isocenter_max: float = 100.0) -> list[PairSource]:
    """Every source of the datalists (``cbct``) and CT files (``ct``)."""
    out: list[PairSource] = []
    for d in datalists:
        out += sources_from_datalist(d, network_spacing, context_spacing, isocenter_max)
    out += sources_from_cts(cts, network_spacing, context_spacing, isocenter_max)
    if not out:
        raise ValueError("no training sources: give datalists and/or CT files")
    return out
