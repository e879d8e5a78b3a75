"""Where to find the optional real CT volumes (not shipped with the package)."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["DATA_ENV_VAR", "shared_data_dir", "find_data_file"]

DATA_ENV_VAR = "MONAI_RIGIDREG_DATA"


def shared_data_dir() -> Path | None:
    """Directory of real CT volumes: ``$MONAI_RIGIDREG_DATA``, else ``../shared/data`` beside the working directory
    or beside the source checkout (``monai_rigidreg/io/`` is three levels below the folder holding both); ``None`` if
    none exists."""
    candidates = []
    if os.environ.get(DATA_ENV_VAR):
        candidates.append(Path(os.environ[DATA_ENV_VAR]))
    candidates += [Path.cwd().parent / "shared" / "data", Path(__file__).resolve().parents[3] / "shared" / "data"]
    for c in candidates:
        if c.is_dir():
            return c
    return None


def find_data_file(name: str) -> Path | None:
    """Path of ``name`` in :func:`shared_data_dir`, or ``None`` if absent."""
    d = shared_data_dir()
    if d is None or not (d / name).is_file():
        return None
    return d / name
