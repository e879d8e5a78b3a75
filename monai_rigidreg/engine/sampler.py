"""An endless stream of training samples drawn on the fly from a few simulated pairs and real CTs.

Each sample is a CBCT / CT pair on the network grid with its ground truth, drawn fresh from a *source*:

* ``cbct``: a simulated pair (a CBCT reconstructed from simulated cone-beam projections, with its field-of-view
  mask, and the CT it was simulated from, the ground truth ``T0``: ``monai-rigidreg simulate`` datalists and the
  clinical cases of :mod:`monai_rigidreg.simulation.clinical`). A further random motion ``A`` is applied in the
  image domain, so the sample's truth is ``A o T0``.
* ``ct``: a CT alone, moved by a random motion and made to look like a CBCT in the image domain
  (:class:`~monai_rigidreg.transforms.RandCBCTDegradation`).

What a sample varies, beyond the motion: the isocentre (a random point of the body up to ``isocenter_max`` from the
CT centre, or a simulated case's own isocentre), the scanner's field of view (a cylinder about the grid's z axis, cut
after the motion so that it does not move with the anatomy, never wider than what the source CBCT covers, so its
edge cannot give the motion away), the CT's couch (removed from the CT as the registrar removes it, or kept), the
CBCT's couch (the moved CT couch removed, a static treatment couch painted in the scanner frame), image-domain CBCT
degradation, and optionally the anatomy itself: the CT stretched about the isocentre by a random factor per axis
(``anatomy_prob``, ``anatomy_scale``), a body of another size and shape seen by both images, so that a few real CTs
stand for more patients, and then turned about the isocentre (``orientation_prob``, ``orientation_max``), the body
seen in other orientations by both images (the ground truth stays the rigid motion between them). Every sample is
computed with a handful of ``grid_sample`` calls on volumes kept in memory, on the sampler's device (CPU or CUDA).

A sample (dict): ``moving``, ``fixed`` (``[1, *network_size]``, normalized HU), ``context`` (``[1,
*context_size]``: the CT on the context grid, ``context_factor`` times the spacing, same centre), ``moving_fov``
(``[1, *network_size]``), ``rigid_params`` (``{"params": [6], "matrix": [4, 4], "center": [3]}``: the fixed -> moving
transform about the grid centre, mm / degrees, the convention of the whole package) and ``source`` (the source's
name).

>>> from monai_rigidreg.engine.sampler import MotionRange
>>> MotionRange(60.0, 45.0).max_translation
60.0
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch
from torch.utils.data import IterableDataset, get_worker_info

from monai_rigidreg.core.geometry import Grid, matrix_to_params, params_to_matrix
from monai_rigidreg.engine.sources import AIR_HU, PairSource, load_sources, sources_from_cts, sources_from_datalist
from monai_rigidreg.simulation.couch import Couch, couch_fractions
from monai_rigidreg.transforms.cbct import RandCBCTDegradation

# the sources moved to monai_rigidreg.engine.sources; their names stay importable from here
__all__ = ["MotionRange", "PairSource", "RigidPairSampler", "load_sources", "sources_from_datalist",
           "sources_from_cts"]

MIN_VIEW = 0.15
"""Least share of the network grid a sample's field of view must cover (else it is drawn again)."""


@dataclass(frozen=True)
class MotionRange:
    """One band of random rigid motion: translation uniform in a ball shell, angles uniform per axis.

    Args:
        max_translation: largest ``|t|`` (mm); min_translation: smallest.
        max_rotation: largest angle per axis (degrees; every axis moves).
        weight: relative probability of the band.
    """

    max_translation: float
    max_rotation: float
    min_translation: float = 0.0
    weight: float = 1.0

    def draw(self, rng: np.random.Generator) -> np.ndarray:
        """``(tx, ty, tz, rx, ry, rz)`` (mm, degrees)."""
        direction = rng.normal(size=3)
        direction /= max(np.linalg.norm(direction), 1e-12)
        # uniform in the shell's volume
        lo3, hi3 = self.min_translation ** 3, self.max_translation ** 3
        length = float(np.cbrt(rng.uniform(lo3, hi3)))
        angles = rng.uniform(-self.max_rotation, self.max_rotation, size=3)
        return np.concatenate([direction * length, angles])


