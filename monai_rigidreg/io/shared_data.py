"""Where to find the optional real CT volumes (not shipped with the package)."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["DATA_ENV_VAR", "TRAINING_CTS", "HELD_OUT_CTS", "shared_data_dir", "find_data_file", "training_ct_paths"]

DATA_ENV_VAR = "MONAI_RIGIDREG_DATA"

TRAINING_CTS = ("abdomen_pelvis_totalsegmentator_example_ct", "head_tcia_cptac_lscc_ct", "thorax_tcia_cptac_pda_ct",
                "abdomen_pelvis_tcia_tcga_ov_ct")
"""The real CTs (file stems in the data folder) the shipped network (``configs/train_context.json``) trains on:
``scripts/train_context_model.sh`` (which repeats the list; ``tests/test_training_cts.py`` keeps the two equal), the
coarse pretraining and the context network's ablation scripts."""

HELD_OUT_CTS = ("thorax_4dct_phase00_itkelastix", "head_tigre_ct")
"""The real CTs no training reads: the held-out pair of every accuracy figure since 0.4.x."""


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


def training_ct_paths(folder: Path | str) -> list[Path]:
    """The :data:`TRAINING_CTS` present in ``folder`` (``<stem>.nii.gz``), in that order.

    >>> training_ct_paths("/nonexistent")
    []
    """
    folder = Path(folder)
    return [folder / f"{n}.nii.gz" for n in TRAINING_CTS if (folder / f"{n}.nii.gz").is_file()]
