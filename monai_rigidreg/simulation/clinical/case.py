"""One clinical-geometry pair (:class:`ClinicalCase`): made (:func:`make_clinical_case`), written and read back
(:func:`save_clinical_case`, :func:`load_clinical_case`).

Frames and units: :mod:`monai_rigidreg.simulation.clinical`.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.core.geometry import (
    params_to_matrix,
    recenter_params,
    transform_points,
)
from monai_rigidreg.simulation.clinical.cbct import simulate_clinical_cbct
from monai_rigidreg.simulation.clinical.landmarks import best_rigid_fit, roi_landmarks
from monai_rigidreg.simulation.clinical.planning_ct import PlanningCT, inside_mask
from monai_rigidreg.simulation.clinical.sampling import sample_deformation, sample_isocenter, sample_motion
from monai_rigidreg.simulation.clinical.spec import ClinicalCBCTSpec, ClinicalGroup

__all__ = ["ClinicalCase", "make_clinical_case", "save_clinical_case", "load_clinical_case"]


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
