"""The service's configuration: one JSON file, checked as a whole before anything starts.

Every key, its type and its default is in :data:`EXAMPLE` (``monai-rigidreg serve example-config`` prints it) and in
``docs/serve.md``. Unknown keys are refused (a typo would otherwise silently keep a default), and so is any value of
the wrong type or range, with one line naming the key.
"""

from __future__ import annotations

import copy
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from monai_rigidreg.core.errors import InputError

__all__ = ["ServeConfig", "Destination", "Classification", "CtSelection", "Thresholds", "load_config",
           "config_from_dict", "example_config", "EXAMPLE"]

EXAMPLE: dict[str, Any] = {
    "ae_title": "RIGIDREG",
    "host": "0.0.0.0",
    "port": 11112,
    "allowed_ae_titles": ["CONSOLE1", "PACS"],
    "destinations": [{"ae_title": "PACS", "host": "pacs.example.org", "port": 104}],
    "storage_dir": "/var/lib/monai-rigidreg",
    "completion_timeout_s": 10.0,
    "hold_for_ct_s": 86400.0,
    "min_slices": 16,
    "classification": {
        "cbct_ae_titles": [],
        "ct_ae_titles": [],
        "cbct_markers": ["CBCT", "CONE BEAM", "CONEBEAM", "CONE-BEAM"],
        "marker_fields": ["SeriesDescription", "ProtocolName", "StationName", "ImageType", "ManufacturerModelName"],
        "unmarked": "ct",
    },
    "ct_selection": {"same_study": "ignore", "several": "refuse"},
    "thresholds": {"confidence": 0.5, "translation_mm": 20.0, "rotation_deg": 5.0},
    "registration": {"device": "auto", "threads": None, "bundle": None, "qc": True, "warm_up": True},
    "send_retry_initial_s": 5.0,
    "send_retry_max_s": 300.0,
    "log_file": None,
}
"""A complete configuration with every key at its default, except the site's own (AE titles, hosts, folders)."""

_AE_PATTERN = re.compile(r"[ -~]{1,16}")  # DICOM AE: 1-16 printable ASCII characters, no backslash
_CHOICES = {"unmarked": ("ct", "refuse"), "same_study": ("ignore", "prefer", "require"),
            "several": ("refuse", "newest")}


@dataclass(frozen=True)
class Destination:
    """A DICOM node that receives the REG objects by C-STORE."""

    ae_title: str
    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.ae_title}@{self.host}:{self.port}"


@dataclass(frozen=True)
class Classification:
    """How a CT Image Storage series is told to be a CBCT or a planning CT (:func:`~monai_rigidreg.serve.rules.
    classify_series`)."""

    cbct_ae_titles: tuple[str, ...] = ()
    ct_ae_titles: tuple[str, ...] = ()
    cbct_markers: tuple[str, ...] = ("CBCT", "CONE BEAM", "CONEBEAM", "CONE-BEAM")
    marker_fields: tuple[str, ...] = ("SeriesDescription", "ProtocolName", "StationName", "ImageType",
                                      "ManufacturerModelName")
    unmarked: str = "ct"


@dataclass(frozen=True)
class CtSelection:
    """Which planning CT a CBCT is registered to, after the Patient ID (:func:`~monai_rigidreg.serve.rules.
    choose_ct`)."""

    same_study: str = "ignore"
    several: str = "refuse"


@dataclass(frozen=True)
class Thresholds:
    """A result is flagged (REG Content Label ``RIGIDREG_FLAGGED``) when the package flags it, when its confidence
    is below ``confidence``, or when the correction exceeds ``translation_mm`` (length of the couch translation) or
    ``rotation_deg`` (largest angle); ``None`` leaves a limit out."""

    confidence: float | None = 0.5
    translation_mm: float | None = 20.0
    rotation_deg: float | None = 5.0


@dataclass(frozen=True)
class ServeConfig:
    """The service's settings (see :data:`EXAMPLE` and ``docs/serve.md``)."""

    storage_dir: Path
    allowed_ae_titles: tuple[str, ...]
    ae_title: str = "RIGIDREG"
    host: str = "0.0.0.0"
    port: int = 11112
    destinations: tuple[Destination, ...] = ()
    completion_timeout_s: float = 10.0
    hold_for_ct_s: float = 86400.0
    min_slices: int = 16
    classification: Classification = field(default_factory=Classification)
    ct_selection: CtSelection = field(default_factory=CtSelection)
    thresholds: Thresholds = field(default_factory=Thresholds)
    device: str = "auto"
    threads: int | None = None
    bundle: Path | None = None
    qc: bool = True
    warm_up: bool = True
    send_retry_initial_s: float = 5.0
    send_retry_max_s: float = 300.0
    log_file: Path | None = None
    source: Path | None = None

    @property
    def index_path(self) -> Path:
        return self.storage_dir / "index.sqlite"


