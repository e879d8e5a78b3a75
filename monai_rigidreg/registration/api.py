"""The registration function, :func:`register`: one call from two images (or paths) to a
:class:`~monai_rigidreg.registration.result.RegistrationResult`, with the shipped network loaded once per bundle and
device and kept for later calls.

>>> import SimpleITK as sitk
>>> from monai_rigidreg.simulation.toy import blob_ct
>>> ct = blob_ct()  # a CT-like test object in HU
>>> cbct = sitk.Resample(ct, ct, sitk.TranslationTransform(3, (-4.0, 0.0, 0.0)), sitk.sitkLinear, -1000.0)
>>> result = register(ct, cbct, device="cpu")
>>> [int(round(v)) for v in result.params]  # tx ty tz (mm) rx ry rz (degrees), CT -> CBCT about the CT centre
[4, 0, 0, 0, 0, 0]
>>> result.transform.GetName(), result.flagged
('Euler3DTransform', False)
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import SimpleITK as sitk
import torch
from torch import nn

from monai_rigidreg.core.device import resolve_device
from monai_rigidreg.export.provenance import registration_provenance
from monai_rigidreg.export.record import complete_record
from monai_rigidreg.io.dicom_series import check_distinct_inputs
from monai_rigidreg.io.volumes import as_image
from monai_rigidreg.registration.inputs import check_same_patient
from monai_rigidreg.registration.match_region import RoiLike
from monai_rigidreg.registration.registrar import RigidRegistrar
from monai_rigidreg.registration.result import RegistrationResult

__all__ = ["register"]

logger = logging.getLogger(__name__)

_DEFAULT_REGISTRARS: dict[tuple[str, str], RigidRegistrar] = {}


def register(
    fixed: sitk.Image | str | Path,
    moving: sitk.Image | str | Path,
    *,
    model: nn.Module | RigidRegistrar | None = None,
    bundle: str | Path | None = None,
    device: str | torch.device | None = "auto",
    cascade_steps: int | None = None,
    refine: bool = False,
    resample_moving: bool = True,
    moving_fov: sitk.Image | None = None,
    fine_stage: bool | None = None,
    global_init: bool | None = None,
    roi: RoiLike = None,
    match: str = "soft",
    keep_couch: bool = False,
    allow_swapped: bool = False,
    thorough: bool | None = None,
    allow_other_patient: bool = False,
) -> RegistrationResult:
    """Rigidly register a CBCT (``moving``) to a planning CT (``fixed``).

    Args:
        fixed: planning CT: path (NIfTI, MetaImage, NRRD, DICOM directory) or ``SimpleITK.Image`` (HU).
        moving: CBCT, likewise; any grid, spacing, origin, direction and field of view overlapping the CT.
        model: a :class:`RigidRegistrar` built once (:meth:`RigidRegistrar.from_bundle`), or a bare network (on the
            shipped bundle's network grid), or ``None`` for the shipped (or ``bundle``'s) network, loaded once per
            bundle and device and kept for later calls.
        bundle: MONAI bundle directory to load the network from (default: the shipped ``cbct_ct_rigid``).
        device: ``"auto"`` (CUDA if available), ``"cpu"``, ``"cuda"``...
        cascade_steps: network applications (default: the bundle's setting).
        refine: polish the network estimate with SimpleITK Mattes-MI (Euler3D, masked to the CBCT FOV).
        resample_moving: also return the CBCT resampled onto the CT grid.
        moving_fov: mask of the CBCT field of view on the CBCT grid (default: inscribed cylinder).
        fine_stage: ``False`` measures the learned network alone: the regression's estimate, without the
            Gauss-Newton stage, search, multi-start or optimizer (``refine`` adds its optimizer, so keep it off for
            that). Also with ``model=`` a registrar built once. ``None`` (default): as the network is configured
            (the shipped bundle: on). ``details["fine_stage"]`` records what ran.
        global_init: the global search for large offsets (translations over +-72 mm for 27 rotation
            candidates, :mod:`monai_rigidreg.registration.search`): the network also starts from the search's best
            candidates (the registrar's ``search_starts``) when the best one disagrees with the estimate from the
            identity, and the estimate whose CBCT field of view matches the CT best is kept (``details["start"]``
            says which: ``"identity"`` or ``"search"``). ``None``
            (default): on, except with ``fine_stage=False`` (the learned network alone); ``False``: off. The
            confidence check's swapped-input estimate is a third candidate: when it disagrees by more than
            :data:`~monai_rigidreg.registration.confidence.SWAP_AGREE_MM` and matches better, it replaces the estimate
            (after its own last level; ``details["start"] == "swapped"``; not with ``refine`` or ``fine_stage=False``),
            and when it matches worse its disagreement does not lower the confidence (``details["swap_check"]``).
        roi: restrict the match to a region of the CT: a box ``(x0, y0, z0, x1, y1, z1)`` in CT LPS mm or a mask
            image (non-zero inside) on the CT's physical space (:mod:`monai_rigidreg.registration.match_region`).
        match: ``"soft"`` (all tissue, default) or ``"bone"`` (the CT's bone and a few mm around it).
        keep_couch: by default the couches (which do not move with the patient) are excluded from the match: the
            CT's tissue-like voxels outside its body (:func:`~monai_rigidreg.registration.body.coarse_body_mask`, 4 mm
            beyond the skin) count as air, and the match weight is zero outside that body, so the CBCT's couch meets no
            weight wherever an estimate puts it. ``True`` keeps them, and so does ``fine_stage=False`` (the learned
            network alone on the inputs as they are).
        allow_swapped: the fixed image really is the planning CT although it looks like the CBCT (its box inside the
            moving one's, or a CBCT's truncated cylindrical field of view,
            :func:`~monai_rigidreg.registration.inputs.swapped_reasons`): the warning stays, the result is not
            flagged for it (``details.signals.swap_allowed``).
        allow_other_patient: register two DICOM folders whose headers name different patients (default: refused,
            :func:`~monai_rigidreg.registration.inputs.check_same_patient`; allowed: its warning in
            ``details["warnings"]``).
        thorough: ``True`` runs the thorough path: the global search beside the network on every call, the further
            starts where they disagree and the swapped-input estimate beside the last level. ``None`` (default): the
            registrar's ``network_leads`` (the shipped bundle: the network-led path,
            :mod:`monai_rigidreg.registration.lead`: the network from the identity, the last level and a cheap check;
            the search, further starts and the swapped-input estimate only as a fallback where the check fails,
            ``details["fallback"]``). ``refine`` always takes the thorough path.

    Returns:
        :class:`RegistrationResult` with ``params`` (mm/deg, fixed -> moving, about the fixed image centre),
        ``transform`` (``Euler3DTransform``), ``registered``, ``timings``, ``confidence``, ``couch_shift`` (at the
        CBCT's centre, head-first supine assumed: :func:`~monai_rigidreg.export.record.complete_record`) and
        ``provenance`` (the audit trail, with the input paths where paths were given).

    Raises:
        InputError: bad input, e.g. both paths naming the same file or the same DICOM series, or a constant
            image.
    """
    paths = isinstance(fixed, (str, Path)) and isinstance(moving, (str, Path))
    if paths:
        check_distinct_inputs(fixed, moving)
    if isinstance(model, RigidRegistrar):
        registrar = model
    elif isinstance(model, nn.Module):
        registrar = RigidRegistrar(model, device=device)
    else:
        key = (str(bundle), str(resolve_device(device)))
        if key not in _DEFAULT_REGISTRARS:
            _DEFAULT_REGISTRARS[key] = RigidRegistrar.from_bundle(bundle, device=device)
        registrar = _DEFAULT_REGISTRARS[key]
    # two DICOM folders: their headers are read once, before registering, for the patient check and the audit trail
    provenance, patient_warning = {}, ""
    if paths and Path(fixed).is_dir() and Path(moving).is_dir():
        provenance = registration_provenance(fixed, moving, bundle=registrar.source, device=str(registrar.device))
        patient_warning = check_same_patient(provenance["inputs"]["fixed"], provenance["inputs"]["moving"],
                                             allow_other_patient)
    # read here (as the registrar would: the same reader and checks), so that the result's couch shifts can be placed
    # at the CBCT's centre
    t_load = time.perf_counter()
    fixed_img, moving_img = as_image(fixed, "fixed"), as_image(moving, "moving")
    t_load = time.perf_counter() - t_load
    result = registrar(fixed_img, moving_img, refine=refine, cascade_steps=cascade_steps,
                       resample_moving=resample_moving, moving_fov=moving_fov, fine_stage=fine_stage,
                       global_init=global_init, roi=roi, match=match, keep_couch=keep_couch,
                       allow_swapped=allow_swapped, thorough=thorough)
    for stage in ("load", "total"):
        result.timings[stage] = result.timings.get(stage, 0.0) + t_load
    if provenance:  # (complete_record makes it where it is still empty)
        result.provenance = provenance
    if patient_warning:
        logger.warning("%s", patient_warning)
        result.details.setdefault("warnings", []).append(patient_warning)
    return complete_record(result, moving_img, fixed, moving, bundle=registrar.source, device=str(registrar.device))
