"""The DICOM Storage SCP (pynetdicom): accepts CT Image Storage (CT and CBCT) and Verification from the AE titles of
``allowed_ae_titles`` only, writes each instance to disk and indexes it before acknowledging it."""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
from collections import Counter
from collections.abc import Callable
from typing import Any

from monai_rigidreg.serve.config import ServeConfig
from monai_rigidreg.serve.store import Store, StoredInstance, header_facts

__all__ = ["StorageSCP", "ACCEPTED_TRANSFER_SYNTAXES", "STATUS_NOT_AUTHORIZED"]

logger = logging.getLogger("monai_rigidreg.serve")

ACCEPTED_TRANSFER_SYNTAXES = (
    "1.2.840.10008.1.2",  # Implicit VR Little Endian
    "1.2.840.10008.1.2.1",  # Explicit VR Little Endian
    "1.2.840.10008.1.2.1.99",  # Deflated Explicit VR Little Endian
    "1.2.840.10008.1.2.2",  # Explicit VR Big Endian (retired, still sent by old consoles)
    "1.2.840.10008.1.2.4.70",  # JPEG Lossless, first-order prediction
    "1.2.840.10008.1.2.4.90",  # JPEG 2000 lossless
    "1.2.840.10008.1.2.5",  # RLE Lossless
)
"""Transfer syntaxes offered for CT Image Storage: the uncompressed ones and the lossless compressions GDCM (the
series reader) decodes."""
CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
VERIFICATION = "1.2.840.10008.1.1"
STATUS_NOT_AUTHORIZED = 0x0124
STATUS_OUT_OF_RESOURCES = 0xA700
STATUS_CANNOT_UNDERSTAND = 0xC000


