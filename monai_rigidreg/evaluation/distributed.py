"""An evaluation of a datalist split across the processes of a ``torch.distributed`` group (``torchrun``; the
bundle's ``configs/multi_gpu_evaluate.json``): each process registers its share of the cases (a sampler's indices,
MONAI's ``DistributedSampler`` without padding), draws their overlays into the one report folder, and hands its
results to rank 0, which merges them in datalist order and writes the report once: the same ``cases.csv``,
``summary.json``, ``report.md`` and ``report.html`` as :func:`~monai_rigidreg.evaluation.evaluate.evaluate_datalist`
in one process, each case once.

Every process makes the same read-only checks first (:func:`~monai_rigidreg.evaluation.evaluate.checked_items`), so
a bad input stops all of them before any collective call; a registration that fails in one process is reported by
every process after the exchange (none waits forever for it).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from monai_rigidreg.core.errors import RigidRegError
from monai_rigidreg.evaluation.evaluate import REPORT_FILES, checked_items, register_cases, report_cases
from monai_rigidreg.evaluation.overlays import DEFAULT_MAX_OVERLAYS, OVERLAY_DIR, OverlayGallery
from monai_rigidreg.io.staging import staged_output_dir

__all__ = ["evaluate_distributed", "rank_share", "DistributedEvaluationError"]


class DistributedEvaluationError(RigidRegError):
    """A process of a distributed evaluation failed; raised by every process, naming the ranks and their errors."""


def rank_share(n_items: int, rank: int, world: int, sampler: Iterable[int] | None = None) -> list[int]:
    """The datalist positions this rank registers: the sampler's indices below ``n_items`` (``max_cases``), else
    every ``world``-th position from ``rank``."""
    if sampler is None:
        return list(range(rank, n_items, world))
    return [int(i) for i in sampler if int(i) < n_items]


def evaluate_distributed(
    datalist: str | Path,
    methods: Sequence[str] = ("network",),
    output_dir: str | Path | None = None,
    registrar: Any = None,
    sampler: Iterable[int] | None = None,
    max_cases: int | None = None,
    key: str | None = None,
    progress: bool = False,
    html: bool = True,
    max_overlays: int = DEFAULT_MAX_OVERLAYS,
    overwrite: bool = False,
    peer_mask: bool | None = None,
) -> dict[str, Any]:
    """:func:`~monai_rigidreg.evaluation.evaluate.evaluate_datalist` across an initialised process group (without
    one: that function, in this process).

    Args:
        datalist, methods, output_dir, max_cases, key, progress, html, overwrite, peer_mask: as
            ``evaluate_datalist``.
        registrar: this process's :class:`~monai_rigidreg.registration.RigidRegistrar` (each rank builds its own,
            on its own device).
        sampler: this rank's datalist positions (a ``DistributedSampler`` over the datalist's items with
            ``even_divisible=False, shuffle=False``, so that the ranks' shares together hold every case once);
            default every ``world``-th case from the rank's own.
        max_overlays: over all ranks (each draws at most its share).

    Returns:
        on every rank, the merged ``{"summary", "report", "cases", "paths"}`` (the paths exist once rank 0 has moved
        the report into place); ``cases`` in datalist order, each case's methods in ``methods`` order.

    Raises:
        InputError, OutputExistsError: as ``evaluate_datalist``, on every rank before any registration.
        DistributedEvaluationError: a rank failed while registering (every rank raises it; no report is written).
    """
    import torch.distributed as dist

    from monai_rigidreg.evaluation.evaluate import evaluate_datalist

    if not (dist.is_available() and dist.is_initialized()):
        return evaluate_datalist(datalist, methods, output_dir, registrar=registrar, max_cases=max_cases, key=key,
                                 progress=progress, html=html, max_overlays=max_overlays, overwrite=overwrite,
                                 peer_mask=peer_mask)
    methods = list(methods)
    items = checked_items(datalist, methods, output_dir, max_cases, key, max_overlays, overwrite)
    rank, world = dist.get_rank(), dist.get_world_size()
    share = rank_share(len(items), rank, world, sampler)
    out = Path(output_dir) if output_dir is not None else None
    staging = (staged_output_dir(out, overwrite, replaceable=REPORT_FILES) if out is not None and rank == 0
               else contextlib.nullcontext(None))
    with staging as tmp:
        holder = [str(tmp) if tmp is not None else None]
        dist.broadcast_object_list(holder, src=0)  # rank 0's staging folder, where every rank's overlays go
        folder = Path(holder[0]) if holder[0] is not None else None
        per_rank_cap = max_overlays // world + (rank < max_overlays % world)
        gallery = (OverlayGallery(folder / OVERLAY_DIR, methods, max_others=per_rank_cap)
                   if html and folder is not None else None)
        try:
            cases = register_cases([items[i] for i in share], methods, registrar, progress, gallery, index_of=share,
                                   peer_mask=peer_mask)
            mine: dict[str, Any] = {"share": share, "cases": cases, "images": dict(gallery.images) if gallery else {},
                                    "omitted": gallery.omitted if gallery else 0}
        except Exception as exc:  # every rank learns of it in the exchange below instead of waiting
            mine = {"error": f"{type(exc).__name__}: {exc}"}
        gathered: list[Any] = [None] * world
        dist.all_gather_object(gathered, mine)
        errors = [f"rank {r}: {g['error']}" for r, g in enumerate(gathered) if "error" in g]
        if errors:
            raise DistributedEvaluationError("distributed evaluation failed (" + "; ".join(errors) + ")")
        result = _merge(gathered, len(items), len(methods), items, datalist, folder if rank == 0 else None, html)
    if out is not None and folder is not None:
        result["paths"] = {k: out / Path(v).relative_to(folder) for k, v in result["paths"].items()}
    return result


def _merge(gathered: list[dict[str, Any]], n_items: int, n_methods: int, items: list[dict[str, Any]],
           datalist: str | Path, folder: Path | None, html: bool) -> dict[str, Any]:
    """The ranks' results in datalist order, each position exactly once; the report written into ``folder`` (rank
    0's staging folder; ``None``: nowhere)."""
    by_position: dict[int, list[Any]] = {}
    images: dict[int, Path] = {}
    omitted = 0
    for g in gathered:
        for k, position in enumerate(g["share"]):
            if position in by_position:
                raise DistributedEvaluationError(f"case {position} was given to two ranks: the sampler must not "
                                                 "pad (DistributedSampler(even_divisible=False))")
            by_position[position] = g["cases"][k * n_methods:(k + 1) * n_methods]
        images.update(g["images"])
        omitted += g["omitted"]
    missing = sorted(set(range(n_items)) - set(by_position))
    if missing:
        names = ", ".join(str(items[i].get("case_id", i)) for i in missing[:5])
        raise DistributedEvaluationError(f"{len(missing)} case(s) were given to no rank ({names}): the sampler must "
                                         "cover the whole datalist")
    cases = [c for position in range(n_items) for c in by_position[position]]
    overlays = images if html and folder is not None else None
    return report_cases(cases, folder, datalist, overlays, omitted)
