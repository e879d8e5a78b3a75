"""The couch shifts and the audit trail of a result, with their defaults where the caller gave none.

Every entry point's result carries both (``RegistrationResult.couch_shift`` and ``.provenance``, and so every
``result.json``): :func:`~monai_rigidreg.registration.files.register_files` (the ``register`` command, the bundle,
``--datalist`` runs) builds them from the input files, ``--isocenter`` and ``--patient-position``;
:func:`~monai_rigidreg.registration.register` and :func:`~monai_rigidreg.export.outputs.write_outputs` (the demo,
in-memory images) complete a result that has none with :func:`complete_record`: the couch shifts at the CBCT's centre
with head-first supine assumed (``patient_position_assumed``), the audit trail with what is known of the inputs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.export.couch_shifts import couch_shifts
from monai_rigidreg.export.provenance import registration_provenance

__all__ = ["couch_shift_record", "complete_record", "ASSUMED_POSITION_SOURCE"]

ASSUMED_POSITION_SOURCE = "assumed (no DICOM header)"
"""``patient_position_source`` where no Patient Position was given or read: head-first supine is assumed."""


def couch_shift_record(matrix: Any, moving: sitk.Image, position: str | None = None,
                       position_source: str = ASSUMED_POSITION_SOURCE, isocenter: Any = None, problem: str = "",
                       warn: bool = True) -> dict[str, Any]:
    """``result.json``'s ``"couch_shift"``: :func:`~monai_rigidreg.export.couch_shifts.couch_shifts` of ``matrix``
    (fixed -> moving, LPS) at ``isocenter`` (CT LPS mm; default the CBCT's centre), with where the isocentre and the
    patient position came from; ``{"unavailable": problem}`` where no couch shifts can be given.

    ``position=None`` assumes head-first supine (``patient_position_assumed``), with a warning in the log unless
    ``warn=False`` (the defaults of :func:`complete_record`, which say so in the record only).
    """
    if problem:
        return {"unavailable": problem}
    source = "--isocenter" if isocenter is not None else "CBCT centre (default)"
    iso = Grid.from_sitk(moving).center() if isocenter is None else np.asarray(isocenter, dtype=np.float64)
    shifts = couch_shifts(matrix, position if (position or warn) else "HFS", iso).to_dict()
    if position is None:
        shifts["patient_position_assumed"] = True
    return {**shifts, "isocentre_source": source, "patient_position_source": position_source}


def _path(value: Any) -> str | Path | None:
    return value if isinstance(value, (str, Path)) else None


def complete_record(result: Any, moving: sitk.Image, fixed_source: Any = None, moving_source: Any = None,
                    names: tuple[str, str] | None = None, bundle: dict[str, Any] | None = None,
                    device: str = "") -> Any:
    """Give ``result`` (a :class:`~monai_rigidreg.registration.result.RegistrationResult`) the couch shifts and the
    audit trail it lacks, in place; returns it.

    Args:
        result: its ``couch_shift`` and ``provenance`` are filled where empty (never replaced).
        moving: the CBCT image (its centre is the default isocentre).
        fixed_source, moving_source: the inputs as given: paths are recorded as
            :func:`~monai_rigidreg.export.provenance.input_record` does (DICOM UIDs included), images as
            :data:`~monai_rigidreg.export.provenance.IN_MEMORY` (with ``names``' entry, where given).
        names: the inputs' display names (e.g. their file names) where they are images.
        bundle: the bundle record (``RigidRegistrar.source``), device: the device it ran on.
    """
    if not result.couch_shift:
        result.couch_shift = couch_shift_record(result.matrix, moving, warn=False)
    if not result.provenance:
        record = registration_provenance(_path(fixed_source), _path(moving_source), bundle=bundle, device=device)
        for key, name in zip(("fixed", "moving"), names or ()):
            if record["inputs"][key]["path"] is None and name:
                record["inputs"][key]["name"] = name
        result.provenance = record
    return result
