"""The service's decisions, as plain functions of the headers it indexed: is a series a CBCT or a planning CT
(:func:`classify_series`), is it whole (:func:`check_series_complete`), and which planning CT does a CBCT go to
(:func:`choose_ct`). Each returns its reason in words, for the log and ``serve status``; none guesses: an ambiguous
case is refused with the reason, and the explicit trigger (``serve trigger --series CBCT --ct CT``) settles it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from monai_rigidreg.io.dicom_series import same_patient_ids
from monai_rigidreg.serve.config import Classification, CtSelection

__all__ = ["SeriesFacts", "SliceFacts", "classify_series", "check_series_complete", "choose_ct", "CtChoice",
           "GAP_FACTOR"]

GAP_FACTOR = 1.5
"""A gap between neighbouring slices larger than this multiple of the series' median gap is a missing slice."""


@dataclass(frozen=True)
class SeriesFacts:
    """What the index knows about a series (from its first instance's header and every association that sent it)."""

    series_uid: str
    patient_id: str = ""
    issuer: str = ""
    patient_name: str = ""
    study_uid: str = ""
    for_uid: str = ""
    modality: str = ""
    series_datetime: str = ""
    description: str = ""
    markers: dict[str, str] = field(default_factory=dict)
    calling_aets: tuple[str, ...] = ()
    n_instances: int = 0
    first_at: float = 0.0


@dataclass(frozen=True)
class SliceFacts:
    """The geometry of one received image."""

    sop_uid: str
    ipp: tuple[float, ...] | None = None
    iop: tuple[float, ...] | None = None
    rows: int | None = None
    cols: int | None = None
    spacing: tuple[float, ...] | None = None
    images_in_acquisition: int | None = None


def classify_series(series: SeriesFacts, rule: Classification) -> tuple[str | None, str]:
    """``("cbct" | "ct" | None, reason)``: the role of a complete CT Image Storage series; ``None`` refuses it.

    The rule, in this order:

    1. Modality must be ``CT`` (a CBCT is stored as a CT image by every console this was written for).
    2. The sending AE: one of ``cbct_ae_titles`` says CBCT, one of ``ct_ae_titles`` says planning CT; a series sent
       by AEs of both lists is refused.
    3. The markers: any of ``cbct_markers`` (case-insensitive substring) in one of ``marker_fields`` (Series
       Description, Protocol Name, Station Name, Image Type, Manufacturer's Model Name by default) says CBCT.
    4. AE and markers disagree (a planning-CT AE sent a series marked CBCT): refused. Neither says anything: a
       planning CT where ``unmarked`` is ``"ct"``, refused where it is ``"refuse"``.
    """
    if series.modality.strip().upper() != "CT":
        return None, f"Modality is {series.modality or 'missing'!r}, not CT"
    by_ae = {("cbct" if ae in rule.cbct_ae_titles else "ct") for ae in series.calling_aets
             if ae in rule.cbct_ae_titles or ae in rule.ct_ae_titles}
    senders = ", ".join(series.calling_aets) or "unknown"
    if len(by_ae) > 1:
        return None, f"sent by AE titles of both the CBCT and the planning-CT lists ({senders})"
    marker = _marker(series, rule)
    if by_ae == {"cbct"}:
        return "cbct", f"sent by a CBCT AE title ({senders})" + (f"; {marker}" if marker else "")
    if by_ae == {"ct"}:
        if marker:
            return None, f"sent by a planning-CT AE title ({senders}) but {marker}"
        return "ct", f"sent by a planning-CT AE title ({senders})"
    if marker:
        return "cbct", marker
    if rule.unmarked == "ct":
        return "ct", "no CBCT marker (classification.unmarked is 'ct')"
    return None, ("neither a CBCT marker nor a known sending AE title (classification.unmarked is 'refuse'); fields "
                  f"read: {', '.join(rule.marker_fields)}")


def _marker(series: SeriesFacts, rule: Classification) -> str:
    for name in rule.marker_fields:
        value = series.markers.get(name, "")
        for marker in rule.cbct_markers:
            if marker and marker in value.upper():
                return f"{name} {value!r} contains {marker!r}"
    return ""


def check_series_complete(slices: Sequence[SliceFacts], min_slices: int, aborted: bool = False) -> str:
    """``""`` for a series that can be registered, else why not (a truncated or inconsistent series).

    Refused: fewer than ``min_slices`` images; fewer images than an Images in Acquisition (0020,1002) value says;
    an image without position or orientation; images of different orientation, size or pixel spacing; two images at
    one position; a gap between neighbouring slices larger than :data:`GAP_FACTOR` times the median (missing
    slices); a series whose last sending association was aborted (the sender stopped mid-series). A series cut short
    at its end, without Images in Acquisition and with a normal release, cannot be told from a shorter scan.
    """
    n = len(slices)
    if aborted:
        return (f"the association that sent it was aborted after {n} image(s): the sender stopped mid-series "
                "(resend the series)")
    if n < min_slices:
        return f"only {n} image(s) received (min_slices is {min_slices})"
    expected = max((s.images_in_acquisition or 0) for s in slices)
    if expected > n:
        return f"{n} of {expected} images received (Images in Acquisition): {expected - n} missing"
    if any(s.ipp is None or s.iop is None for s in slices):
        return "an image has no Image Position (Patient) or Image Orientation (Patient)"
    first = slices[0]
    for s in slices[1:]:
        if (s.rows, s.cols) != (first.rows, first.cols):
            return f"images of different sizes ({first.rows}x{first.cols} and {s.rows}x{s.cols})"
        if s.spacing is None or first.spacing is None or not np.allclose(s.spacing, first.spacing, atol=1e-4):
            return f"images of different pixel spacing ({first.spacing} and {s.spacing})"
        if not np.allclose(s.iop, first.iop, atol=1e-4):
            return "images of different orientation (Image Orientation (Patient))"
    iop = np.asarray(first.iop, dtype=np.float64)
    normal = np.cross(iop[:3], iop[3:])
    pos = np.sort(np.asarray([s.ipp for s in slices], dtype=np.float64) @ normal)
    gaps = np.diff(pos)
    if np.any(gaps < 1e-3):
        k = int(np.argmin(gaps))
        return f"two images at the same position ({pos[k]:.2f} mm along the slice normal)"
    median = float(np.median(gaps))
    big = np.flatnonzero(gaps > GAP_FACTOR * median)
    if big.size:
        k = int(big[0])
        missing = int(round(gaps[k] / median)) - 1
        return (f"missing slice(s): a gap of {gaps[k]:.2f} mm between {pos[k]:.2f} and {pos[k + 1]:.2f} mm along the "
                f"slice normal (median gap {median:.2f} mm, about {max(missing, 1)} missing; {big.size} such gap(s))")
    return ""


