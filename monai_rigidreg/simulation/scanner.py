"""Scanner geometries of the simulator: a circular cone-beam CT (flat panel) and a fan-beam CT.

Both share one frame: the physical LPS frame of the images, in mm, with the isocentre at the origin and the
rotation axis along ``+z`` (LPS superior). At gantry angle ``beta`` (radians) the source sits at
``S = sod * e``, ``e = (cos beta, sin beta, 0)``; the flat detector is perpendicular to ``e`` at distance ``sdd``
from the source, its centre at ``(sod - sdd) * e``; its column axis ``u`` is ``(-sin beta, cos beta, 0)`` and its
row axis ``v`` is ``+z``. Detector coordinates are in mm *on the detector* (magnified by ``sdd / sod`` with
respect to the isocentre). Projections are stored ``[views, rows (v), columns (u)]`` for the cone beam and
``[views, slices (z), columns (u)]`` for the fan beam.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

__all__ = ["ConeBeamGeometry", "FanBeamGeometry", "detector_half_width"]


def detector_half_width(radius_mm: float, sod: float, sdd: float) -> float:
    """Half-width (mm on the detector) of the shadow of a cylinder of ``radius_mm`` about the rotation axis.

    The extreme rays are tangent to the cylinder: ``u = sdd * r / sqrt(sod^2 - r^2)``.
    """
    if radius_mm >= sod:
        raise ValueError(f"object radius {radius_mm} mm reaches the source (sod={sod} mm)")
    return sdd * radius_mm / math.sqrt(sod**2 - radius_mm**2)


def _check_common(sod: float, sdd: float, num_views: int, arc: float) -> None:
    if not (sod > 0 and sdd > sod):
        raise ValueError(f"need 0 < sod < sdd, got sod={sod} mm, sdd={sdd} mm")
    if int(num_views) < 1:
        raise ValueError(f"num_views must be >= 1, got {num_views}")
    if not (0 < arc <= 360.0):
        raise ValueError(f"arc must be in (0, 360] degrees, got {arc}")


class _CircularOrbit:
    """What both scanners share: the source on a circle of radius ``sod`` about the ``z`` axis, the detector at
    ``sdd`` from it, ``num_views`` views equally spaced over ``arc`` degrees from ``start_angle``."""

    sod: float
    sdd: float
    num_views: int
    arc: float
    start_angle: float

    @property
    def magnification(self) -> float:
        """Magnification at the isocentre, ``sdd / sod``."""
        return self.sdd / self.sod

    def angles(self, device: torch.device | str | None = None) -> torch.Tensor:
        """Gantry angles ``[num_views]`` in radians (float64)."""
        step = math.radians(self.arc) / self.num_views
        return math.radians(self.start_angle) + step * torch.arange(self.num_views, dtype=torch.float64, device=device)

    def radius_seen(self, half_width_mm: float) -> float:
        """Radius (mm) about the axis that a detector reaching ``half_width_mm`` from its centre on both sides sees
        from every view: ``sod sin(atan(half / sdd))`` (0 for no width)."""
        return self.sod * math.sin(math.atan(max(float(half_width_mm), 0.0) / self.sdd))

    def fov_radius(self) -> float:
        """Radius (mm) of the cylinder about the axis seen by every view (the transaxial field of view; with an
        offset detector, the smaller side's)."""
        u = self.u_coords()  # type: ignore[attr-defined]
        return self.radius_seen(float(min(-u[0], u[-1])) + self._u_pitch / 2)


@dataclass(frozen=True)
class ConeBeamGeometry(_CircularOrbit):
    """Circular-orbit cone-beam CT with a flat-panel detector (an on-board imager).

    Args:
        sod: source-to-isocentre (source-object) distance, mm.
        sdd: source-to-detector distance, mm (magnification at the isocentre ``sdd / sod``, 1.5 by default).
        num_views: number of projections, equally spaced over ``arc``.
        arc: gantry arc, degrees (360 = full scan; the reconstruction needs a full scan).
        start_angle: gantry angle of the first view, degrees.
        detector_shape: ``(columns nu, rows nv)``; ``None``: sized by :meth:`fitted` to cover the object.
        pixel_pitch: ``(du, dv)`` detector pixel pitch in mm; ``None``: chosen by :meth:`fitted`.
        detector_offset: ``(u, v)`` shift of the detector centre in mm on the detector (a half-fan offset
            detector has a large ``u`` offset).
    """

    sod: float = 800.0
    sdd: float = 1200.0
    num_views: int = 360
    arc: float = 360.0
    start_angle: float = 0.0
    detector_shape: tuple[int, int] | None = None
    pixel_pitch: tuple[float, float] | None = None
    detector_offset: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        _check_common(self.sod, self.sdd, self.num_views, self.arc)
        if self.detector_shape is not None and min(self.detector_shape) < 2:
            raise ValueError(f"detector_shape must be >= 2 pixels per side, got {self.detector_shape}")
        if self.pixel_pitch is not None and min(self.pixel_pitch) <= 0:
            raise ValueError(f"pixel_pitch must be > 0 mm, got {self.pixel_pitch}")

    @property
    def is_complete(self) -> bool:
        """Whether the detector shape and pitch are set (after :meth:`fitted`)."""
        return self.detector_shape is not None and self.pixel_pitch is not None

    def fitted(self, radius_mm: float, half_height_mm: float, iso_pixel_mm: float, margin: float = 1.05):
        """A copy with the unset detector fields chosen so that the detector covers the object.

        Args:
            radius_mm: radius (mm) of the cylinder about the rotation axis that holds the object.
            half_height_mm: half-height (mm) of the region along ``z`` that the detector must cover.
            iso_pixel_mm: wanted pixel size back-projected to the isocentre, mm (pitch = this times the
                magnification) when ``pixel_pitch`` is unset.
            margin: relative margin added to the covered half-widths.
        """
        pitch = self.pixel_pitch or (iso_pixel_mm * self.magnification,) * 2
        shape = self.detector_shape
        if shape is None:
            half_u = detector_half_width(radius_mm, self.sod, self.sdd) * margin + abs(self.detector_offset[0])
            half_v = self.sdd * half_height_mm / (self.sod - radius_mm) * margin + abs(self.detector_offset[1])
            shape = (2 * math.ceil(half_u / pitch[0]) + 2, 2 * math.ceil(half_v / pitch[1]) + 2)
        return replace(self, detector_shape=tuple(int(s) for s in shape), pixel_pitch=tuple(float(p) for p in pitch))

    def _require_complete(self) -> tuple[int, int, float, float]:
        if not self.is_complete:
            raise ValueError("the detector is not set: give detector_shape and pixel_pitch or call .fitted(...)")
        return (*self.detector_shape, *self.pixel_pitch)  # type: ignore[misc]

    def u_coords(self, device: torch.device | str | None = None) -> torch.Tensor:
        """Column centres ``[nu]`` in mm on the detector (float64)."""
        nu, _, du, _ = self._require_complete()
        return (torch.arange(nu, dtype=torch.float64, device=device) - (nu - 1) / 2) * du + self.detector_offset[0]

    def v_coords(self, device: torch.device | str | None = None) -> torch.Tensor:
        """Row centres ``[nv]`` in mm on the detector (float64)."""
        _, nv, _, dv = self._require_complete()
        return (torch.arange(nv, dtype=torch.float64, device=device) - (nv - 1) / 2) * dv + self.detector_offset[1]

    @property
    def _u_pitch(self) -> float:
        return float(self.pixel_pitch[0])  # type: ignore[index]


@dataclass(frozen=True)
class FanBeamGeometry(_CircularOrbit):
    """Fan-beam CT (the planning CT), simulated slice by slice: one detector row per reconstructed slice.

    Args:
        sod: source-to-isocentre distance, mm.
        sdd: source-to-detector distance, mm.
        num_views: number of projections over ``arc``.
        arc: gantry arc, degrees (360 = full scan; the reconstruction needs a full scan).
        start_angle: gantry angle of the first view, degrees.
        num_detectors: number of detector columns; ``None``: sized by :meth:`fitted`.
        pixel_pitch: detector column pitch in mm on the detector; ``None``: chosen by :meth:`fitted`.
        detector_offset: shift of the detector centre along ``u``, mm on the detector.
    """

    sod: float = 800.0
    sdd: float = 1200.0
    num_views: int = 360
    arc: float = 360.0
    start_angle: float = 0.0
    num_detectors: int | None = None
    pixel_pitch: float | None = None
    detector_offset: float = 0.0

    def __post_init__(self) -> None:
        _check_common(self.sod, self.sdd, self.num_views, self.arc)
        if self.num_detectors is not None and self.num_detectors < 2:
            raise ValueError(f"num_detectors must be >= 2, got {self.num_detectors}")
        if self.pixel_pitch is not None and self.pixel_pitch <= 0:
            raise ValueError(f"pixel_pitch must be > 0 mm, got {self.pixel_pitch}")

    @property
    def is_complete(self) -> bool:
        """Whether the detector size and pitch are set."""
        return self.num_detectors is not None and self.pixel_pitch is not None

    def fitted(self, radius_mm: float, iso_pixel_mm: float, margin: float = 1.05) -> FanBeamGeometry:
        """A copy whose unset detector fields cover a cylinder of ``radius_mm`` with ``iso_pixel_mm`` pixels."""
        pitch = self.pixel_pitch or iso_pixel_mm * self.magnification
        n = self.num_detectors
        if n is None:
            half_u = detector_half_width(radius_mm, self.sod, self.sdd) * margin + abs(self.detector_offset)
            n = 2 * math.ceil(half_u / pitch) + 2
        return replace(self, num_detectors=int(n), pixel_pitch=float(pitch))

    def u_coords(self, device: torch.device | str | None = None) -> torch.Tensor:
        """Column centres ``[nu]`` in mm on the detector (float64)."""
        if not self.is_complete:
            raise ValueError("the detector is not set: give num_detectors and pixel_pitch or call .fitted(...)")
        n = int(self.num_detectors)  # type: ignore[arg-type]
        return (torch.arange(n, dtype=torch.float64, device=device) - (n - 1) / 2) * self.pixel_pitch + (
            self.detector_offset
        )

    @property
    def _u_pitch(self) -> float:
        return float(self.pixel_pitch)  # type: ignore[arg-type]