def load_config(path: str | Path) -> ServeConfig:
    """Read and check a configuration file (JSON). Relative paths in it are relative to the file's folder.

    Raises:
        InputError: the file is missing or not JSON, or a key is unknown, missing or of the wrong type or range.
    """
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("no such configuration file", p) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"unreadable configuration file ({exc})", p) from exc
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON: {exc}", p) from exc
    try:
        return config_from_dict(data, base=p.parent.resolve(), source=p)
    except InputError as exc:
        raise InputError(f"configuration: {exc.reason}", p) from None


def config_from_dict(data: Any, base: Path | None = None, source: Path | None = None) -> ServeConfig:
    """A :class:`ServeConfig` from the parsed JSON ``data`` (relative paths resolved against ``base``)."""
    d = _Section(data, "")
    registration = _Section(d.pop("registration", {}), "registration.")
    classification = _Section(d.pop("classification", {}), "classification.")
    selection = _Section(d.pop("ct_selection", {}), "ct_selection.")
    thresholds = _Section(d.pop("thresholds", {}), "thresholds.")
    base = base or Path.cwd()
    cfg = ServeConfig(
        storage_dir=_path(d.pop("storage_dir", required=True), base),
        allowed_ae_titles=_ae_list(d.pop("allowed_ae_titles", required=True), "allowed_ae_titles", nonempty=True),
        ae_title=_ae(d.pop("ae_title", "RIGIDREG"), "ae_title"),
        host=_text(d.pop("host", "0.0.0.0"), "host"),
        port=_int(d.pop("port", 11112), "port", 1, 65535),
        destinations=tuple(_destination(v, f"destinations[{k}]")
                           for k, v in enumerate(_list(d.pop("destinations", []), "destinations"))),
        completion_timeout_s=_number(d.pop("completion_timeout_s", 10.0), "completion_timeout_s", 0.1),
        hold_for_ct_s=_number(d.pop("hold_for_ct_s", 86400.0), "hold_for_ct_s", 0.0),
        min_slices=_int(d.pop("min_slices", 16), "min_slices", 3, 100000),
        classification=Classification(
            cbct_ae_titles=_ae_list(classification.pop("cbct_ae_titles", []), "classification.cbct_ae_titles"),
            ct_ae_titles=_ae_list(classification.pop("ct_ae_titles", []), "classification.ct_ae_titles"),
            cbct_markers=tuple(_text(v, "classification.cbct_markers").upper() for v in _list(
                classification.pop("cbct_markers", list(Classification.cbct_markers)), "classification.cbct_markers")),
            marker_fields=tuple(_keyword(v, "classification.marker_fields") for v in _list(
                classification.pop("marker_fields", list(Classification.marker_fields)),
                "classification.marker_fields")),
            unmarked=_choice(classification.pop("unmarked", "ct"), "classification.unmarked", "unmarked"),
        ),
        ct_selection=CtSelection(
            same_study=_choice(selection.pop("same_study", "ignore"), "ct_selection.same_study", "same_study"),
            several=_choice(selection.pop("several", "refuse"), "ct_selection.several", "several"),
        ),
        thresholds=Thresholds(
            confidence=_optional_number(thresholds.pop("confidence", 0.5), "thresholds.confidence", 0.0, 1.0),
            translation_mm=_optional_number(thresholds.pop("translation_mm", 20.0), "thresholds.translation_mm", 0.0),
            rotation_deg=_optional_number(thresholds.pop("rotation_deg", 5.0), "thresholds.rotation_deg", 0.0),
        ),
        device=_text(registration.pop("device", "auto"), "registration.device"),
        threads=_optional_int(registration.pop("threads", None), "registration.threads", 1),
        bundle=_optional_path(registration.pop("bundle", None), base, "registration.bundle"),
        qc=_bool(registration.pop("qc", True), "registration.qc"),
        warm_up=_bool(registration.pop("warm_up", True), "registration.warm_up"),
        send_retry_initial_s=_number(d.pop("send_retry_initial_s", 5.0), "send_retry_initial_s", 0.01),
        send_retry_max_s=_number(d.pop("send_retry_max_s", 300.0), "send_retry_max_s", 0.01),
        log_file=_optional_path(d.pop("log_file", None), base, "log_file"),
        source=source,
    )
    for section in (d, registration, classification, selection, thresholds):
        section.check_empty()
    if cfg.send_retry_max_s < cfg.send_retry_initial_s:
        raise InputError("send_retry_max_s must not be below send_retry_initial_s")
    clash = set(cfg.classification.cbct_ae_titles) & set(cfg.classification.ct_ae_titles)
    if clash:
        raise InputError(f"classification: AE title(s) {sorted(clash)} are listed as both CBCT and CT senders")
    return cfg


