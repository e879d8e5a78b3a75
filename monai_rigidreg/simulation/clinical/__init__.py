"""CT/CBCT pairs with clinical geometry from a real planning CT.

The paper protocol (:mod:`.protocols`, :func:`~monai_rigidreg.simulation.simulate_case`) simulates both images
about the CT centre. A physicist's pairs look different: the CBCT is centred on the treatment isocentre somewhere
inside a larger planning CT, the setup error (couch and patient) reaches several centimetres and tens of degrees,
the anatomy may have changed between the scans, and the match is judged on the target region. This module builds
such pairs from a real CT; ``benchmarks/accuracy/bench_clinical_geometry.py`` registers them.

Frames (LPS mm throughout, one physical frame shared by both images, as a registration system sees them):

* **CT frame.** The planning CT is the real CT itself, on its own grid (the fixed image; :func:`load_planning_ct`
  resamples only very large CTs). ``c`` is its grid centre (:meth:`~monai_rigidreg.core.geometry.Grid.center`).
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

Modules: :mod:`.spec` (the CBCT acquisition, the groups, the seeds), :mod:`.planning_ct` (the real CT, its body),
:mod:`.sampling` (isocentre, setup error, deformation), :mod:`.landmarks` (where the error is measured), :mod:`.cbct`
(the CBCT of one pair) and :mod:`.case` (one pair made, written and read back).
"""

from __future__ import annotations

import warnings
from typing import Any

from monai_rigidreg.simulation.clinical.case import (
    ClinicalCase,
    load_clinical_case,
    make_clinical_case,
    save_clinical_case,
)
from monai_rigidreg.simulation.clinical.cbct import moved_object, simulate_clinical_cbct
from monai_rigidreg.simulation.clinical.landmarks import best_rigid_fit, roi_landmarks, tre_points
from monai_rigidreg.simulation.clinical.planning_ct import (
    PlanningCT,
    inside_mask,
    load_planning_ct,
    nearest_values,
    planning_ct_body,
)
from monai_rigidreg.simulation.clinical.sampling import (
    SmoothDeformation,
    sample_deformation,
    sample_isocenter,
    sample_motion,
)
from monai_rigidreg.simulation.clinical.spec import (
    CLINICAL_GROUPS,
    CLINICAL_PHYSICS,
    ClinicalCBCTSpec,
    ClinicalGroup,
    case_seed,
)

__all__ = [
    "CLINICAL_GROUPS",
    "CLINICAL_PHYSICS",
    "ClinicalCBCTSpec",
    "ClinicalCase",
    "ClinicalGroup",
    "PlanningCT",
    "SmoothDeformation",
    "best_rigid_fit",
    "case_seed",
    "inside_mask",
    "load_clinical_case",
    "load_planning_ct",
    "make_clinical_case",
    "moved_object",
    "nearest_values",
    "planning_ct_body",
    "roi_landmarks",
    "sample_deformation",
    "sample_isocenter",
    "sample_motion",
    "save_clinical_case",
    "simulate_clinical_cbct",
    "tre_points",
]

_RENAMED = {"body_mask": "planning_ct_body"}
"""Old name -> new name: ``body_mask`` said the same as :func:`monai_rigidreg.registration.body.body_mask`, another
algorithm (this one: the pair generation's body of a planning CT)."""


def __getattr__(name: str) -> Any:
    if name in _RENAMED:
        warnings.warn(f"{__name__}.{name} is now {_RENAMED[name]}; the old name works until monai-rigidreg 0.6",
                      DeprecationWarning, stacklevel=2)
        return globals()[_RENAMED[name]]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
