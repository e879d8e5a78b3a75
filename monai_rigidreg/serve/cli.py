"""``monai-rigidreg serve``: DICOM registration service: receive CT and CBCT series, register each CBCT, send the REG.

A DICOM Storage SCP that keeps the planning CTs it receives, registers every complete CBCT series to its patient's
planning CT with the model loaded once, writes the results (result.json with the couch shifts, the QC figure,
registration.dcm) per registration and sends the DICOM Spatial Registration to the configured destinations.
Configuration: one JSON file (monai-rigidreg serve example-config prints one; docs/serve.md describes every key).
ACTION: run (the default), status, trigger, example-config.

Run the service, or ask it for its status, or trigger a series::

    monai-rigidreg serve --config serve.json                 run (until SIGTERM or Ctrl-C)
    monai-rigidreg serve status --config serve.json [--echo] [--json]
    monai-rigidreg serve trigger --config serve.json --series UID [--ct UID] [--repeat] [--as cbct|ct] [--wait S]
    monai-rigidreg serve example-config [--storage-dir DIR]

This module imports nothing heavy at the top (``monai-rigidreg --help`` imports it to build its parser): pynetdicom
is imported when the service starts or ``status --echo`` runs, torch and MONAI when the service loads its model.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

from monai_rigidreg.core.command_text import add_command

__all__ = ["add_parser", "run", "EXIT_NOT_RUNNING"]

EXIT_NOT_RUNNING = 3
"""``serve status``: the service is not running or does not answer; ``serve trigger --wait``: the series did not end
registered (refused, invalid, failed, held, or still running when the wait ended)."""

_EPILOG = ("serve status exits with 3 where the service is not running (no heartbeat in the last 10 s) or, with "
           "--echo, does not answer C-ECHO; serve trigger --wait exits with 3 where the series did not end registered.")


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = add_command(subparsers, "serve", __doc__, run, epilog=_EPILOG)
    p.add_argument("--config", type=Path, default=None, help="the service's configuration file (JSON)")
    actions = p.add_subparsers(dest="serve_action", metavar="ACTION")
    run_p = actions.add_parser("run", help="run the service (the default action)")
    status = actions.add_parser("status", help="the service's state from its index: running, series, pending sends",
                                epilog=_EPILOG)
    status.add_argument("--echo", action="store_true", help="also C-ECHO the service (as its own AE title)")
    status.add_argument("--json", action="store_true", help="print the status as JSON")
    status.add_argument("--series", default=None, metavar="UID", help="the state and events of one series")
    trigger = actions.add_parser("trigger", help="complete a series now, or judge it again",
                                 description="Treat a series as complete now (a CBCT is registered at once), or judge "
                                 "a held, refused, failed or invalid one again. The service reads the trigger from its "
                                 "index within 0.1 s (a stopped service at its next start).", epilog=_EPILOG)
    trigger.add_argument("--series", required=True, metavar="UID", help="Series Instance UID (CBCT or planning CT)")
    trigger.add_argument("--ct", default=None, metavar="UID",
                         help="the planning CT to register this CBCT to (settles an ambiguous choice)")
    trigger.add_argument("--repeat", action="store_true", help="register a CBCT that is already registered again")
    trigger.add_argument("--as", dest="role", choices=("cbct", "ct"), default=None,
                         help="take the series as a CBCT or a planning CT whatever the classification says")
    trigger.add_argument("--wait", type=float, default=None, metavar="S",
                         help="wait up to S seconds for the outcome and print it")
    example = actions.add_parser("example-config", help="print a configuration with every key")
    example.add_argument("--storage-dir", default="/var/lib/monai-rigidreg", metavar="DIR",
                         help="the storage folder the printed configuration names (default: /var/lib/monai-rigidreg)")
    for sub in (run_p, status, trigger):
        sub.add_argument("--config", type=Path, default=argparse.SUPPRESS,
                         help="the service's configuration file (JSON)")
    for sub in (run_p, status, trigger, example):
        sub.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS, help="more log output")
        sub.add_argument("-q", "--quiet", action="count", default=argparse.SUPPRESS, help="less log output")
    return p


def run(args: argparse.Namespace) -> int:
    action = getattr(args, "serve_action", None) or "run"
    if action == "example-config":
        from monai_rigidreg.serve.config import example_config

        print(json.dumps(example_config(args.storage_dir), indent=2))
        return 0
    from monai_rigidreg.core.errors import InputError
    from monai_rigidreg.serve.config import load_config

    if args.config is None:
        raise InputError(f"serve {action}: --config FILE is required (monai-rigidreg serve example-config prints one)")
    cfg = load_config(args.config)
    if action == "status":
        return _status(cfg, args)
    if action == "trigger":
        return _trigger(cfg, args)
    return _serve(cfg, args)


def _serve(cfg: Any, args: argparse.Namespace) -> int:
    from monai_rigidreg.serve.service import Service

    root = logging.getLogger()
    if cfg.log_file is not None:
        cfg.log_file.parent.mkdir(parents=True, exist_ok=True)
        handler = logging.FileHandler(cfg.log_file, encoding="utf-8")
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        root.addHandler(handler)
    service = Service(cfg)
    service.start()
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt as exc:  # Ctrl-C, and SIGTERM (cli.main turns it into Terminated): an orderly stop
        logging.getLogger("monai_rigidreg.serve").info("stopping (%s)", type(exc).__name__)
    finally:
        service.stop()
    return 0


def _open_index(cfg: Any, readonly: bool) -> Any:
    from monai_rigidreg.core.errors import InputError
    from monai_rigidreg.serve.store import Store

    if not cfg.index_path.is_file():
        raise InputError(f"no index at {cfg.index_path}: the service has not run with this storage_dir yet")
    return Store(cfg.storage_dir, cfg.classification.marker_fields, readonly=readonly)


def service_status(cfg: Any, echo: bool = False, series: str | None = None) -> dict[str, Any]:
    """What ``serve status`` prints, as a dictionary (``running``, ``healthy``, ``service``, ``series_states``,
    ``pending_sends``, ``attention`` (series held, refused, invalid or failed), ``recent_events``)."""
    from monai_rigidreg.serve.service import HEARTBEAT_S

    store = _open_index(cfg, readonly=True)
    try:
        record = store.service_record()
        now = time.time()
        beat = record.get("heartbeat")
        running = (record.get("stopped_at") is None and beat is not None and now - beat < 5 * HEARTBEAT_S
                   and _alive(record.get("pid")))
        out: dict[str, Any] = {
            "running": running,
            "service": {**record, "heartbeat_age_s": None if beat is None else round(now - beat, 1)},
            "series_states": {r["state"]: r["n"] for r in store.query(
                "SELECT state, COUNT(*) AS n FROM series GROUP BY state ORDER BY state")},
            "pending_sends": [{k: r[k] for k in ("series_uid", "sop_uid", "destination", "attempts", "last_error",
                                                 "path")} | {"next_try_in_s": round(max(0.0, r["next_at"] - now), 1)}
                              for r in store.query("SELECT * FROM sends WHERE state='pending' ORDER BY id")],
            "sent": store.query("SELECT COUNT(*) AS n FROM sends WHERE state='sent'")[0]["n"],
            "attention": [{k: r[k] for k in ("series_uid", "patient_id", "role", "state", "reason")}
                          for r in store.query("SELECT * FROM series WHERE state IN ('waiting_ct', 'refused', "
                                               "'invalid', 'failed', 'expired') ORDER BY updated_at DESC LIMIT 20")],
            "recent_events": [f"{time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(e['at']))} {e['level']} "
                              f"{e['text']}" for e in store.events(15)],
        }
        if series is not None:
            row = store.series(series)
            out["series"] = None if row is None else {
                **{k: row[k] for k in ("series_uid", "patient_id", "role", "state", "reason", "ct_series_uid",
                                       "output_dir", "n_instances")},
                "sends": store.query("SELECT destination, state, attempts, last_error FROM sends WHERE series_uid=?",
                                     (series,)),
                "events": [e["text"] for e in store.events(50, series)]}
    finally:
        store.close()
    out["healthy"] = running and out["service"].get("model") == "ready"
    if echo:
        from monai_rigidreg.serve.sender import echo as c_echo

        host = "127.0.0.1" if cfg.host in ("0.0.0.0", "", "::") else cfg.host
        ok, what = c_echo(cfg.ae_title, host, out["service"].get("port") or cfg.port, cfg.ae_title)
        out["echo"] = what
        out["healthy"] = out["healthy"] and ok
    return out


def _alive(pid: Any) -> bool:
    if not isinstance(pid, int):
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _status(cfg: Any, args: argparse.Namespace) -> int:
    out = service_status(cfg, echo=args.echo, series=args.series)
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        s = out["service"]
        print(f"service: {'running' if out['running'] else 'NOT RUNNING'} (pid {s.get('pid')}, "
              f"{s.get('ae_title')} on {s.get('host')}:{s.get('port')}, model {s.get('model')}, last heartbeat "
              f"{s.get('heartbeat_age_s')} s ago)" + (f"; {out['echo']}" if "echo" in out else ""))
        print("series: " + (", ".join(f"{k} {v}" for k, v in out["series_states"].items()) or "none"))
        print(f"REG sends: {out['sent']} sent, {len(out['pending_sends'])} pending")
        for p in out["pending_sends"]:
            print(f"  pending: REG of {p['series_uid']} to {p['destination']}: {p['attempts']} attempt(s), next in "
                  f"{p['next_try_in_s']} s, last error: {p['last_error']}")
        for a in out["attention"]:
            print(f"  {a['state']}: {a['series_uid']} (Patient ID {a['patient_id']!r}): {a['reason']}")
        if out.get("series") is not None:
            print(json.dumps(out["series"], indent=2))
        print("recent events:")
        for e in out["recent_events"]:
            print(f"  {e}")
    return 0 if out["healthy"] else EXIT_NOT_RUNNING


def _trigger(cfg: Any, args: argparse.Namespace) -> int:
    from monai_rigidreg.core.errors import InputError

    store = _open_index(cfg, readonly=False)
    try:
        row = store.series(args.series)
        if row is None:
            known = [r["series_uid"] for r in store.query("SELECT series_uid FROM series ORDER BY last_at DESC "
                                                          "LIMIT 10")]
            raise InputError(f"no series {args.series} received (latest: {', '.join(known) or 'none'})")
        if args.ct is not None and store.series(args.ct) is None:
            raise InputError(f"no series {args.ct} received (--ct)")
        start = time.time()
        store.add_trigger(args.series, args.ct, args.repeat, args.role)
        print(f"trigger for series {args.series} ({row['state']}) handed to the service", flush=True)
        if args.wait is None:
            return 0
        end = start + args.wait
        while time.time() < end:
            row = store.series(args.series)
            if row["updated_at"] > start and row["state"] in ("done", "refused", "invalid", "failed", "expired",
                                                              "waiting_ct", "ready"):
                break
            time.sleep(0.1)
        print(json.dumps({k: row[k] for k in ("series_uid", "role", "state", "reason", "ct_series_uid",
                                               "output_dir")}, indent=2))
        return 0 if row["state"] in ("done", "ready") and row["updated_at"] > start else EXIT_NOT_RUNNING
    finally:
        store.close()