class StorageSCP:
    """The listening side of the service.

    Args:
        cfg: the configuration (AE title, host, port, allowed AE titles).
        store: where instances go.
        on_stored: called after each instance is on disk and indexed, with the :class:`StoredInstance`, the calling
            AE title and the header facts.
        event: the service's event logger, ``event(level, text, series_uid=None)``.
    """

    def __init__(self, cfg: ServeConfig, store: Store, on_stored: Callable[[StoredInstance, str, dict], None],
                 event: Callable[..., None]) -> None:
        self.cfg, self.store, self.on_stored, self.event = cfg, store, on_stored, event
        self._server: Any = None
        self._ae: Any = None
        self._lock = threading.Lock()
        self._sent: dict[Any, Counter] = {}  # association -> instances per series it delivered

    def start(self) -> None:
        from pynetdicom import AE, evt

        ae = AE(ae_title=self.cfg.ae_title)
        ae.add_supported_context(CT_IMAGE_STORAGE, list(ACCEPTED_TRANSFER_SYNTAXES))
        ae.add_supported_context(VERIFICATION)
        # the service's own AE title may associate too, for the C-ECHO of `serve status --echo` (its C-STOREs are
        # refused in _on_store)
        ae.require_calling_aet = [*self.cfg.allowed_ae_titles, self.cfg.ae_title]
        ae.require_called_aet = True
        ae.maximum_associations = 16
        ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = 60.0
        handlers = [(evt.EVT_CONN_OPEN, _quick_acks), (evt.EVT_C_STORE, self._on_store),
                    (evt.EVT_C_ECHO, self._on_echo), (evt.EVT_ACCEPTED, self._on_accepted),
                    (evt.EVT_REJECTED, self._on_rejected),
                    (evt.EVT_RELEASED, self._on_released), (evt.EVT_ABORTED, self._on_aborted)]
        self._server = ae.start_server((self.cfg.host, self.cfg.port), block=False, evt_handlers=handlers)
        self._ae = ae

    @property
    def port(self) -> int:
        """The port listened on (the configured one; the actual one where the configuration said 0)."""
        return int(self._server.server_address[1]) if self._server is not None else self.cfg.port

    def stop(self) -> None:
        if self._server is not None:
            self._server.shutdown()  # stops listening and aborts the associations in progress
            self._server = None

    # -- handlers (each runs in its association's thread) ----------------------------------------------------------
    @staticmethod
    def _peer(event: Any) -> str:
        r = event.assoc.requestor
        return f"{r.ae_title!r} ({r.address}:{r.port})"

    def _on_store(self, event: Any) -> int:
        calling = event.assoc.requestor.ae_title.strip()
        if calling == self.cfg.ae_title and calling not in self.cfg.allowed_ae_titles:
            self.event(logging.WARNING, f"C-STORE from the service's own AE title {calling!r} refused (it may only "
                                        "C-ECHO)")
            return STATUS_NOT_AUTHORIZED
        try:
            ds = event.dataset
            ds.file_meta = event.file_meta
            facts = header_facts(ds, self.cfg.classification.marker_fields)
        except Exception as exc:  # noqa: BLE001 - a data set that cannot be decoded is refused, the association lives
            self.event(logging.WARNING, f"C-STORE from {self._peer(event)} refused: the data set cannot be decoded "
                                        f"({exc})")
            return STATUS_CANNOT_UNDERSTAND
        if not facts["sop_uid"] or not facts["series_uid"]:
            self.event(logging.WARNING, f"C-STORE from {self._peer(event)} refused: no SOP Instance UID or Series "
                                        "Instance UID")
            return STATUS_CANNOT_UNDERSTAND
        try:
            path = self.store.write_instance_file(facts["series_uid"], facts["sop_uid"], event.encoded_dataset())
            stored = self.store.add_instance(facts, path, calling)
        except Exception as exc:  # noqa: BLE001 - disk full, index locked: the sender is told, and may resend
            self.event(logging.ERROR, f"instance {facts['sop_uid']} of series {facts['series_uid']} from "
                                      f"{self._peer(event)} not stored: {exc}", facts["series_uid"])
            return STATUS_OUT_OF_RESOURCES
        with self._lock:
            self._sent.setdefault(event.assoc, Counter())[stored.series_uid] += 1
        try:
            self.on_stored(stored, calling, facts)
        except Exception:  # noqa: BLE001 - the instance is safe on disk; a bug in the follow-up is logged only
            logger.exception("after storing instance %s", stored.sop_uid)
        return 0x0000

    def _on_echo(self, event: Any) -> int:
        logger.debug("C-ECHO from %s", self._peer(event))
        return 0x0000

    def _on_accepted(self, event: Any) -> None:
        logger.info("association from %s accepted", self._peer(event))

    def _on_rejected(self, event: Any) -> None:
        r = event.assoc.requestor
        calling = (r.ae_title or "").strip()
        if calling not in (*self.cfg.allowed_ae_titles, self.cfg.ae_title):
            why = f"calling AE title {calling!r} is not in allowed_ae_titles"
        else:
            why = f"it did not call this service's AE title {self.cfg.ae_title!r}"
        self.event(logging.WARNING, f"association from {r.address}:{r.port} refused: {why}")

    def _finish(self, event: Any, aborted: bool) -> None:
        with self._lock:
            sent = self._sent.pop(event.assoc, Counter())
        if sent:
            self.store.mark_association(set(sent), aborted)
        what = ", ".join(f"{n} of series {uid}" for uid, n in sent.items()) or "no instances"
        if aborted and sent:
            for uid, n in sent.items():
                self.event(logging.WARNING, f"association from {self._peer(event)} aborted after {n} instance(s) of "
                                            f"series {uid}: the series is refused as truncated unless the rest "
                                            "arrives", uid)
        else:
            logger.info("association from %s %s: %s stored", self._peer(event), "aborted" if aborted else "released",
                        what)

    def _on_released(self, event: Any) -> None:
        self._finish(event, aborted=False)

    def _on_aborted(self, event: Any) -> None:
        self._finish(event, aborted=True)


def _quick_acks(event: Any) -> None:
    """Acknowledge received data at once on this connection (Linux ``TCP_QUICKACK``, set again before every read:
    the kernel clears it). A sender that leaves Nagle's algorithm on (dcmtk's ``storescu`` without
    ``TCP_NODELAY=1``) holds the last segment of each image until the previous ones are acknowledged, and a delayed
    acknowledgement costs up to 40 ms per image: 55 ms per 128 KiB image on loopback, against about 6 ms with either
    side's fix."""
    sock = event.assoc.dul.socket
    raw = getattr(sock, "socket", None)
    quickack = getattr(socket, "TCP_QUICKACK", None)
    if raw is None:
        return
    with contextlib.suppress(OSError):
        raw.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    if quickack is None:
        return
    read = sock.recv

    def recv(nr_bytes: int) -> bytearray:
        with contextlib.suppress(OSError):
            raw.setsockopt(socket.IPPROTO_TCP, quickack, 1)
        return read(nr_bytes)

    sock.recv = recv