def example_config(storage_dir: str = "/var/lib/monai-rigidreg") -> dict[str, Any]:
    """:data:`EXAMPLE` with ``storage_dir`` set (a copy)."""
    out = copy.deepcopy(EXAMPLE)
    out["storage_dir"] = storage_dir
    return out


class _Section:
    """The keys of one JSON object, popped as they are read; what is left at the end is unknown."""

    def __init__(self, data: Any, prefix: str) -> None:
        if not isinstance(data, dict):
            raise InputError(f"{prefix.rstrip('.') or 'the configuration'} must be a JSON object, got "
                             f"{type(data).__name__}")
        self.data, self.prefix = dict(data), prefix

    _MISSING = object()

    def pop(self, key: str, default: Any = _MISSING, required: bool = False) -> Any:
        if key not in self.data:
            if required or default is self._MISSING:
                raise InputError(f"{self.prefix}{key} is required")
            return default
        return self.data.pop(key)

    def check_empty(self) -> None:
        if self.data:
            raise InputError(f"unknown key(s) {', '.join(self.prefix + k for k in sorted(self.data))} (see "
                             "'monai-rigidreg serve example-config' for the known ones)")


def _text(value: Any, key: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"{key} must be a non-empty string, got {value!r}")
    return value.strip()


def _keyword(value: Any, key: str) -> str:
    text = _text(value, key)
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9]*", text):
        raise InputError(f"{key}: {text!r} is not a DICOM attribute keyword (e.g. SeriesDescription)")
    return text


def _ae(value: Any, key: str) -> str:
    text = value.strip() if isinstance(value, str) else ""
    if not _AE_PATTERN.fullmatch(text) or "\\" in text:
        raise InputError(f"{key} must be a DICOM AE title (1 to 16 printable ASCII characters, no backslash), got "
                         f"{value!r}")
    return text


def _list(value: Any, key: str) -> list[Any]:
    if not isinstance(value, list):
        raise InputError(f"{key} must be a JSON list, got {value!r}")
    return value


def _ae_list(value: Any, key: str, nonempty: bool = False) -> tuple[str, ...]:
    titles = tuple(_ae(v, key) for v in _list(value, key))
    if nonempty and not titles:
        raise InputError(f"{key} must name at least one AE title: associations from any other are refused")
    return titles


def _number(value: Any, key: str, low: float | None = None, high: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value:
        raise InputError(f"{key} must be a number, got {value!r}")
    if (low is not None and value < low) or (high is not None and value > high):
        bounds = f"at least {low}" if high is None else f"between {low} and {high}"
        raise InputError(f"{key} must be {bounds}, got {value!r}")
    return float(value)


def _optional_number(value: Any, key: str, low: float | None = None, high: float | None = None) -> float | None:
    return None if value is None else _number(value, key, low, high)


def _int(value: Any, key: str, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise InputError(f"{key} must be a whole number from {low} to {high}, got {value!r}")
    return value


def _optional_int(value: Any, key: str, low: int) -> int | None:
    return None if value is None else _int(value, key, low, 4096)


def _bool(value: Any, key: str) -> bool:
    if not isinstance(value, bool):
        raise InputError(f"{key} must be true or false, got {value!r}")
    return value


def _choice(value: Any, key: str, kind: str) -> str:
    if value not in _CHOICES[kind]:
        raise InputError(f"{key} must be one of {list(_CHOICES[kind])}, got {value!r}")
    return value


def _path(value: Any, base: Path) -> Path:
    p = Path(_text(value, "storage_dir")).expanduser()
    return p if p.is_absolute() else base / p


def _optional_path(value: Any, base: Path, key: str) -> Path | None:
    if value is None:
        return None
    p = Path(_text(value, key)).expanduser()
    return p if p.is_absolute() else base / p


def _destination(value: Any, key: str) -> Destination:
    d = _Section(value, key + ".")
    out = Destination(ae_title=_ae(d.pop("ae_title", required=True), key + ".ae_title"),
                      host=_text(d.pop("host", required=True), key + ".host"),
                      port=_int(d.pop("port", required=True), key + ".port", 1, 65535))
    d.check_empty()
    return out
