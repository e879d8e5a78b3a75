"""What a clinical-geometry pair draws: the isocentre inside the body (:func:`sample_isocenter`), the setup error about
it (:func:`sample_motion`, mm and degrees) and a smooth local deformation (:class:`SmoothDeformation`,
:func:`sample_deformation`), all in LPS mm.

Frames and units: :mod:`monai_rigidreg.simulation.clinical`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from monai_rigidreg.simulation.clinical.planning_ct import PlanningCT, nearest_values

__all__ = ["sample_isocenter", "sample_motion", "SmoothDeformation", "sample_deformation"]


_WENDLAND_SLOPE = 20.0 * 0.25 * 0.75**3
"""Largest ``|psi'(r)|`` of the Wendland bump ``psi(r) = (1 - r)^4 (4 r + 1)`` (at ``r = 1/4``)."""



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
        if nearest_values(ct.depth, p[None], outside=-1.0)[0] >= min_depth_mm:
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
