"""The settings of the clinical-geometry pairs: the CBCT acquisition (:class:`ClinicalCBCTSpec`), the benchmark's groups
(:data:`CLINICAL_GROUPS`) and the seeds of their random streams (:func:`case_seed`).

Frames and units: :mod:`monai_rigidreg.simulation.clinical`.
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from monai_rigidreg.core.geometry import (
    Grid,
)
from monai_rigidreg.simulation.physics import CBCTPhysics

__all__ = ["CLINICAL_PHYSICS", "ClinicalCBCTSpec", "ClinicalGroup", "CLINICAL_GROUPS", "case_seed"]


CLINICAL_PHYSICS = CBCTPhysics(photons=3e4, scatter_to_primary=0.5, beam_hardening=0.02, exposure_reference=6.5)
"""CBCT degradations of the clinical pairs: those of ``benchmarks/accuracy/bench_real_ct.py`` (noisy on-board
imager), with the exposure raised for patients thicker than about 325 mm of water at the isocentre (without it a large
pelvis, whose whole body is in the beam, is photon-starved to a CBCT that shows no anatomy)."""


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
