"""What the service keeps on disk: the received instances, one file each, and an index (SQLite) of series, their
state, the REG objects still to send, the explicit triggers and the events.

Layout of ``storage_dir``::

    index.sqlite                      the index (WAL journal: readable by ``serve status`` while the service runs)
    instances/<series UID>/<SOP UID>.dcm   every instance received, written aside and renamed into place
    results/<Patient ID>/<CBCT series UID>/   each registration's outputs (result.json, qc.png, registration.dcm, ...)
    tmp/                              files being written (emptied at start)

An instance is acknowledged (C-STORE success) only once its file is synced to disk and indexed, so a crash loses
nothing the sender was told was stored; at start :meth:`Store.reconcile` indexes any file whose index entry a crash
cut off. A series moves through the states of :data:`STATES`; only the service process changes them (``serve
trigger`` adds a row to ``triggers``, which the service reads).
"""

from __future__ import annotations

import json
import logging
import os
import re
import secrets
import sqlite3
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from monai_rigidreg.serve.rules import SeriesFacts, SliceFacts

__all__ = ["Store", "StoredInstance", "STATES", "TERMINAL_STATES", "safe_name", "header_facts"]

logger = logging.getLogger("monai_rigidreg.serve")

RECEIVING, READY, QUEUED, REGISTERING, DONE = "receiving", "ready", "queued", "registering", "done"
WAITING_CT, REFUSED, FAILED, INVALID, EXPIRED = "waiting_ct", "refused", "failed", "invalid", "expired"
STATES = {
    RECEIVING: "instances arriving; complete after completion_timeout_s without a new one, or on a trigger",
    READY: "a complete planning CT, available to the CBCTs of its patient",
    QUEUED: "a complete CBCT waiting for the registration worker",
    REGISTERING: "a CBCT being registered",
    DONE: "registered; its REG written (sends listed separately)",
    WAITING_CT: "a complete CBCT whose patient has no planning CT yet (held until hold_for_ct_s)",
    REFUSED: "not registered: ambiguous or unusable (the reason says why; a trigger with --ct can settle it)",
    FAILED: "the registration failed (the reason says why)",
    INVALID: "truncated or inconsistent series (missing slices, aborted transfer, ...); nothing registered or sent",
    EXPIRED: "a CBCT held longer than hold_for_ct_s without a planning CT",
}
TERMINAL_STATES = frozenset({DONE, REFUSED, FAILED, INVALID, EXPIRED})

_SCHEMA = """
CREATE TABLE IF NOT EXISTS series (
    series_uid TEXT PRIMARY KEY, patient_id TEXT, issuer TEXT, patient_name TEXT, study_uid TEXT, for_uid TEXT,
    modality TEXT, series_datetime TEXT, description TEXT, markers TEXT, calling_aets TEXT,
    first_at REAL, last_at REAL, role TEXT, state TEXT, reason TEXT, ct_series_uid TEXT, output_dir TEXT,
    aborted INTEGER DEFAULT 0, hold_until REAL, done_at REAL, attempts INTEGER DEFAULT 0, updated_at REAL);
CREATE TABLE IF NOT EXISTS instances (
    sop_uid TEXT PRIMARY KEY, series_uid TEXT, path TEXT, received_at REAL, calling_aet TEXT, sop_class TEXT,
    ipp TEXT, iop TEXT, rows INTEGER, cols INTEGER, spacing TEXT, images_in_acquisition INTEGER);
CREATE INDEX IF NOT EXISTS instances_series ON instances(series_uid);
CREATE TABLE IF NOT EXISTS sends (
    id INTEGER PRIMARY KEY AUTOINCREMENT, series_uid TEXT, path TEXT, sop_uid TEXT, destination TEXT, state TEXT,
    attempts INTEGER DEFAULT 0, next_at REAL, last_error TEXT, created_at REAL, sent_at REAL, flagged INTEGER);
CREATE TABLE IF NOT EXISTS triggers (
    id INTEGER PRIMARY KEY AUTOINCREMENT, series_uid TEXT, ct_series_uid TEXT, repeat INTEGER, role TEXT,
    requested_at REAL);
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT, at REAL, level TEXT, series_uid TEXT, text TEXT);
CREATE TABLE IF NOT EXISTS service (key TEXT PRIMARY KEY, value TEXT);
"""