@dataclass(frozen=True)
class CtChoice:
    """The outcome of :func:`choose_ct`: ``ct`` (the chosen planning CT) with ``state`` ``"chosen"``, or no CT
    with ``state`` ``"hold"`` (none yet: wait for one) or ``"refuse"`` (ambiguous or unusable), and the reason."""

    state: str
    reason: str
    ct: SeriesFacts | None = None


def same_patient(a: SeriesFacts, b: SeriesFacts) -> bool:
    """The same Patient ID, and the same Issuer of Patient ID where both name one
    (:func:`~monai_rigidreg.io.dicom_series.same_patient_ids`)."""
    return same_patient_ids(a.patient_id, b.patient_id, a.issuer, b.issuer)


def choose_ct(cbct: SeriesFacts, cts: Sequence[SeriesFacts], rule: CtSelection,
              explicit: str | None = None) -> CtChoice:
    """The planning CT a CBCT is registered to, among the complete planning CTs held (``cts``).

    1. ``explicit`` (``serve trigger --ct UID``): that CT, if it is held, of the same patient and in another Frame of
       Reference; refused otherwise.
    2. Same patient: Patient ID equal (and Issuer of Patient ID, where both carry one). A CBCT without a Patient ID
       is refused; none held yet: hold.
    3. Frame of Reference: a CT sharing the CBCT's Frame of Reference UID is left out (DICOM already declares the
       two aligned, so no Spatial Registration between them can be stored); none left: refused.
    4. ``same_study``: ``"require"`` keeps only CTs of the CBCT's study (none: hold), ``"prefer"`` keeps them where
       there are any, ``"ignore"`` keeps all.
    5. Several left: ``several`` ``"refuse"`` (the default: a logged reason listing them) or ``"newest"`` (the latest
       Series Date/Time, then the latest received).
    """
    if not cbct.patient_id.strip():
        return CtChoice("refuse", "the CBCT has no Patient ID, so no planning CT can be matched to it")
    if explicit is not None:
        match = [ct for ct in cts if ct.series_uid == explicit]
        if not match:
            return CtChoice("refuse", f"the planning CT {explicit} asked for is not held as a complete planning CT")
        ct = match[0]
        if not same_patient(ct, cbct):
            return CtChoice("refuse", f"the planning CT {explicit} asked for belongs to Patient ID {ct.patient_id!r}, "
                                      f"the CBCT to {cbct.patient_id!r}")
        if ct.for_uid == cbct.for_uid:
            return CtChoice("refuse", f"the planning CT {explicit} asked for shares the CBCT's Frame of Reference "
                                      "UID: no registration between two frames can be stored")
        return CtChoice("chosen", f"planning CT {ct.series_uid} given explicitly", ct)
    mine = [ct for ct in cts if same_patient(ct, cbct)]
    if not mine:
        return CtChoice("hold", f"no planning CT of Patient ID {cbct.patient_id!r} held yet")
    usable = [ct for ct in mine if ct.for_uid != cbct.for_uid]
    if not usable:
        return CtChoice("refuse", f"the planning CT(s) of Patient ID {cbct.patient_id!r} share the CBCT's Frame of "
                                  f"Reference UID {cbct.for_uid}: DICOM already declares them aligned, so no "
                                  "registration between two frames can be stored")
    rule_used = f"the only planning CT of Patient ID {cbct.patient_id!r}"
    if rule.same_study != "ignore":
        in_study = [ct for ct in usable if ct.study_uid == cbct.study_uid]
        if rule.same_study == "require":
            if not in_study:
                return CtChoice("hold", f"no planning CT in the CBCT's study {cbct.study_uid} held yet "
                                        "(ct_selection.same_study is 'require')")
            usable, rule_used = in_study, "the only planning CT in the CBCT's study"
        elif in_study:
            usable, rule_used = in_study, "the only planning CT in the CBCT's study (ct_selection.same_study 'prefer')"
    if len(usable) == 1:
        return CtChoice("chosen", rule_used, usable[0])
    listing = "; ".join(f"{ct.series_uid} ({ct.description or 'no description'}, {ct.series_datetime or 'no date'})"
                        for ct in usable)
    if rule.several == "newest":
        ct = max(usable, key=lambda c: (c.series_datetime, c.first_at))
        return CtChoice("chosen", f"the newest of {len(usable)} planning CTs (ct_selection.several 'newest'): "
                                  f"{listing}", ct)
    return CtChoice("refuse", f"{len(usable)} planning CTs of Patient ID {cbct.patient_id!r} could be meant: "
                              f"{listing}. Choose one with 'monai-rigidreg serve trigger --series {cbct.series_uid} "
                              "--ct UID', or set ct_selection")