DEFAULT_MOTIONS: tuple[MotionRange, ...] = (
    MotionRange(10.0, 10.0, weight=0.25),
    MotionRange(40.0, 30.0, weight=0.45),
    MotionRange(60.0, 45.0, min_translation=30.0, weight=0.30),
)
"""The clinic's range of motion: small setup errors, up to 40 mm / 30 degrees, and 30-60 mm / up to 45 degrees."""


class RigidPairSampler(IterableDataset):
    """An endless, seeded stream of training samples (see the module doc).

    Args:
        sources: from :func:`load_sources`.
        network_size, network_spacing: the network grid (voxels, mm).
        context_size, context_factor: the context grid (voxels; spacing ``context_factor`` x ``network_spacing``).
        motions: the motion bands of ``ct`` sources and of simulated pairs without an isocentre.
        case_motions: the extra motion of simulated cases with their own isocentre (their ``T0`` already carries
            the clinical setup error).
        isocenter_jitter: uniform offset (mm per axis) of a simulated case's isocentre.
        kind_weights: ``{"cbct": w, "ct": w}`` probability of each kind of source.
        fov_prob, fov_radius, fov_half_length: the scanner field of view (probability, ranges in mm).
        fixed_couch_removed_prob: probability that the CT's couch is removed (the registrar removes it by default).
        moving_couch_removed_prob, static_couch_prob: probabilities that the CBCT's moved CT couch is removed and
            that a static treatment couch is painted in.
        degradation: keyword arguments of :class:`~monai_rigidreg.transforms.RandCBCTDegradation` for ``ct`` sources
            (its field-of-view cut is replaced by the sampler's); ``cbct_degradation``: for ``cbct`` sources.
        anatomy_prob, anatomy_scale: probability that a sample's anatomy is the CT stretched about the isocentre, and
            the range of the factor drawn per axis (L-R, A-P, S-I); the CT and the CBCT both show the stretched body
            (for ``cbct`` sources the CBCT is stretched about the isocentre's image under ``T0``), the truth is
            unchanged. ``0`` (the default) draws nothing from the stream for it.
        orientation_prob, orientation_max: probability that a sample's anatomy is then turned about the isocentre,
            and the largest angle per axis (degrees, uniform): the anatomy map is ``stretch @ turn`` (the stretched
            body, turned), seen by the CT and the CBCT alike, as if the patient lay turned in both scanners (a kept
            CT couch turns with the body, and for ``cbct`` sources the CBCT, its field-of-view edge included, is
            turned about the isocentre's image under ``T0``); the truth is unchanged. ``0`` (the default) draws
            nothing from the stream for it.
        hu_range: HU window mapped to [0, 1].
        seed: the stream's seed (each DataLoader worker draws its own stream from it).
        device: where samples are computed.
    """

    def __init__(
        self,
        sources: Sequence[PairSource],
        network_size: Sequence[int] = (64, 64, 64),
        network_spacing: Sequence[float] = (2.0, 2.0, 2.0),
        context_size: Sequence[int] | None = None,
        context_factor: int = 2,
        motions: Sequence[MotionRange] = DEFAULT_MOTIONS,
        case_motions: Sequence[MotionRange] = (MotionRange(8.0, 8.0),),
        isocenter_jitter: float = 10.0,
        kind_weights: Mapping[str, float] | None = None,
        fov_prob: float = 0.8,
        fov_radius: Sequence[float] = (55.0, 130.0),
        fov_half_length: Sequence[float] = (55.0, 130.0),
        fixed_couch_removed_prob: float = 0.8,
        moving_couch_removed_prob: float = 0.6,
        static_couch_prob: float = 0.5,
        degradation: Mapping[str, Any] | None = None,
        cbct_degradation: Mapping[str, Any] | None = None,
        anatomy_prob: float = 0.0,
        anatomy_scale: Sequence[float] = (0.85, 1.15),
        orientation_prob: float = 0.0,
        orientation_max: float = 15.0,
        hu_range: Sequence[float] = (-1000.0, 2000.0),
        seed: int = 0,
        device: str | torch.device = "cpu",
    ) -> None:
        super().__init__()
        if not sources:
            raise ValueError("no sources")
        self.device = torch.device(device)
        self.sources = [s.to(self.device) for s in sources]
        self.network_size = tuple(int(s) for s in network_size)
        self.network_spacing = tuple(float(s) for s in network_spacing)
        self.context_size = self.network_size if context_size is None else tuple(int(s) for s in context_size)
        self.context_spacing = tuple(s * int(context_factor) for s in self.network_spacing)
        self.motions = tuple(motions)
        self.case_motions = tuple(case_motions)
        self.isocenter_jitter = float(isocenter_jitter)
        weights = {"cbct": 0.7, "ct": 0.3} if kind_weights is None else dict(kind_weights)
        kinds = sorted({s.kind for s in self.sources})
        self._kinds = kinds
        self._kind_p = np.array([float(weights.get(k, 0.0)) for k in kinds])
        if self._kind_p.sum() <= 0:
            raise ValueError(f"kind_weights {weights} give no weight to the sources' kinds {kinds}")
        self._kind_p /= self._kind_p.sum()
        self.fov_prob = float(fov_prob)
        self.fov_radius = tuple(float(v) for v in fov_radius)
        self.fov_half_length = tuple(float(v) for v in fov_half_length)
        self.fixed_couch_removed_prob = float(fixed_couch_removed_prob)
        self.moving_couch_removed_prob = float(moving_couch_removed_prob)
        self.static_couch_prob = float(static_couch_prob)
        base = {"fov_prob": 0.0}
        self.degrade_ct = RandCBCTDegradation(**{**base, **(degradation or {})})
        light = {"blur_prob": 0.5, "blur_sigma": (0.2, 0.8), "downsample_prob": 0.0, "scatter_prob": 0.5,
                 "scatter_amplitude": (0.0, 0.04), "cupping_prob": 0.5, "cupping_depth": (0.0, 0.04),
                 "streak_prob": 0.1, "ring_prob": 0.1, "noise_prob": 0.7, "noise_std": (0.0, 25.0), "hu_prob": 0.8}
        self.degrade_cbct = RandCBCTDegradation(**{**base, **light, **(cbct_degradation or {})})
        self.anatomy_prob = float(anatomy_prob)
        if not 0.0 <= self.anatomy_prob <= 1.0:
            raise ValueError(f"anatomy_prob must be in [0, 1], got {anatomy_prob}")
        self.anatomy_scale = (float(anatomy_scale[0]), float(anatomy_scale[1]))
        if not 0.0 < self.anatomy_scale[0] <= self.anatomy_scale[1]:
            raise ValueError(f"anatomy_scale must be (low, high) with 0 < low <= high, got {anatomy_scale}")
        self.orientation_prob = float(orientation_prob)
        self.orientation_max = float(orientation_max)
        if not 0.0 <= self.orientation_prob <= 1.0 or not 0.0 <= self.orientation_max <= 180.0:
            raise ValueError(f"orientation_prob must be in [0, 1] and orientation_max in [0, 180] degrees, got "
                             f"{orientation_prob}, {orientation_max}")
        self.hu_range = (float(hu_range[0]), float(hu_range[1]))
        self.seed = int(seed)
        self._epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """A new stream per epoch (called by the training loop; workers read it when their iterator starts)."""
        self._epoch = int(epoch)

    # -----------------------------------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[dict[str, Any]]:
        info = get_worker_info()
        worker = 0 if info is None else info.id
        rng = np.random.default_rng([self.seed, self._epoch, worker])
        self.degrade_ct.set_random_state(seed=int(rng.integers(1 << 31)))
        self.degrade_cbct.set_random_state(seed=int(rng.integers(1 << 31)))
        while True:
            yield self.draw(rng)

    def draw(self, rng: np.random.Generator, tries: int = 10) -> dict[str, Any]:
        """One sample (see the module doc) from the random generator ``rng``: drawn again (up to ``tries``
        times) while less than :data:`MIN_VIEW` of the grid is in the field of view."""
        for _ in range(max(1, int(tries)) - 1):
            sample = self._draw(rng)
            if float(sample["moving_fov"].mean()) >= MIN_VIEW:
                return sample
        return self._draw(rng)

    def _draw(self, rng: np.random.Generator) -> dict[str, Any]:
        kind = self._kinds[int(rng.choice(len(self._kinds), p=self._kind_p))]
        pool = [s for s in self.sources if s.kind == kind]
        src = pool[int(rng.integers(len(pool)))]
        if src.isocenter is not None:
            g = src.isocenter + rng.uniform(-self.isocenter_jitter, self.isocenter_jitter, 3)
            bands = self.case_motions
        else:
            g = src.body_points[int(rng.integers(len(src.body_points)))]
            bands = self.motions
        p = np.array([b.weight for b in bands], dtype=np.float64)
        band = bands[int(rng.choice(len(bands), p=p / p.sum()))]
        a = params_to_matrix(band.draw(rng), g)  # the extra motion about the isocentre
        t1 = a @ src.matrix  # fixed -> moving of the sample
        grid = Grid.centered(self.network_size, self.network_spacing, g)
        ctx_grid = Grid.centered(self.context_size, self.context_spacing, g)
        anatomy = self._stretch(rng, g) @ self._orientation(rng, g)  # the sample shows CT(anatomy @ x) at x
        fixed = src.fixed.sample(grid, anatomy, AIR_HU)
        context = src.context.sample(ctx_grid, anatomy, AIR_HU)
        if rng.random() < self.fixed_couch_removed_prob:
            fixed = torch.where(src.body.sample(grid, anatomy) > 0.5, fixed, torch.full_like(fixed, AIR_HU))
            context = torch.where(src.body.sample(ctx_grid, anatomy) > 0.5, context,
                                  torch.full_like(context, AIR_HU))
        # a CBCT point y shows the anatomy of the CT point anatomy @ t1^-1 @ y, the source CBCT's point T0 @ that
        to_ct = anatomy @ np.linalg.inv(t1)
        if src.kind == "cbct":
            to_cbct = src.matrix @ to_ct  # T0 @ A^-1 without a stretch or a turn
            moving = src.moving.sample(grid, to_cbct, AIR_HU)
            covered = _inside(src.moving.grid, grid, to_cbct, moving.device)
            if src.moving_fov is not None:
                covered &= src.moving_fov.sample(grid, to_cbct) > 0.5
        else:
            moving = src.fixed.sample(grid, to_ct, AIR_HU)
            covered = _inside(src.fixed.grid, grid, to_ct, moving.device)
        moved_body = src.body.sample(grid, to_ct) > 0.5
        if rng.random() < self.moving_couch_removed_prob:
            moving = torch.where(moved_body, moving, torch.full_like(moving, AIR_HU))
        if rng.random() < self.static_couch_prob:
            moving = self._paint_couch(moving, moved_body, grid, rng)
        fov = self._field_of_view(covered, grid, rng)
        moving = self._degrade(moving, grid, src.kind)
        moving = torch.where(fov, moving, torch.full_like(moving, AIR_HU))
        lo, hi = self.hu_range
        norm = [((v - lo) / (hi - lo)).clamp(0.0, 1.0) for v in (moving, fixed, context)]
        params = matrix_to_params(t1, g)
        return {
            "moving": norm[0].float(), "fixed": norm[1].float(), "context": norm[2].float(),
            "moving_fov": fov.float(),
            "rigid_params": {"params": torch.as_tensor(params, dtype=torch.float32),
                             "matrix": torch.as_tensor(t1, dtype=torch.float64),
                             "center": torch.as_tensor(g, dtype=torch.float64)},
            "source": src.name,
        }

    # -----------------------------------------------------------------------------------------------------------
    def _stretch(self, rng: np.random.Generator, center: np.ndarray) -> np.ndarray:
        """4x4: a scaling per axis about ``center`` (LPS mm) with probability ``anatomy_prob``, else the identity."""
        out = np.eye(4)
        if self.anatomy_prob > 0.0 and rng.random() < self.anatomy_prob:
            factors = rng.uniform(*self.anatomy_scale, size=3)
            out[:3, :3] = np.diag(1.0 / factors)  # the anatomy grows by `factors`: CT points shrink towards g
            out[:3, 3] = center - out[:3, :3] @ center
        return out

    def _orientation(self, rng: np.random.Generator, center: np.ndarray) -> np.ndarray:
        """4x4: a rotation about ``center`` (LPS mm) with probability ``orientation_prob``, else the identity."""
        if self.orientation_prob > 0.0 and rng.random() < self.orientation_prob:
            angles = rng.uniform(-self.orientation_max, self.orientation_max, size=3)
            return params_to_matrix([0.0, 0.0, 0.0, *angles], center)
        return np.eye(4)

    def _field_of_view(self, covered: torch.Tensor, grid: Grid, rng: np.random.Generator) -> torch.Tensor:
        """The scanner's field of view on the grid: a cylinder about the grid's z axis cut by a slab along z, never
        reaching voxels the source does not cover (so the source's own edge stays out of view). The drawn
        half-length is shortened first to the nearest uncovered voxel inside the drawn radius (a CT shorter than
        the scan), then the radius to the nearest uncovered voxel inside that slab."""
        x, y, z = _axes(grid, covered.device)
        shape = covered.shape[1:]
        rr = (x[:, None, None] ** 2 + y[None, :, None] ** 2).sqrt().expand(shape)
        zz = z.abs()[None, None, :].expand(shape)
        outside = ~covered[0]
        radius = rng.uniform(*self.fov_radius) if rng.random() < self.fov_prob else math.inf
        half = rng.uniform(*self.fov_half_length) if rng.random() < self.fov_prob else math.inf
        limit = outside & (rr <= radius)
        if bool(limit.any()):
            half = min(half, float(zz[limit].min()) - 0.5 * grid.spacing[2])
        limit = outside & (zz <= half)
        if bool(limit.any()):
            radius = min(radius, float(rr[limit].min()) - 0.5 * min(grid.spacing[:2]))
        return ((rr <= radius) & (zz <= half))[None]

    def _paint_couch(self, moving: torch.Tensor, body: torch.Tensor, grid: Grid, rng: np.random.Generator
                     ) -> torch.Tensor:
        """A static treatment couch just posterior to the (moved) body, in the scanner frame of the grid."""
        x, y, _ = _axes(grid, moving.device)
        yy = y[None, :, None].expand(body.shape[1:]) + float(grid.center()[1])
        in_body = body[0]
        if not bool(in_body.any()):
            return moving
        top = float(yy[in_body].max()) + float(rng.uniform(0.0, 6.0))
        couch = Couch(top_y_mm=top, center_x_mm=float(grid.center()[0] + rng.uniform(-20, 20)),
                      width_mm=float(rng.uniform(450, 550)),
                      curvature_radius_mm=None if rng.random() < 0.5 else float(rng.uniform(1000, 3000)),
                      core_hu=float(rng.uniform(-900, -700)), shell_hu=float(rng.uniform(200, 800)),
                      rail_width_mm=0.0 if rng.random() < 0.5 else 20.0)
        ref = sitk.Image([int(self.network_size[0]), int(self.network_size[1]), 1], sitk.sitkFloat32)
        ref.SetSpacing(self.network_spacing)
        corner = grid.index_to_physical()[:3, 3]
        ref.SetOrigin([float(corner[0]), float(corner[1]), 0.0])
        fr = couch_fractions(ref, couch)  # [1, y, x] arrays
        hu = {"shell": couch.shell_hu, "core": couch.core_hu, "rail": couch.rail_hu}
        total = sum(np.broadcast_to(fr[k], (1, ref.GetSize()[1], ref.GetSize()[0])) for k in hu)
        paint = sum(np.broadcast_to(fr[k], (1, ref.GetSize()[1], ref.GetSize()[0])) * v for k, v in hu.items())
        f, v = (torch.as_tensor(np.ascontiguousarray(a[0].T), dtype=moving.dtype,
                                device=moving.device)[None, :, :, None]
                for a in (total, paint))  # [y, x] -> [1, x, y, 1]
        return moving * (1 - f) + v

    def _degrade(self, moving: torch.Tensor, grid: Grid, kind: str) -> torch.Tensor:
        from monai.data import MetaTensor

        deg = self.degrade_ct if kind == "ct" else self.degrade_cbct
        img = MetaTensor(moving, affine=torch.as_tensor(grid.affine("RAS")))
        return deg(img).as_tensor()


def _inside(source: Grid, out_grid: Grid, matrix: np.ndarray, device: torch.device) -> torch.Tensor:
    """``[1, *out_grid.size]`` bool: the points ``matrix @ y`` of ``out_grid`` that fall inside ``source``'s voxels."""
    m = source.physical_to_index() @ np.asarray(matrix, dtype=np.float64) @ out_grid.index_to_physical()
    m = torch.as_tensor(m, dtype=torch.float32, device=device)
    axes = [torch.arange(n, device=device, dtype=torch.float32) for n in out_grid.size]
    idx = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)  # [X, Y, Z, 3]
    src = idx @ m[:3, :3].T + m[:3, 3]
    size = torch.as_tensor(source.size, dtype=torch.float32, device=device)
    return ((src >= -0.5) & (src <= size - 0.5)).all(-1)[None]


def _axes(grid: Grid, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-axis voxel positions of an axis-aligned grid relative to its centre (mm)."""
    return tuple(((torch.arange(n, device=device, dtype=torch.float32) - (n - 1) / 2) * s)
                 for n, s in zip(grid.size, grid.spacing))
