"""The running service: the SCP, a monitor (completion timeouts, triggers, held CBCTs, heartbeat), one registration
worker with the model loaded once, and a sender that retries with backoff.

Threads: pynetdicom runs one thread per association (the SCP stores and indexes, nothing more); the monitor thread
makes every decision about series (so they are made one at a time); the worker registers one CBCT at a time; the
sender sends the REG objects. Every state change goes through the index first, so a restart resumes from it:
series still arriving get a fresh completion window, CBCTs queued or being registered are queued again (a
registration cut off is redone into a clean folder; its REG had not been sent), and REG objects not yet sent are
sent.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import shutil
import threading
import time
from datetime import datetime
from pathlib import Path
from typing import Any

from monai_rigidreg import __version__
from monai_rigidreg.serve import store as st
from monai_rigidreg.serve.config import ServeConfig
from monai_rigidreg.serve.rules import check_series_complete, choose_ct, classify_series
from monai_rigidreg.serve.scp import StorageSCP
from monai_rigidreg.serve.sender import backoff_s, send_file
from monai_rigidreg.serve.store import Store, StoredInstance, safe_name

__all__ = ["Service", "POLL_S", "HEARTBEAT_S"]

logger = logging.getLogger("monai_rigidreg.serve")

POLL_S = 0.1
"""How often the monitor looks at triggers and completion times (seconds)."""
HEARTBEAT_S = 2.0
"""How often the service writes its heartbeat into the index (``serve status`` calls it running within 5x this)."""


class Service:
    """The registration service on one configuration.

    Args:
        cfg: the configuration.
        registrar: a loaded :class:`~monai_rigidreg.RigidRegistrar` to use (default: loaded by the worker at start,
            then warmed up with one registration of a generated pair where ``registration.warm_up``).
    """

    def __init__(self, cfg: ServeConfig, registrar: Any = None) -> None:
        self.cfg = cfg
        self.store = Store(cfg.storage_dir, cfg.classification.marker_fields)
        self.registrar = registrar
        self._warm_up = cfg.warm_up and registrar is None
        self.model_ready = threading.Event()
        self._queue: queue.Queue[str | None] = queue.Queue()
        self._stop = threading.Event()
        self._wake_monitor = threading.Event()
        self._wake_sender = threading.Event()
        self._threads: list[threading.Thread] = []
        self.scp = StorageSCP(cfg, self.store, self._stored, self.event)
        self._started = False

    # -- life cycle ------------------------------------------------------------------------------------------------
    def start(self) -> None:
        """Resume from the index, start listening and the threads. Returns at once (the model loads in the
        worker; instances are received meanwhile)."""
        self._lock_storage()
        try:
            self._start()
        except BaseException:
            self._unlock_storage()
            raise

    def _start(self) -> None:
        from pydicom import dcmread

        pynetdicom_log = logging.getLogger("pynetdicom")
        if pynetdicom_log.level == logging.NOTSET:  # it logs every association and message at INFO; the events here
            pynetdicom_log.setLevel(logging.WARNING)  # say what matters, once
        touched = self.store.reconcile(lambda p: dcmread(str(p), stop_before_pixels=True))
        if touched:
            self.event(logging.WARNING, f"indexed instance files a previous run had stored but not indexed: series "
                                        f"{', '.join(touched)}")
        now = time.time()
        for row in self.store.in_state(st.RECEIVING):
            self.store.set_state(row["series_uid"], st.RECEIVING, last_at=now)
            self.event(logging.INFO, f"series {row['series_uid']}: {self._count(row['series_uid'])} instance(s) held "
                                     f"from before the restart; complete {self.cfg.completion_timeout_s:g} s after "
                                     "its last new instance", row["series_uid"])
        for row in self.store.in_state(st.QUEUED, st.REGISTERING):
            if row["state"] == st.REGISTERING:
                self.store.set_state(row["series_uid"], st.QUEUED, row["reason"])
            self.event(logging.INFO, f"CBCT {row['series_uid']}: queued again after the restart (its registration "
                                     "had not finished)", row["series_uid"])
            self._queue.put(row["series_uid"])
        pending = self.store.query("SELECT COUNT(*) AS n FROM sends WHERE state='pending'")[0]["n"]
        if pending:
            self.event(logging.INFO, f"{pending} REG send(s) pending from before the restart")
        self.scp.start()
        self.store.set_service(pid=os.getpid(), started_at=now, heartbeat=now, version=__version__,
                               ae_title=self.cfg.ae_title, host=self.cfg.host, port=self.scp.port, model="loading",
                               stopped_at=None, config=str(self.cfg.source) if self.cfg.source else None)
        for name, target in (("monitor", self._monitor), ("worker", self._worker), ("sender", self._sender)):
            t = threading.Thread(target=target, name=f"rigidreg-serve-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        self._started = True
        self.event(logging.INFO, f"listening as {self.cfg.ae_title} on {self.cfg.host}:{self.scp.port} (allowed: "
                                 f"{', '.join(self.cfg.allowed_ae_titles)}; REG to "
                                 f"{', '.join(map(str, self.cfg.destinations)) or 'no destination (results on disk)'};"
                                 f" storage {self.cfg.storage_dir})")

    def stop(self, timeout: float = 120.0) -> None:
        """Stop listening, let a registration in progress finish (up to ``timeout``), stop the threads."""
        if not self._started:
            self.store.close()
            return
        self.scp.stop()
        self._stop.set()
        self._queue.put(None)
        self._wake_monitor.set()
        self._wake_sender.set()
        end = time.monotonic() + timeout
        for t in self._threads:
            t.join(max(0.1, end - time.monotonic()))
        alive = [t.name for t in self._threads if t.is_alive()]
        self.store.set_service(stopped_at=time.time(), model="stopped")
        self.event(logging.INFO, "stopped" + (f" (still running: {', '.join(alive)})" if alive else ""))
        self._started = False
        if not alive:
            self.store.close()
        self._unlock_storage()

    def _lock_storage(self) -> None:
        """One service per storage folder: a second would register the same series again."""
        from monai_rigidreg.core.errors import InputError

        self._lock_file = open(self.cfg.storage_dir / "service.lock", "a+")  # noqa: SIM115 - held while running
        try:
            import fcntl
        except ImportError:  # pragma: no cover - not POSIX: no lock
            return
        try:
            fcntl.flock(self._lock_file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self._lock_file.close()
            pid = self.store.service_record().get("pid")
            raise InputError(f"another service is running on this storage_dir (pid {pid}): one service per "
                             "storage folder", self.cfg.storage_dir) from None

    def _unlock_storage(self) -> None:
        lock = getattr(self, "_lock_file", None)
        if lock is not None and not lock.closed:
            lock.close()  # releases the lock

    def trigger(self, series_uid: str, ct_series_uid: str | None = None, repeat: bool = False,
                role: str | None = None) -> None:
        """The explicit trigger (what ``serve trigger`` does from another process)."""
        self.store.add_trigger(series_uid, ct_series_uid, repeat, role)
        self._wake_monitor.set()

    def event(self, level: int, text: str, series_uid: str | None = None) -> None:
        self.store.event(level, text, series_uid)

    # -- receiving -------------------------------------------------------------------------------------------------
    def _stored(self, stored: StoredInstance, calling: str, facts: dict) -> None:
        if stored.new_series:
            self.event(logging.INFO, f"receiving series {stored.series_uid} from {calling!r}: Modality "
                                     f"{facts['modality'] or '?'}, {facts['description'] or 'no description'!r}, "
                                     f"Patient ID {facts['patient_id']!r}", stored.series_uid)
        elif stored.duplicate:
            logger.debug("instance %s of series %s received again (kept once)", stored.sop_uid, stored.series_uid)
        elif stored.series_state in (st.QUEUED, st.REGISTERING, st.DONE):
            self.event(logging.WARNING, f"new instance {stored.sop_uid} for series {stored.series_uid}, which is "
                                        f"already {stored.series_state}: stored, not registered again (serve trigger "
                                        "--repeat registers it again)", stored.series_uid)

    def _count(self, series_uid: str) -> int:
        return self.store.query("SELECT COUNT(*) AS n FROM instances WHERE series_uid=?", (series_uid,))[0]["n"]

    # -- the monitor: every decision about a series ----------------------------------------------------------------
    def _monitor(self) -> None:
        beat = 0.0
        while not self._stop.is_set():
            try:
                for t in self.store.take_triggers():
                    self._on_trigger(t)
                now = time.time()
                for row in self.store.in_state(st.RECEIVING):
                    if row["last_at"] + self.cfg.completion_timeout_s <= now:
                        self._complete(row["series_uid"], f"no new instance for {self.cfg.completion_timeout_s:g} s")
                for row in self.store.in_state(st.WAITING_CT):
                    if row["hold_until"] is not None and row["hold_until"] <= now:
                        self.store.set_state(row["series_uid"], st.EXPIRED, row["reason"])
                        self.event(logging.WARNING, f"CBCT {row['series_uid']} (Patient ID {row['patient_id']!r}): "
                                                    f"held {self.cfg.hold_for_ct_s:g} s without a planning CT; not "
                                                    "registered (send the CT, then serve trigger --series UID)",
                                   row["series_uid"])
                if now - beat >= HEARTBEAT_S:
                    self.store.set_service(heartbeat=now, queued=self._queue.qsize())
                    beat = now
            except Exception:  # noqa: BLE001 - the monitor must survive anything one series does
                logger.exception("monitor")
            self._wake_monitor.wait(POLL_S)
            self._wake_monitor.clear()

    def _on_trigger(self, t: dict[str, Any]) -> None:
        uid, ct = t["series_uid"], t["ct_series_uid"]
        row = self.store.series(uid)
        if row is None:
            self.event(logging.WARNING, f"trigger for series {uid}: no such series received")
            return
        state = row["state"]
        self.event(logging.INFO, f"trigger for series {uid} ({state}" + (f", planning CT {ct}" if ct else "")
                   + (", repeat" if t["repeat"] else "") + (f", as {t['role']}" if t.get("role") else "") + ")", uid)
        if state in (st.QUEUED, st.REGISTERING):
            self.event(logging.INFO, f"series {uid} is already {state}", uid)
        elif state == st.DONE and not t["repeat"]:
            self.event(logging.WARNING, f"CBCT {uid} is already registered ({row['output_dir']}); serve trigger "
                                        "--repeat registers it again", uid)
        elif state == st.READY and not t.get("role"):
            self.event(logging.INFO, f"planning CT {uid} is already complete", uid)
        elif row["role"] == "cbct" and state in (st.DONE, st.WAITING_CT, st.REFUSED, st.FAILED, st.EXPIRED) \
                and not t.get("role"):
            self._assign(uid, ct, "trigger")
        else:  # receiving, invalid, a refused classification, or a role given: judge the series again
            self._complete(uid, "explicit trigger", explicit_ct=ct, role=t.get("role"))

    def _complete(self, uid: str, why: str, explicit_ct: str | None = None, role: str | None = None) -> None:
        row = self.store.series(uid)
        if row is None:
            return
        facts = self.store.facts(row)
        who = f"series {uid} (Patient ID {facts.patient_id!r}, {facts.n_instances} image(s), {why})"
        if role is None:
            role, reason = classify_series(facts, self.cfg.classification)
        else:
            reason = f"role {role} given by the trigger"
        if role is None:
            self.store.set_state(uid, st.REFUSED, f"not classified: {reason}", role=None)
            self.event(logging.WARNING, f"{who} refused: cannot tell a CBCT from a planning CT: {reason} (serve "
                                        "trigger --as cbct|ct decides)", uid)
            return
        problem = check_series_complete(self.store.slices(uid), self.cfg.min_slices, aborted=bool(row["aborted"]))
        if problem:
            self.store.set_state(uid, st.INVALID, problem, role=role)
            self.event(logging.ERROR, f"{who}: {'CBCT' if role == 'cbct' else 'planning CT'} truncated or "
                                      f"inconsistent, nothing registered or sent: {problem}", uid)
            return
        if role == "ct":
            self.store.set_state(uid, st.READY, reason, role="ct")
            self.event(logging.INFO, f"{who}: planning CT complete ({reason})", uid)
            for cbct in self.store.in_state(st.WAITING_CT):
                if cbct["patient_id"] == facts.patient_id:
                    self._assign(cbct["series_uid"], None, f"planning CT {uid} arrived")
            return
        self.store.update(uid, role="cbct")
        self.event(logging.INFO, f"{who}: CBCT complete ({reason})", uid)
        self._assign(uid, explicit_ct, "complete")

    def _assign(self, uid: str, explicit_ct: str | None, why: str) -> None:
        row = self.store.series(uid)
        cbct = self.store.facts(row)
        choice = choose_ct(cbct, self.store.ready_cts(), self.cfg.ct_selection, explicit_ct)
        if choice.state == "chosen":
            ct = choice.ct
            if ct.patient_name and cbct.patient_name and ct.patient_name != cbct.patient_name:
                self.event(logging.WARNING, f"CBCT {uid} and planning CT {ct.series_uid} share Patient ID "
                                            f"{cbct.patient_id!r} but not the Patient's Name ({cbct.patient_name!r} "
                                            f"and {ct.patient_name!r})", uid)
            self.store.set_state(uid, st.QUEUED, f"planning CT {ct.series_uid}: {choice.reason}",
                                 ct_series_uid=ct.series_uid)
            self.event(logging.INFO, f"CBCT {uid} ({why}): planning CT {ct.series_uid} chosen ({choice.reason}); "
                                     "queued", uid)
            self._queue.put(uid)
        elif choice.state == "hold":
            until = row["hold_until"] or (time.time() + self.cfg.hold_for_ct_s)
            self.store.set_state(uid, st.WAITING_CT, choice.reason, hold_until=until)
            self.event(logging.WARNING, f"CBCT {uid} held: {choice.reason}; registered when its planning CT arrives, "
                                        f"until {datetime.fromtimestamp(until):%Y-%m-%d %H:%M:%S}", uid)
        else:
            self.store.set_state(uid, st.REFUSED, choice.reason)
            self.event(logging.WARNING, f"CBCT {uid} refused: {choice.reason}", uid)

    # -- the worker: registrations, one at a time, with the model loaded once --------------------------------------
    def _load_model(self) -> None:
        from monai_rigidreg.serve import _pipeline

        t0 = time.perf_counter()
        if self.registrar is None:
            self.registrar = _pipeline.load_registrar(self.cfg)
            loaded = time.perf_counter() - t0
            warm = _pipeline.warm_up(self.registrar) if self._warm_up else 0.0
            self.event(logging.INFO, f"model loaded in {loaded:.1f} s" + (f", warmed up in {warm:.1f} s"
                                                                           if self._warm_up else ""))
        self.store.set_service(model="ready")
        self.model_ready.set()

    def _worker(self) -> None:
        try:
            self._load_model()
        except BaseException as exc:  # noqa: BLE001 - without a model nothing registers: said loudly, service stays up
            self.event(logging.CRITICAL, f"the registration model could not be loaded: {exc}; series are received "
                                         "and kept but not registered (fix and restart)")
            self.store.set_service(model=f"failed: {exc}")
            return
        while True:
            uid = self._queue.get()
            if uid is None or self._stop.is_set():
                return
            row = self.store.series(uid)
            if row is None or row["state"] != st.QUEUED:
                continue  # queued twice (a trigger and a completion), or no longer wanted
            try:
                self._register(row)
            except Exception:  # noqa: BLE001 - one bad series never stops the others
                logger.exception("registration of %s", uid)

    def _output_dir(self, row: dict[str, Any]) -> Path:
        base = self.cfg.storage_dir / "results" / safe_name(row["patient_id"] or "", "no_patient_id") / safe_name(
            row["series_uid"])
        if row["done_at"] is None:
            # what a registration a crash cut off left (its folder, the hidden folder it was writing): never sent,
            # redone from scratch
            for left in [base, *base.parent.glob(f".{base.name}.*")] if base.parent.is_dir() else []:
                if left.is_dir():
                    shutil.rmtree(left)
            return base
        k = 2
        while base.with_name(f"{base.name}.{k}").exists():  # --repeat: the earlier results stay
            k += 1
        return base.with_name(f"{base.name}.{k}")

    def _register(self, row: dict[str, Any]) -> None:
        from monai_rigidreg.core.errors import RigidRegError
        from monai_rigidreg.serve import _pipeline

        uid, ct_uid = row["series_uid"], row["ct_series_uid"]
        out = self._output_dir(row)
        self.store.set_state(uid, st.REGISTERING, row["reason"], attempts=(row["attempts"] or 0) + 1,
                             output_dir=str(out))
        self.event(logging.INFO, f"registering CBCT {uid} to planning CT {ct_uid} (Patient ID {row['patient_id']!r})",
                   uid)
        context = {"cbct_series_uid": uid, "ct_series_uid": ct_uid, "patient_id": row["patient_id"],
                   "ct_choice": row["reason"], "service_version": __version__}
        try:
            done = _pipeline.register_series(
                self.registrar, (self.store.series_folder(ct_uid), self.store.instance_files(ct_uid)),
                (self.store.series_folder(uid), self.store.instance_files(uid)), out, self.cfg, context)
        except RigidRegError as exc:
            self.store.set_state(uid, st.FAILED, str(exc))
            self.event(logging.ERROR, f"registration of CBCT {uid} failed: {exc}; nothing sent", uid)
            return
        except Exception as exc:  # noqa: BLE001
            self.store.set_state(uid, st.FAILED, f"internal error: {type(exc).__name__}: {exc}")
            self.event(logging.ERROR, f"registration of CBCT {uid} failed with an internal error "
                                      f"({type(exc).__name__}: {exc}); nothing sent", uid)
            logger.debug("traceback", exc_info=True)
            return
        summary, flags = done["summary"], done["flags"]
        p = summary["params"]
        couch = summary.get("couch_shift", {}).get("6dof", {})
        text = (f"registered CBCT {uid} to planning CT {ct_uid} in {done['seconds']:.2f} s: "
                f"t=({p['tx']:.2f}, {p['ty']:.2f}, {p['tz']:.2f}) mm r=({p['rx']:.2f}, {p['ry']:.2f}, {p['rz']:.2f}) "
                f"deg, confidence {summary.get('confidence') or 0:.2f}"
                + (f", couch lat/long/vert {couch['lateral']:.1f}/{couch['longitudinal']:.1f}/{couch['vertical']:.1f}"
                   " mm" if couch else "") + f"; outputs in {out}")
        if flags:
            text += f"; FLAGGED ({'; '.join(flags)}): REG labelled {_pipeline.REG_LABEL_FLAGGED}"
        reason = f"REG {done['reg_sop_uid']}" + (f", FLAGGED: {'; '.join(flags)}" if flags else "")
        self.store.finish_registration(uid, out, done["reg_path"], done["reg_sop_uid"],
                                       [json.dumps(d.__dict__) for d in self.cfg.destinations], bool(flags), reason)
        self.event(logging.WARNING if flags else logging.INFO, text, uid)
        self._wake_sender.set()

    # -- the sender: every REG reaches every destination, retried with backoff -------------------------------------
    def _sender(self) -> None:
        while not self._stop.is_set():
            try:
                for send in self.store.due_sends():
                    if self._stop.is_set():
                        return
                    self._send(send)
            except Exception:  # noqa: BLE001
                logger.exception("sender")
            nxt = self.store.next_send_time()
            wait = 1.0 if nxt is None else min(1.0, max(0.0, nxt - time.time()))
            self._wake_sender.wait(wait)
            self._wake_sender.clear()

    def _send(self, send: dict[str, Any]) -> None:
        dest = json.loads(send["destination"])
        where = f"{dest['ae_title']}@{dest['host']}:{dest['port']}"
        ok, what = send_file(send["path"], dest["ae_title"], dest["host"], dest["port"], self.cfg.ae_title)
        label = "FLAGGED REG" if send["flagged"] else "REG"
        if ok:
            self.store.send_done(send["id"])
            self.event(logging.WARNING if send["flagged"] else logging.INFO,
                       f"{label} {send['sop_uid']} of CBCT {send['series_uid']} sent to {where} ({what})",
                       send["series_uid"])
            return
        attempts = send["attempts"] + 1
        delay = backoff_s(attempts, self.cfg.send_retry_initial_s, self.cfg.send_retry_max_s)
        self.store.send_failed(send["id"], what, time.time() + delay)
        self.event(logging.WARNING, f"{label} {send['sop_uid']} of CBCT {send['series_uid']} not sent to {where}: "
                                    f"{what}; retry in {delay:.3g} s (attempt {attempts}); kept in {send['path']}",
                   send["series_uid"])
