"""Registering many pairs in one process, the network loaded once: ``register --datalist`` and the bundle's
inference ``evaluator``.

:func:`registration_pairs` turns the bundle's ``fixed``/``moving`` (one pair) or ``datalist`` (a JSON list of pairs)
into the ``dataset``; :class:`RegistrationEvaluator` registers each pair with
:func:`~monai_rigidreg.registration.files.register_files` and reports the ones that failed. One pair writes its outputs
into ``output_dir`` itself (as ``monai-rigidreg register`` does); several write one sub-folder each (their ``case_id``,
else their index). A failing pair is reported and skipped: it leaves no partial output (the outputs of a pair appear
only when complete), and the others go on.
"""

from __future__ import annotations

import json
import logging
import re
import time
from pathlib import Path
from typing import Any

from tqdm.auto import tqdm

from monai_rigidreg.core.errors import InputError, RigidRegError
from monai_rigidreg.registration.files import register_files
from monai_rigidreg.registration.registrar import RigidRegistrar

__all__ = ["registration_pairs", "RegistrationEvaluator", "BatchFailures"]

logger = logging.getLogger(__name__)

_SAFE = re.compile(r"[^A-Za-z0-9._+-]+")


def registration_pairs(fixed: str | Path | None = None, moving: str | Path | None = None,
                       datalist: str | Path | None = None, dataset_dir: str | Path = ".") -> list[dict[str, Any]]:
    """The pairs to register: ``[{"fixed": path, "moving": path, "case_id": str}, ...]``.

    Args:
        fixed, moving: one pair (CT and CBCT paths: NIfTI, MHA, NRRD or DICOM folders).
        datalist: instead, a JSON file holding a list of ``{"fixed", "moving"}`` items (optionally ``case_id``,
            ``fixed_series_uid``, ``moving_series_uid``), or a MONAI datalist with such items under ``"training"``,
            ``"validation"`` or ``"test"``; relative paths are taken from ``dataset_dir``.
        dataset_dir: folder that relative paths in ``datalist`` start from.

    Raises:
        InputError: neither a pair nor a datalist, both, an unreadable datalist or an item without both paths.
    """
    pair_given = bool(fixed) or bool(moving)
    if datalist and pair_given:
        raise InputError("give either fixed/moving (one pair) or a datalist of pairs, not both")
    if not datalist:
        return [{"fixed": str(fixed or ""), "moving": str(moving or ""), "case_id": "pair"}]
    path = Path(datalist)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"unreadable datalist ({exc})", path) from exc
    if isinstance(data, dict):
        data = next((data[k] for k in ("test", "validation", "training") if isinstance(data.get(k), list)), None)
    if not isinstance(data, list) or not data:
        raise InputError("a datalist of pairs must be a non-empty list of {\"fixed\", \"moving\"} items", path)
    root = Path(dataset_dir)
    items = []
    for i, item in enumerate(data):
        if not isinstance(item, dict) or not item.get("fixed") or not item.get("moving"):
            raise InputError(f"item {i} of the datalist lacks 'fixed' or 'moving'", path)
        items.append({**item, "fixed": str(root / item["fixed"]), "moving": str(root / item["moving"]),
                      "case_id": str(item.get("case_id", f"{i:04d}")), "from_datalist": True})
    return items


