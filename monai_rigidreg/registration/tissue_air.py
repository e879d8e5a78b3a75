"""CT tissue the estimate puts on CBCT air: a failure signal that does not depend on an image optimum.

:func:`tissue_on_air` counts the CT's tissue in the CBCT's field of view that lands on CBCT air. Counted on every air
voxel (``tissue_on_air``, :data:`TISSUE_ON_AIR_LIMIT`) it also sees the body outline that moved between the scans
(deformation, breathing) and a fraction of a voxel of blur; counted only on air at least :data:`DEEP_AIR_MM` from
anything that is not air in the CBCT (``tissue_on_air_deep``, :data:`DEEP_LIMIT`, the rule's signal since 0.5.1) it
sees tissue placed well inside air, which a right pose does not leave. The frames: both volumes on one grid in the CT
frame, the CBCT resampled through the estimate.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from monai_rigidreg.core.image_ops import erode

__all__ = ["TISSUE_HU", "AIR_HU", "TISSUE_ON_AIR_LIMIT", "DEEP_AIR_MM", "DEEP_LIMIT", "tissue_on_air",
           "deep_air_radius"]

TISSUE_ON_AIR_LIMIT = 0.06
"""Share of the CT's tissue in view put on CBCT air (:func:`tissue_on_air`, every air voxel) that scored 0.5 in the
rule score until bundle 0.5.0 (now :data:`DEEP_LIMIT` on deep air does), and the unit of the calibration's
``tissue_on_air`` feature. Measured on the 60 clinical-geometry pairs of two seeds, 1500 and 2500 (``python -m
benchmarks.confidence.bench_confidence_clinical --spoil``; ``docs/results.md``, "Confidence"): true poses at most
0.041 (deformed anatomy included; 0.007 without deformation on the first set, 0.021 on the second), the network's
gross failures 0.151 (thorax, 128 mm), 0.063, 0.058 and 0.032; poses spoiled by 40 mm or 45 degrees a median of
0.11-0.20, by 20 mm or 20 degrees 0.03-0.08, but as little as 0.000-0.005 for a shift along a body that looks alike
along it (which the edge and swap tests must catch)."""

DEEP_AIR_MM = 4.0
"""``tissue_on_air_deep`` counts CBCT air voxels only where the whole box of this half-width (mm) around them is air
(:func:`deep_air_radius`): two voxels of the network's 2 mm grid."""
DEEP_LIMIT = 0.015
"""Share of the CT's tissue in view put on deep CBCT air (:data:`DEEP_AIR_MM`) that scores 0.5 in
:func:`~monai_rigidreg.registration.confidence.confidence_score`. On the 286 cases of bundle 0.5.0's calibration
(``python -m benchmarks.confidence.bench_confidence_calibration``, ``docs/trust.md``) every right result of the
paper, clinical-geometry and partial-overlap sets scored 0.000 (the whole-air share up to 0.119 on deformed
clinical pairs, three false alarms at its 0.06); the CBCTs with a quarter of their slices blank 0.18-0.22; other
patients, regions and a head/feet swap 0.018-0.029 where the whole-air share read 0.077-0.198. Chosen on those
cases (not held out)."""

TISSUE_HU = 0.0
"""CT voxels above this (HU) are soft tissue or bone for :func:`tissue_on_air`. Fat (about -100 HU) is left out: a
CBCT's scatter and beam-hardening shading pull it towards the air level, and with -200 HU here the true pose of a
thorax pair tilted 37 degrees (seed 2500, large_002) scored 0.058 (``benchmarks/confidence/bench_confidence_clinical.py
--spoil`` run with this constant at -200)."""
AIR_HU = -500.0
"""CBCT voxels below this (HU) read as air or lung for :func:`tissue_on_air`. At -700 a CBCT's lung, lifted by
scatter, no longer reads as air: the 128 mm thorax failure (seed 1500, large_004) scored 0.014 instead of 0.151 (the
same benchmark run with this constant at -700)."""

def tissue_on_air(
    fixed: torch.Tensor, moved: torch.Tensor, fov: torch.Tensor, hu_range: tuple[float, float] = (-1000.0, 2000.0),
    air_radius: Sequence[int] | None = None,
) -> float:
    """Fraction of the CT's tissue in the field of view that the estimate maps onto air in the CBCT.

    Args:
        fixed: ``[x, y, z]`` CT on the network grid, HU normalized from ``hu_range`` to ``[0, 1]`` (with the couch
            excluded, its voxels outside the body are air already).
        moved: ``[x, y, z]`` CBCT resampled through the estimate onto the same grid, normalized alike.
        fov: ``[x, y, z]`` the CBCT's field of view on the grid (> 0.5 inside).
        hu_range: the normalization window.
        air_radius: count only CBCT air whose box of these half-widths (voxels per axis) is all air
            (:func:`deep_air_radius`); ``None``: every air voxel.

    Returns the share of the voxels inside ``fov`` with CT above :data:`TISSUE_HU` whose CBCT reads below
    :data:`AIR_HU` (NaN when fewer than 100 tissue voxels are in view). A gross failure puts CT tissue on the air
    around the patient, on lung or on gas; a right pose leaves only the anatomy that changed between the scans (a
    few percent on the deformed clinical-geometry pairs, ``benchmarks/confidence/bench_confidence_clinical.py``). Unlike
    the edge test it does not depend on the estimate being near an optimum, only on where tissue and air lie.

    It looks at the whole field of view, also with a match region (``--roi``): its calibration
    (:data:`TISSUE_ON_AIR_LIMIT`) includes the deformed pairs registered with their ROI box. It expects the couch
    removed from ``fixed`` (the registrar's default): with ``keep_couch`` the CT's couch counts as tissue wherever the
    CBCT has none, which raises the signal by the couch's share of the tissue in view.
    """
    lo, hi = hu_range
    tissue = (fixed > (TISSUE_HU - lo) / (hi - lo)) & (fov > 0.5)
    n = int(tissue.sum())
    if n < 100:
        return float("nan")
    air = moved < (AIR_HU - lo) / (hi - lo)
    if air_radius is not None:
        air = erode(air.to(torch.float32)[None, None], air_radius)[0, 0] > 0.5
    return float((tissue & air).sum()) / n


def deep_air_radius(spacing: Sequence[float], depth_mm: float = DEEP_AIR_MM) -> list[int]:
    """The ``air_radius`` of :func:`tissue_on_air` for a grid of ``spacing`` (mm): ``depth_mm`` in voxels, at least
    one per axis.

    >>> deep_air_radius((2.0, 2.0, 2.0))
    [2, 2, 2]
    """
    return [max(1, round(depth_mm / float(s))) for s in spacing]
