"""Sending a REG object to a destination AE by C-STORE (pynetdicom), and the C-ECHO of ``serve status --echo``."""

from __future__ import annotations

import contextlib
import socket
from pathlib import Path

__all__ = ["send_file", "echo", "SUCCESS_STATUSES", "backoff_s"]

SUCCESS_STATUSES = frozenset({0x0000, 0xB000, 0xB006, 0xB007})
"""C-STORE statuses that mean stored: success and the warnings (coercion of data elements, elements discarded,
data set does not match the SOP class)."""

REG_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.66.1"
TIMEOUT_S = 30.0


def _ae(calling_ae: str, contexts: list[tuple[str, list[str] | None]]):
    from pynetdicom import AE

    ae = AE(ae_title=calling_ae)
    ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = TIMEOUT_S
    ae.connection_timeout = 10.0
    for sop_class, syntaxes in contexts:
        if syntaxes is None:
            ae.add_requested_context(sop_class)
        else:
            ae.add_requested_context(sop_class, syntaxes)
    return ae


def send_file(path: str | Path, ae_title: str, host: str, port: int, calling_ae: str) -> tuple[bool, str]:
    """C-STORE one DICOM file (a REG) to ``ae_title@host:port``. Returns ``(stored, what happened in words)``; never
    raises for a network failure (the caller retries)."""
    from pydicom import dcmread
    from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian

    try:
        ds = dcmread(str(path))
    except Exception as exc:  # noqa: BLE001 - a file that cannot be read is reported, not raised
        return False, f"the REG file cannot be read ({exc})"
    ae = _ae(calling_ae, [(str(ds.SOPClassUID), [ExplicitVRLittleEndian, ImplicitVRLittleEndian])])
    try:
        assoc = ae.associate(host, int(port), ae_title=ae_title)
    except Exception as exc:  # noqa: BLE001
        return False, f"cannot connect ({exc})"
    if not assoc.is_established:
        if assoc.is_rejected:
            return False, "association rejected (is this AE title known to the destination?)"
        return False, "cannot connect or association aborted (is the destination running and reachable?)"
    _no_delay(assoc)
    try:
        status = assoc.send_c_store(ds)
    except Exception as exc:  # noqa: BLE001
        assoc.abort()
        return False, f"C-STORE failed ({exc})"
    code = getattr(status, "Status", None) if status is not None else None
    if assoc.is_established:
        assoc.release()
    if code is None:
        return False, "no C-STORE response (connection timed out or aborted)"
    if int(code) not in SUCCESS_STATUSES:
        return False, f"C-STORE refused with status 0x{int(code):04X}"
    return True, "stored" if int(code) == 0 else f"stored with warning status 0x{int(code):04X}"


def _no_delay(assoc) -> None:
    """Send without Nagle's algorithm: the data set's last segment goes out at once instead of waiting for the
    receiver's (possibly delayed) acknowledgement of the previous ones."""
    raw = getattr(getattr(assoc.dul, "socket", None), "socket", None)
    if raw is not None:
        with contextlib.suppress(OSError):
            raw.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


def echo(ae_title: str, host: str, port: int, calling_ae: str) -> tuple[bool, str]:
    """C-ECHO ``ae_title@host:port`` as ``calling_ae``: ``(answered, what happened)``."""
    from pynetdicom.sop_class import Verification

    ae = _ae(calling_ae, [(Verification, None)])
    assoc = ae.associate(host, int(port), ae_title=ae_title)
    if not assoc.is_established:
        return False, ("association rejected (is the calling AE title in allowed_ae_titles?)" if assoc.is_rejected
                       else f"no answer from {host}:{port}")
    status = assoc.send_c_echo()
    assoc.release()
    ok = status is not None and int(getattr(status, "Status", -1)) == 0
    return ok, "C-ECHO answered" if ok else "C-ECHO without success status"


def backoff_s(attempts: int, initial: float, maximum: float) -> float:
    """Seconds before retry number ``attempts + 1``: ``initial``, doubled per failed attempt, at most ``maximum``."""
    return min(maximum, initial * 2.0 ** max(0, attempts - 1))