class RegistrationEvaluator:
    """Register every pair of ``dataset`` with one loaded ``registrar`` and write each pair's outputs.

    Args:
        registrar: the loaded network (the bundle's ``registrar``).
        dataset: :func:`registration_pairs`.
        output_dir: where the outputs go (one pair: this folder; several: a sub-folder per pair).
        refine, overwrite, qc, fine_stage, isocenter, reg, transform_format, allow_other_patient: as for
            :func:`~monai_rigidreg.registration.files.register_files`.
        progress: a progress bar over the pairs (with more than one).
    """

    def __init__(self, registrar: RigidRegistrar, dataset: list[dict[str, Any]], output_dir: str | Path,
                 refine: bool = False, overwrite: bool = False, qc: bool = True, fine_stage: bool | None = None,
                 isocenter: Any = None, reg: str = "auto", transform_format: str = "tfm",
                 progress: bool = True, patient_position: str | None = None, global_init: bool | None = None,
                 roi: Any = None, match: str = "soft", keep_couch: bool = False,
                 allow_swapped: bool = False, allow_other_patient: bool = False) -> None:
        self.registrar = registrar
        self.dataset = list(dataset)
        self.output_dir = Path(output_dir)
        self.options = {"refine": refine, "overwrite": overwrite, "qc": qc, "fine_stage": fine_stage,
                        "isocenter": isocenter, "reg": reg, "transform_format": transform_format,
                        "patient_position": patient_position, "global_init": global_init, "roi": roi,
                        "match": match, "keep_couch": keep_couch, "allow_swapped": allow_swapped,
                        "allow_other_patient": allow_other_patient}
        self.progress = progress
        # one folder per pair for a datalist (even of one pair), the folder itself for a single --fixed/--moving pair
        self.subfolders = len(self.dataset) > 1 or any(item.get("from_datalist") for item in self.dataset)
        names = [self._folder_name(i) for i in range(len(self.dataset))]
        clashes = sorted({n for n in names if names.count(n) > 1})
        if self.subfolders and clashes:
            raise InputError(f"case ids that name the same output folder: {clashes} (folders are the case ids with "
                             "characters other than letters, digits, '.', '_', '+', '-' replaced by '_'); make them "
                             "distinct")

    def _folder_name(self, index: int) -> str:
        name = _SAFE.sub("_", str(self.dataset[index]["case_id"])).lstrip(".")
        return name or f"{index:04d}"

    def output_dir_for(self, index: int) -> Path:
        """The output folder of pair ``index``: ``output_dir/<case_id>`` (sanitised, never hidden or ``..``) for a
        datalist, ``output_dir`` itself for a single pair."""
        return self.output_dir / self._folder_name(index) if self.subfolders else self.output_dir

    def run(self) -> dict[str, Any]:
        """Register all pairs; returns ``{"done": [...], "failed": [{"case_id", "error"}], "cases_per_second"}``.

        Raises:
            RigidRegError: for a single pair, its error as it is (nothing to skip to).
        """
        done: list[str] = []
        failed: list[dict[str, str]] = []
        t0 = time.perf_counter()
        bar = tqdm(self.dataset, desc="register", unit="pair", disable=not self.progress or len(self.dataset) < 2)
        for i, item in enumerate(bar):
            try:
                register_files(self.registrar, item["fixed"], item["moving"], self.output_dir_for(i),
                               fixed_series_uid=item.get("fixed_series_uid"),
                               moving_series_uid=item.get("moving_series_uid"), **self.options)
                done.append(item["case_id"])
            except (RigidRegError, OSError) as exc:  # bad input or a file-system refusal: this pair only
                if not self.subfolders:
                    raise
                logger.error("pair %s skipped: %s", item["case_id"], exc)
                failed.append({"case_id": item["case_id"], "error": str(exc)})
        seconds = time.perf_counter() - t0
        summary = {"done": done, "failed": failed, "seconds": round(seconds, 3),
                   "cases_per_second": round(len(self.dataset) / seconds, 3) if seconds > 0 else float("nan")}
        if len(self.dataset) > 1:
            logger.info("registered %d of %d pairs (%.2f pairs per second)", len(done), len(self.dataset),
                        summary["cases_per_second"])
        if failed:
            raise BatchFailures(summary)
        return summary


class BatchFailures(RigidRegError):
    """Some pairs of a batch failed (the others completed); ``summary`` says which and why."""

    def __init__(self, summary: dict[str, Any]) -> None:
        self.summary = summary
        names = ", ".join(f["case_id"] for f in summary["failed"])
        n = len(summary["failed"]) + len(summary["done"])
        super().__init__(f"{len(summary['failed'])} of {n} pairs failed and were skipped ({names}); the other "
                         f"{len(summary['done'])} completed")
