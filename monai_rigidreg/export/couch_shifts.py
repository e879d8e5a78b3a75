"""Couch corrections in IEC 61217 terms from a registration result.

The registration transform ``T`` maps a point of the planning CT (fixed) to the CBCT (moving), in DICOM patient
coordinates (ITK LPS, mm; see ``docs/conventions.md``). The CBCT frame is the treatment-room frame registered to
the CT frame: the plan isocentre ``p`` (CT coordinates) is where the machine isocentre sits.

Derivation
----------
The anatomy planned at CT coordinate ``x`` is seen at ``T(x)`` in the room: the patient is displaced by ``T``
relative to the plan. The couch carries the patient, so it must apply the inverse motion ``C = T^-1``
(``C(T(x)) = x`` for every anatomy point). Write ``T(x) = R x + o`` and ``d = T(p) - p``, the displacement of the
isocentre anatomy. Decompose ``C`` into a translation followed by a rotation about the (fixed) isocentre::

    C(y) = R^T (y + s - p) + p,    s = p - T(p) = -d,

which is ``T^-1`` because ``R^T (R x + o - T(p)) + p = R^T R (x - p) + p = x``. The translation ``s`` alone puts
the anatomy planned at the isocentre back on the isocentre, and the rotation ``R^T`` about the isocentre then
leaves it there: the translation is *the correction at the isocentre* and is also the best 3-DoF correction (a
couch that cannot rotate corrects the isocentre exactly and leaves the rotation). For a couch that applies its
rotation first and then translates, the equivalent translation is ``R^T s`` (reported as
``translation_if_rotation_first``); the two differ by ``|s| * angle`` at most.

Both are then expressed in the IEC 61217 fixed (room) system, origin at the isocentre: ``q = A (y - p)`` with
``A`` the 3x3 map from patient LPS axes to IEC axes for the patient position (a proper rotation: LPS and IEC are
both right-handed), so the translation is ``A s`` and the rotation ``A R^T A^T``. The rotation is decomposed as
``Rz(couch rotation) @ Rx(pitch) @ Ry(roll)`` about the IEC fixed axes X (pitch), Y (roll), Z (couch rotation or
yaw): apply roll first, then pitch, then couch rotation (as intrinsic rotations: couch rotation, pitch, roll; the
order of the IEC 61217 chain fixed -> patient support -> table top). Angles are right-handed about the positive IEC
axes (IEC 61217: clockwise seen from the isocentre looking along the positive axis).

Sign convention: every number is the motion to apply to the couch, with the patient on it. Positive lateral moves
the couch toward +X (to the right of an observer at the foot of the couch facing the gantry), positive
longitudinal toward +Y (toward the gantry), positive vertical toward +Z (up). A patient found 3 mm to their left in
HFS (``T`` a pure translation ``(3, 0, 0)``) gives lateral = -3 mm. Consoles differ (some display the patient's
displacement, some a couch position, some angles in 0..360): check the sign of one known shift before clinical use.

Patient axes in IEC fixed axes (``+x`` patient left, ``+y`` posterior, ``+z`` superior), from the DICOM Patient
Position (0018,5100) of the planning CT, assumed to be the treatment position:

========  ==========  ==========  ==========
position  +x (left)   +y (post.)  +z (sup.)
========  ==========  ==========  ==========
HFS       +X          -Z          +Y
HFP       -X          +Z          +Y
FFS       -X          -Z          -Y
FFP       +X          +Z          -Y
HFDL      -Z          -X          +Y
HFDR      +Z          +X          +Y
FFDL      -Z          +X          -Y
FFDR      +Z          -X          -Y
========  ==========  ==========  ==========

A missing patient position (``None`` or empty) is taken as HFS, with a warning, and recorded as assumed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import matrix_to_params, sitk_to_matrix

__all__ = ["PATIENT_POSITIONS", "ROTATION_ORDER", "SIGN_CONVENTION", "CouchShifts", "couch_shifts", "lps_to_iec"]

logger = logging.getLogger(__name__)

_IEC_AXES = {"+X": (1, 0, 0), "-X": (-1, 0, 0), "+Y": (0, 1, 0), "-Y": (0, -1, 0), "+Z": (0, 0, 1), "-Z": (0, 0, -1)}

PATIENT_POSITIONS: dict[str, tuple[str, str, str]] = {
    "HFS": ("+X", "-Z", "+Y"),
    "HFP": ("-X", "+Z", "+Y"),
    "FFS": ("-X", "-Z", "-Y"),
    "FFP": ("+X", "+Z", "-Y"),
    "HFDL": ("-Z", "-X", "+Y"),
    "HFDR": ("+Z", "+X", "+Y"),
    "FFDL": ("-Z", "+X", "-Y"),
    "FFDR": ("+Z", "-X", "-Y"),
}
"""IEC 61217 fixed axis of the patient's ``+x`` (left), ``+y`` (posterior), ``+z`` (superior) per position."""