_MARKER_DEFAULT = ("SeriesDescription", "ProtocolName", "StationName", "ImageType", "ManufacturerModelName")
MAX_EVENTS = 20000
"""Events kept in the index (the oldest are dropped; the log file keeps everything)."""


def safe_name(text: str, fallback: str = "unknown") -> str:
    """``text`` as one folder name: letters, digits, ``.-_`` kept, anything else ``_`` (at most 64 characters)."""
    name = re.sub(r"[^A-Za-z0-9._-]", "_", text.strip())[:64].strip(".")
    return name or fallback


@dataclass(frozen=True)
class StoredInstance:
    """The outcome of :meth:`Store.add_instance`."""

    series_uid: str
    sop_uid: str
    new_series: bool
    duplicate: bool
    series_state: str


def _text(ds: Any, keyword: str) -> str:
    value = ds.get(keyword, "")
    if value is None:
        return ""
    if not isinstance(value, (str, bytes)) and hasattr(value, "__iter__"):
        return "\\".join(str(v) for v in value)
    return str(value).strip()


def _floats(ds: Any, keyword: str, n: int) -> str | None:
    try:
        values = [float(v) for v in ds.get(keyword) or []]
    except (TypeError, ValueError):
        return None
    return json.dumps(values) if len(values) == n else None


def header_facts(ds: Any, marker_fields: tuple[str, ...] = _MARKER_DEFAULT) -> dict[str, Any]:
    """The header values the index keeps for an instance and its series, from a pydicom dataset."""
    try:
        images = int(ds.get("ImagesInAcquisition")) if ds.get("ImagesInAcquisition") not in (None, "") else None
    except (TypeError, ValueError):
        images = None
    return {
        "sop_uid": _text(ds, "SOPInstanceUID"),
        "sop_class": _text(ds, "SOPClassUID"),
        "series_uid": _text(ds, "SeriesInstanceUID"),
        "patient_id": _text(ds, "PatientID"),
        "issuer": _text(ds, "IssuerOfPatientID"),
        "patient_name": _text(ds, "PatientName"),
        "study_uid": _text(ds, "StudyInstanceUID"),
        "for_uid": _text(ds, "FrameOfReferenceUID"),
        "modality": _text(ds, "Modality"),
        "series_datetime": _text(ds, "SeriesDate") + _text(ds, "SeriesTime"),
        "description": _text(ds, "SeriesDescription"),
        "markers": {k: _text(ds, k) for k in marker_fields if _text(ds, k)},
        "ipp": _floats(ds, "ImagePositionPatient", 3),
        "iop": _floats(ds, "ImageOrientationPatient", 6),
        "rows": int(ds.get("Rows") or 0) or None,
        "cols": int(ds.get("Columns") or 0) or None,
        "spacing": _floats(ds, "PixelSpacing", 2),
        "images_in_acquisition": images,
    }


