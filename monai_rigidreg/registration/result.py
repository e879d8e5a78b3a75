"""What a registration returns: :class:`RegistrationResult` (the six parameters, their transform and the checks)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.geometry import LPS_TO_RAS, PARAM_NAMES, invert_matrix, params_to_matrix, params_to_sitk
from monai_rigidreg.core.json_safe import json_safe

__all__ = ["RegistrationResult"]


@dataclass
class RegistrationResult:
    """Result of :func:`~monai_rigidreg.registration.register`.

    Attributes:
        params: ``(tx, ty, tz, rx, ry, rz)`` mm / degrees, fixed -> moving, about ``center`` (``docs/conventions.md``).
        center: rotation centre (LPS mm): the fixed image centre.
        registered: the moving image resampled onto the fixed grid (``None`` if not asked for), under the
            parameters the result was made with: :meth:`registered_is_current` says whether they are still
            :attr:`params` and :attr:`center` (the outputs resample again where they are not).
        timings: seconds per stage (``load``, ``body``, ``preprocess``, ``network``, ``global_search``,
            ``second_start``, ``native_level``, ``refine``, ``confidence``, ``resample``, ``total``; those that ran).
            The global search runs in a worker thread beside the network from the identity: ``global_search`` is
            its own duration, which overlaps ``network``, and ``global_search_wait`` the time the registration
            waited for it afterwards. The confidence check's swapped-input estimate runs in a worker thread beside
            the last level: ``swap_estimate`` is its own duration (overlapping ``native_level``; ``confidence``
            includes only the wait for it).
        confidence: a number in [0, 1]; what it means is :attr:`confidence_meaning` (with the shipped calibration
            the estimated probability that the target registration error is under 2 mm,
            :mod:`~monai_rigidreg.registration.calibration`). 0 where an input's intensities are certainly not HU
            (:func:`~monai_rigidreg.registration.inputs.not_hu`; ``details.signals.not_hu`` names it) or the inputs
            look swapped (``details.signals.swapped``, unless allowed). A flagged result's confidence lies below the
            flag threshold (``details.confidence_calibration.flag_below``).
        flagged: likely failure: check the QC figure; ``details.flag_reasons`` says why (``"confidence"``,
            ``"rule"``, ``"overlap"``, ``"swapped"``, ``"not_hu"``).
        confidence_meaning: what :attr:`confidence` says, in a sentence (``""`` where the check did not run).
        details: network-only parameters, refinement change, similarity before/after, swap consistency, and
            ``warnings`` (a list of sentences, e.g. an input whose intensities are not HU) where there are any.
        provenance: the audit trail (:func:`~monai_rigidreg.export.provenance.registration_provenance`: inputs and their
            DICOM UIDs, bundle and weights' SHA-256, software versions, device, time, command line), filled in by
            :func:`~monai_rigidreg.registration.files.register_files` and, for images given in memory too, by
            :func:`~monai_rigidreg.registration.register` and :func:`~monai_rigidreg.export.outputs.write_outputs`
            (:func:`~monai_rigidreg.export.record.complete_record`); empty from a bare :class:`RigidRegistrar` call.
        couch_shift: the correction in IEC 61217 couch terms at the isocentre
            (:func:`~monai_rigidreg.export.couch_shifts.couch_shifts`), filled in by the same functions
            (:func:`~monai_rigidreg.registration.register`: at the CBCT's centre, head-first supine assumed).
    """

    params: np.ndarray
    center: np.ndarray
    registered: sitk.Image | None = None
    timings: dict[str, float] = field(default_factory=dict)
    confidence: float = float("nan")
    flagged: bool = False
    details: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    couch_shift: dict[str, Any] = field(default_factory=dict)
    confidence_meaning: str = ""
    _registered_under: tuple[np.ndarray, np.ndarray, sitk.Image] | None = field(default=None, repr=False,
                                                                                compare=False)

    def __post_init__(self) -> None:
        if self.registered is not None and self._registered_under is None:  # (dataclasses.replace keeps the record)
            self._registered_under = (np.array(self.params, dtype=np.float64),
                                      np.array(self.center, dtype=np.float64), self.registered)

    def registered_is_current(self) -> bool:
        """Whether :attr:`registered` is the image the result was made with, under the current :attr:`params` and
        :attr:`center` (``False`` where either was changed since, also through ``dataclasses.replace``, or another
        image was set).

        >>> import SimpleITK as sitk
        >>> res = RegistrationResult(np.zeros(6), np.zeros(3), registered=sitk.Image(4, 4, 4, sitk.sitkFloat32))
        >>> res.registered_is_current()
        True
        >>> res.params = np.array([5.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        >>> res.registered_is_current()
        False
        """
        if self.registered is None or self._registered_under is None:
            return False
        params, center, image = self._registered_under
        return bool(image is self.registered
                    and np.array_equal(params, np.asarray(self.params, dtype=np.float64))
                    and np.array_equal(center, np.asarray(self.center, dtype=np.float64)))

    @property
    def transform(self) -> sitk.Euler3DTransform:
        """The ``SimpleITK.Euler3DTransform`` (fixed -> moving): ``sitk.Resample(moving, fixed, transform)``."""
        return params_to_sitk(self.params, self.center)

    @property
    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix of :attr:`transform` (LPS mm)."""
        return params_to_matrix(self.params, self.center)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (``result.json``)."""
        return {
            "params": {n: float(v) for n, v in zip(PARAM_NAMES, self.params)},
            "units": {"translation": "mm", "rotation": "degrees"},
            "convention": "ITK LPS; maps fixed (CT) points to moving (CBCT) points; Euler3DTransform, "
            "rotation R = Rz @ Rx @ Ry about center",
            "center": [float(v) for v in self.center],
            "matrix": [[float(v) for v in row] for row in self.matrix],
            # the same transform the other way round (CBCT points -> CT points, LPS: what a DICOM Spatial
            # Registration stores) and in RAS for 3D Slicer (the "to parent" matrix Slicer shows for the CBCT
            # placed under the loaded transform.tfm)
            "matrix_moving_to_fixed": [[float(v) for v in row] for row in invert_matrix(self.matrix)],
            "matrix_moving_to_fixed_ras": [[float(v) for v in row]
                                           for row in LPS_TO_RAS @ invert_matrix(self.matrix) @ LPS_TO_RAS],
            "runtime_s": {k: round(float(v), 4) for k, v in self.timings.items()},
            "confidence": json_safe(float(self.confidence)),  # null where the check did not run
            "confidence_meaning": self.confidence_meaning or None,
            "flagged": bool(self.flagged),
            "details": json_safe(self.details),
            "provenance": json_safe(self.provenance),
            "couch_shift": json_safe(self.couch_shift),
        }