ROTATION_ORDER = (
    "R = Rz(couch_rotation) @ Rx(pitch) @ Ry(roll) about the IEC fixed axes through the isocentre "
    "(roll about Y first, then pitch about X, then couch rotation about Z), applied after the translation"
)
SIGN_CONVENTION = (
    "correction to apply to the couch (patient moves with it), IEC 61217 fixed axes, origin at the isocentre: "
    "+lateral = +X (right of an observer at the couch foot facing the gantry), +longitudinal = +Y (toward the "
    "gantry), +vertical = +Z (up); angles right-handed about the positive axes"
)


def lps_to_iec(patient_position: str) -> np.ndarray:
    """3x3 matrix ``A`` with ``q_iec = A @ v_lps`` for the DICOM patient position (column j: IEC image of LPS axis j).

    Raises:
        InputError: a patient position outside :data:`PATIENT_POSITIONS`.
    """
    key = str(patient_position).strip().upper()
    if key not in PATIENT_POSITIONS:
        raise InputError(
            f"unsupported patient position {patient_position!r}; expected one of {sorted(PATIENT_POSITIONS)}"
        )
    return np.array([_IEC_AXES[a] for a in PATIENT_POSITIONS[key]], dtype=np.float64).T


@dataclass(frozen=True)
class CouchShifts:
    """Couch correction in IEC 61217 fixed axes (see the module docstring for the derivation and signs).

    Attributes:
        lateral, longitudinal, vertical: 6-DoF translation (mm), applied before the rotation.
        pitch, roll, couch_rotation: rotation about the isocentre (degrees) about IEC X, Y, Z (yaw), in the
            order of :data:`ROTATION_ORDER`.
        lateral_3dof, longitudinal_3dof, vertical_3dof: translation for a couch that cannot rotate (mm): it puts the
            anatomy planned at the isocentre back on it, ``-(T(p) - p)`` in IEC axes (equal to the 6-DoF
            translation in this order).
        translation_if_rotation_first: the 6-DoF translation (mm, IEC) for a couch that rotates first.
        isocentre: the isocentre used (CT coordinates, LPS mm).
        isocentre_displacement: ``T(p) - p`` in LPS mm, where the isocentre anatomy is seen relative to the plan.
        patient_position: the DICOM patient position used.
        patient_position_assumed: ``True`` when none was given and HFS was assumed.
    """

    lateral: float
    longitudinal: float
    vertical: float
    pitch: float
    roll: float
    couch_rotation: float
    lateral_3dof: float
    longitudinal_3dof: float
    vertical_3dof: float
    translation_if_rotation_first: tuple[float, float, float]
    isocentre: tuple[float, float, float]
    isocentre_displacement: tuple[float, float, float]
    patient_position: str
    patient_position_assumed: bool

    @property
    def translation(self) -> np.ndarray:
        """6-DoF ``(lateral, longitudinal, vertical)`` in mm."""
        return np.array([self.lateral, self.longitudinal, self.vertical])

    @property
    def rotation(self) -> np.ndarray:
        """``(pitch, roll, couch_rotation)`` in degrees."""
        return np.array([self.pitch, self.roll, self.couch_rotation])

    @property
    def translation_3dof(self) -> np.ndarray:
        """3-DoF ``(lateral, longitudinal, vertical)`` in mm."""
        return np.array([self.lateral_3dof, self.longitudinal_3dof, self.vertical_3dof])

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (for ``result.json``)."""
        return {
            "convention": SIGN_CONVENTION,
            "rotation_order": ROTATION_ORDER,
            "units": {"translation": "mm", "rotation": "degrees"},
            "6dof": {
                "lateral": self.lateral,
                "longitudinal": self.longitudinal,
                "vertical": self.vertical,
                "pitch": self.pitch,
                "roll": self.roll,
                "couch_rotation": self.couch_rotation,
            },
            "3dof": {
                "lateral": self.lateral_3dof,
                "longitudinal": self.longitudinal_3dof,
                "vertical": self.vertical_3dof,
            },
            "translation_if_rotation_first": list(self.translation_if_rotation_first),
            "isocentre_lps_mm": list(self.isocentre),
            "isocentre_displacement_lps_mm": list(self.isocentre_displacement),
            "patient_position": self.patient_position,
            "patient_position_assumed": self.patient_position_assumed,
        }


def _rigid_matrix(transform: Any) -> np.ndarray:
    if isinstance(transform, sitk.Transform):
        try:
            return _rigid_matrix(sitk_to_matrix(transform))
        except ValueError as exc:  # a transform without a 4x4 matrix (B-spline, displacement field)
            raise InputError(f"expected a rigid transform, got {transform.GetName()} ({exc})") from exc
    m = np.asarray(transform, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise InputError(f"expected a finite 4x4 fixed->moving matrix, got shape {m.shape}")
    r = m[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) <= 0:
        raise InputError("the transform is not rigid: its 3x3 block is not a proper rotation")
    return m


def couch_shifts(transform: Any, patient_position: str | None, isocentre: Any) -> CouchShifts:
    """The couch correction that returns the anatomy seen in the CBCT to its planned position.

    Args:
        transform: the registration result, fixed (CT) -> moving (CBCT), LPS mm: a 4x4 matrix
            (``RegistrationResult.matrix``) or a SimpleITK transform.
        patient_position: DICOM Patient Position of the CT (``"HFS"``, ``"HFP"``, ``"FFS"``, ``"FFP"``,
            ``"HFDL"``, ``"HFDR"``, ``"FFDL"``, ``"FFDR"``); ``None`` or empty: HFS is assumed, with a warning.
        isocentre: the plan isocentre in CT coordinates (LPS mm).

    Raises:
        InputError: an unknown patient position, a non-rigid transform or a bad isocentre.
    """
    assumed = patient_position is None or not str(patient_position).strip()
    if assumed:
        logger.warning("patient position unknown: assuming head first supine (HFS) for the couch shifts")
        position = "HFS"
    else:
        position = str(patient_position).strip().upper()
    a = lps_to_iec(position)
    p = np.asarray(isocentre, dtype=np.float64).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise InputError(f"the isocentre must be 3 finite LPS coordinates (mm), got {isocentre!r}")
    m = _rigid_matrix(transform)
    r = m[:3, :3]
    d = r @ p + m[:3, 3] - p  # T(p) - p: displacement of the isocentre anatomy
    s_iec = a @ -d  # translation first: brings the isocentre anatomy back to the isocentre
    rc_iec = a @ r.T @ a.T  # then the inverse rotation about the isocentre, in IEC axes
    rot = np.eye(4)
    rot[:3, :3] = rc_iec
    # Rz @ Rx @ Ry is geometry's Euler3D order: its (rx, ry, rz) are (pitch, roll, couch rotation) in IEC axes
    pitch, roll, yaw = matrix_to_params(rot)[3:]
    t_first = rc_iec @ s_iec
    return CouchShifts(
        lateral=float(s_iec[0]),
        longitudinal=float(s_iec[1]),
        vertical=float(s_iec[2]),
        pitch=float(pitch),
        roll=float(roll),
        couch_rotation=float(yaw),
        lateral_3dof=float(s_iec[0]),
        longitudinal_3dof=float(s_iec[1]),
        vertical_3dof=float(s_iec[2]),
        translation_if_rotation_first=tuple(float(v) for v in t_first),
        isocentre=tuple(float(v) for v in p),
        isocentre_displacement=tuple(float(v) for v in d),
        patient_position=position,
        patient_position_assumed=bool(assumed),
    )