class Store:
    """The storage folder and its index. Thread-safe (one connection, one lock); a second process (``serve
    status``, ``serve trigger``) opens its own :class:`Store` and may read and add triggers while the service runs.

    Args:
        root: the storage folder (created).
        marker_fields: header fields kept per series for the CBCT markers (``classification.marker_fields``).
        readonly: open the index without creating anything (``serve status``).
    """

    def __init__(self, root: str | Path, marker_fields: tuple[str, ...] = _MARKER_DEFAULT,
                 readonly: bool = False) -> None:
        self.root = Path(root)
        self.marker_fields = tuple(marker_fields)
        self._lock = threading.RLock()
        if readonly:
            if not (self.root / "index.sqlite").is_file():
                from monai_rigidreg.core.errors import InputError

                raise InputError("no index.sqlite here: the service has not run with this storage_dir yet", self.root)
            uri = f"file:{self.root / 'index.sqlite'}?mode=ro"
            self._db = sqlite3.connect(uri, uri=True, timeout=30.0, check_same_thread=False, isolation_level=None)
            return
        for sub in ("instances", "results", "tmp"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(str(self.root / "index.sqlite"), timeout=30.0, check_same_thread=False,
                                   isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")  # a commit is on disk before the C-STORE is acknowledged
        self._db.executescript(_SCHEMA)
        for table, column in (("instances", "sop_class TEXT"), ("triggers", "role TEXT")):  # indexes of before 0.5
            if column.split()[0] not in {r[1] for r in self._db.execute(f"PRAGMA table_info({table})")}:
                self._db.execute(f"ALTER TABLE {table} ADD COLUMN {column}")

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # -- transactions ----------------------------------------------------------------------------------------------
    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    def query(self, sql: str, args: tuple = ()) -> list[dict[str, Any]]:
        with self._lock:
            cur = self._db.execute(sql, args)
            cols = [c[0] for c in cur.description or ()]
            return [dict(zip(cols, row)) for row in cur.fetchall()]

    # -- instances -------------------------------------------------------------------------------------------------
    def write_instance_file(self, series_uid: str, sop_uid: str, data: bytes) -> Path:
        """Write ``data`` (a DICOM Part 10 file) to ``instances/<series>/<sop>.dcm``: written in ``tmp/``, synced,
        renamed into place, the folder synced."""
        folder = self.root / "instances" / safe_name(series_uid)
        new_folder = not folder.is_dir()
        folder.mkdir(parents=True, exist_ok=True)
        final = folder / f"{safe_name(sop_uid)}.dcm"
        part = self.root / "tmp" / f"{safe_name(sop_uid)}.{secrets.token_hex(4)}.part"
        with open(part, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(part, final)
        _fsync_dir(folder)
        if new_folder:
            _fsync_dir(folder.parent)
        return final

    def add_instance(self, facts: dict[str, Any], path: Path, calling_aet: str, now: float | None = None
                     ) -> StoredInstance:
        """Index one received instance (its file already in place). A SOP Instance UID already held is a duplicate
        (the file is the same instance again); a new series starts in ``receiving``; an instance for a series that
        is already complete reopens it only where it was refused as truncated (``invalid``: the sender resent what
        was missing) or was still waiting."""
        now = time.time() if now is None else now
        series_uid, sop_uid = facts["series_uid"], facts["sop_uid"]
        with self.transaction() as db:
            duplicate = db.execute("SELECT 1 FROM instances WHERE sop_uid=?", (sop_uid,)).fetchone() is not None
            row = db.execute("SELECT state, calling_aets FROM series WHERE series_uid=?", (series_uid,)).fetchone()
            if not duplicate:
                db.execute("INSERT INTO instances (sop_uid, series_uid, path, received_at, calling_aet, sop_class, "
                           "ipp, iop, rows, cols, spacing, images_in_acquisition) VALUES (?,?,?,?,?,?,?,?,?,?,?,?)",
                           (sop_uid, series_uid, str(path.relative_to(self.root)), now, calling_aet,
                            facts.get("sop_class", ""), facts["ipp"],
                            facts["iop"], facts["rows"], facts["cols"], facts["spacing"],
                            facts["images_in_acquisition"]))
            if row is None:
                db.execute("INSERT INTO series (series_uid, patient_id, issuer, patient_name, study_uid, for_uid, "
                           "modality, series_datetime, description, markers, calling_aets, first_at, last_at, state, "
                           "updated_at) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                           (series_uid, facts["patient_id"], facts["issuer"], facts["patient_name"],
                            facts["study_uid"], facts["for_uid"], facts["modality"], facts["series_datetime"],
                            facts["description"], json.dumps(facts["markers"]), json.dumps([calling_aet]), now, now,
                            RECEIVING, now))
                return StoredInstance(series_uid, sop_uid, True, duplicate, RECEIVING)
            state, aets = row
            aets = json.loads(aets or "[]")
            if calling_aet not in aets:
                aets.append(calling_aet)
            if not duplicate and state in (INVALID, WAITING_CT, EXPIRED, READY):
                # more of the series arrived (a resend of what was missing, a CT declared complete too early): it is
                # judged again once complete; a CBCT queued, being registered or done is not reopened
                state = RECEIVING
                db.execute("UPDATE series SET state=?, reason=NULL, role=NULL, aborted=0 WHERE series_uid=?",
                           (state, series_uid))
            db.execute("UPDATE series SET last_at=?, calling_aets=?, updated_at=? WHERE series_uid=?",
                       (now, json.dumps(aets), now, series_uid))
            return StoredInstance(series_uid, sop_uid, False, duplicate, state)

    def series_folder(self, series_uid: str) -> Path:
        return self.root / "instances" / safe_name(series_uid)

    def reconcile(self, read_header: Any) -> list[str]:
        """At start: remove unfinished files in ``tmp/`` and index every instance file the index lacks (a crash
        between a file's rename and its index entry). ``read_header(path)`` returns a pydicom dataset. Returns the
        series UIDs touched."""
        for part in (self.root / "tmp").glob("*"):
            part.unlink(missing_ok=True)
        known = {r["path"] for r in self.query("SELECT path FROM instances")}
        touched: list[str] = []
        for folder in sorted((self.root / "instances").iterdir()):
            if not folder.is_dir():
                continue
            for f in sorted(folder.glob("*.dcm")):
                rel = str(f.relative_to(self.root))
                if rel in known:
                    continue
                try:
                    facts = header_facts(read_header(f), self.marker_fields)
                except Exception as exc:  # noqa: BLE001 - a damaged file is set aside, the others indexed
                    logger.warning("instance file %s unreadable at start (%s): not indexed", f, exc)
                    continue
                if not facts["sop_uid"] or not facts["series_uid"]:
                    continue
                self.add_instance(facts, f, "unknown (indexed at start)", now=f.stat().st_mtime)
                touched.append(facts["series_uid"])
        return sorted(set(touched))

    def mark_association(self, series_uids: set[str], aborted: bool) -> None:
        """Record how the last association that sent instances of these series ended."""
        with self.transaction() as db:
            for uid in series_uids:
                db.execute("UPDATE series SET aborted=? WHERE series_uid=?", (int(aborted), uid))

    # -- series ----------------------------------------------------------------------------------------------------
    def series(self, series_uid: str) -> dict[str, Any] | None:
        rows = self.query("SELECT * FROM series WHERE series_uid=?", (series_uid,))
        if not rows:
            return None
        row = dict(rows[0])
        row["n_instances"] = self.query("SELECT COUNT(*) AS n FROM instances WHERE series_uid=?",
                                        (series_uid,))[0]["n"]
        return row

    def facts(self, row: dict[str, Any]) -> SeriesFacts:
        n = row.get("n_instances")
        if n is None:
            n = self.query("SELECT COUNT(*) AS n FROM instances WHERE series_uid=?", (row["series_uid"],))[0]["n"]
        return SeriesFacts(series_uid=row["series_uid"], patient_id=row["patient_id"] or "",
                           issuer=row["issuer"] or "", patient_name=row["patient_name"] or "",
                           study_uid=row["study_uid"] or "", for_uid=row["for_uid"] or "",
                           modality=row["modality"] or "", series_datetime=row["series_datetime"] or "",
                           description=row["description"] or "", markers=json.loads(row["markers"] or "{}"),
                           calling_aets=tuple(json.loads(row["calling_aets"] or "[]")), n_instances=n,
                           first_at=row["first_at"] or 0.0)

    def slices(self, series_uid: str) -> list[SliceFacts]:
        def floats(text: str | None) -> tuple[float, ...] | None:
            return None if text is None else tuple(json.loads(text))

        return [SliceFacts(sop_uid=r["sop_uid"], ipp=floats(r["ipp"]), iop=floats(r["iop"]), rows=r["rows"],
                           cols=r["cols"], spacing=floats(r["spacing"]),
                           images_in_acquisition=r["images_in_acquisition"])
                for r in self.query("SELECT * FROM instances WHERE series_uid=? ORDER BY sop_uid", (series_uid,))]

    def instance_files(self, series_uid: str) -> list[tuple[str, str, Path]]:
        """``(SOP Class UID, SOP Instance UID, file)`` of every instance of a series, in slice order (position along
        the slice normal, where known)."""
        rows = self.query("SELECT sop_class, sop_uid, path, ipp, iop FROM instances WHERE series_uid=?", (series_uid,))

        def position(r: dict[str, Any]) -> float:
            if not r["ipp"] or not r["iop"]:
                return 0.0
            ipp, iop = json.loads(r["ipp"]), json.loads(r["iop"])
            normal = (iop[1] * iop[5] - iop[2] * iop[4], iop[2] * iop[3] - iop[0] * iop[5],
                      iop[0] * iop[4] - iop[1] * iop[3])
            return sum(a * b for a, b in zip(ipp, normal))

        return [(r["sop_class"] or "", r["sop_uid"], self.root / r["path"])
                for r in sorted(rows, key=lambda r: (position(r), r["sop_uid"]))]

    def set_state(self, series_uid: str, state: str, reason: str | None = None, **fields: Any) -> None:
        if state not in STATES:
            raise ValueError(f"unknown state {state!r}")
        now = time.time()
        cols = {"state": state, "reason": reason, "updated_at": now, **fields}
        with self.transaction() as db:
            db.execute(f"UPDATE series SET {', '.join(f'{k}=?' for k in cols)} WHERE series_uid=?",
                       (*cols.values(), series_uid))

    def update(self, series_uid: str, **fields: Any) -> None:
        """Set ``fields`` of a series without changing its state."""
        with self.transaction() as db:
            db.execute(f"UPDATE series SET {', '.join(f'{k}=?' for k in fields)}, updated_at=? WHERE series_uid=?",
                       (*fields.values(), time.time(), series_uid))

    def in_state(self, *states: str) -> list[dict[str, Any]]:
        marks = ",".join("?" * len(states))
        return self.query(f"SELECT * FROM series WHERE state IN ({marks}) ORDER BY first_at", states)

    def ready_cts(self) -> list[SeriesFacts]:
        return [self.facts(r) for r in self.query("SELECT * FROM series WHERE state=? AND role='ct'", (READY,))]

    # -- results and sends -----------------------------------------------------------------------------------------
    def finish_registration(self, series_uid: str, output_dir: Path, reg_path: Path, reg_sop_uid: str,
                            destinations: list[str], flagged: bool, reason: str) -> None:
        """In one transaction: the CBCT ``done`` and one pending send per destination (so a crash cannot leave a
        done series without its sends, nor sends without a done series)."""
        now = time.time()
        with self.transaction() as db:
            db.execute("UPDATE series SET state=?, reason=?, output_dir=?, done_at=?, updated_at=? WHERE "
                       "series_uid=?", (DONE, reason, str(output_dir), now, now, series_uid))
            for dest in destinations:
                db.execute("INSERT INTO sends (series_uid, path, sop_uid, destination, state, attempts, next_at, "
                           "created_at, flagged) VALUES (?,?,?,?,?,?,?,?,?)",
                           (series_uid, str(reg_path), reg_sop_uid, dest, "pending", 0, now, now, int(flagged)))

    def due_sends(self, now: float | None = None) -> list[dict[str, Any]]:
        now = time.time() if now is None else now
        return self.query("SELECT * FROM sends WHERE state='pending' AND next_at<=? ORDER BY id", (now,))

    def next_send_time(self) -> float | None:
        rows = self.query("SELECT MIN(next_at) AS t FROM sends WHERE state='pending'")
        return rows[0]["t"] if rows else None

    def send_done(self, send_id: int) -> None:
        with self.transaction() as db:
            db.execute("UPDATE sends SET state='sent', sent_at=?, attempts=attempts+1, last_error=NULL WHERE id=?",
                       (time.time(), send_id))

    def send_failed(self, send_id: int, error: str, next_at: float) -> None:
        with self.transaction() as db:
            db.execute("UPDATE sends SET attempts=attempts+1, last_error=?, next_at=? WHERE id=?",
                       (error, next_at, send_id))

    # -- triggers --------------------------------------------------------------------------------------------------
    def add_trigger(self, series_uid: str, ct_series_uid: str | None = None, repeat: bool = False,
                    role: str | None = None) -> None:
        """Ask the service to complete (or judge again) a series: ``ct_series_uid`` names the planning CT of a CBCT,
        ``repeat`` registers a registered CBCT again, ``role`` (``"cbct"`` or ``"ct"``) overrides the
        classification."""
        if role not in (None, "cbct", "ct"):
            raise ValueError(f"role must be 'cbct' or 'ct', got {role!r}")
        with self.transaction() as db:
            db.execute("INSERT INTO triggers (series_uid, ct_series_uid, repeat, role, requested_at) "
                       "VALUES (?,?,?,?,?)", (series_uid, ct_series_uid, int(repeat), role, time.time()))

    def take_triggers(self) -> list[dict[str, Any]]:
        """The triggers waiting, oldest first, removed from the index (a read only, when there are none)."""
        if not self.query("SELECT 1 AS x FROM triggers LIMIT 1"):
            return []
        with self.transaction() as db:
            cur = db.execute("SELECT id, series_uid, ct_series_uid, repeat, role, requested_at FROM triggers "
                             "ORDER BY id")
            rows = [dict(zip(("id", "series_uid", "ct_series_uid", "repeat", "role", "requested_at"), r))
                    for r in cur.fetchall()]
            if rows:
                db.execute("DELETE FROM triggers WHERE id<=?", (rows[-1]["id"],))
        return rows

    # -- events and the service's own record ------------------------------------------------------------------------
    def event(self, level: int, text: str, series_uid: str | None = None) -> None:
        """Log ``text`` and keep it in the index's event list (for ``serve status``)."""
        logger.log(level, "%s", text)
        try:
            with self.transaction() as db:
                cur = db.execute("INSERT INTO events (at, level, series_uid, text) VALUES (?,?,?,?)",
                                 (time.time(), logging.getLevelName(level), series_uid, text))
                if cur.lastrowid and cur.lastrowid % 1000 == 0:
                    db.execute("DELETE FROM events WHERE id<=?", (cur.lastrowid - MAX_EVENTS,))
        except sqlite3.Error as exc:  # the log line is out; the index's copy is a convenience
            logger.warning("event not kept in the index (%s)", exc)

    def events(self, limit: int = 20, series_uid: str | None = None) -> list[dict[str, Any]]:
        if series_uid is None:
            rows = self.query("SELECT * FROM events ORDER BY id DESC LIMIT ?", (limit,))
        else:
            rows = self.query("SELECT * FROM events WHERE series_uid=? ORDER BY id DESC LIMIT ?", (series_uid, limit))
        return rows[::-1]

    def set_service(self, **values: Any) -> None:
        with self.transaction() as db:
            for k, v in values.items():
                db.execute("INSERT OR REPLACE INTO service (key, value) VALUES (?, ?)", (k, json.dumps(v)))

    def service_record(self) -> dict[str, Any]:
        return {r["key"]: json.loads(r["value"]) for r in self.query("SELECT key, value FROM service")}


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
