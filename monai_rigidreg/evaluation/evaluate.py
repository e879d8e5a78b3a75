"""Run registration methods over a datalist with known motion and report the paper's tables.

Methods: ``network`` (the bundle's model, cascade steps as configured), ``network+refine`` (network, then
SimpleITK Mattes MI from its estimate), ``sitk`` (classical SimpleITK, geometry-centred initialisation),
``elastix`` (itk-elastix's default rigid map, optional extra), and the peer tools ``ants`` (ANTs' rigid preset,
``antspyx``) and ``greedy`` (``greedy -a -dof 6``, ``picsl-greedy``; both the ``bench`` extra,
:mod:`monai_rigidreg.registration.peers`). All are measured on the same cases in one run.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk
from tqdm.auto import tqdm

from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import (
    Grid,
    grid_points,
    mask_points,
    matrix_to_params,
    recenter_params,
    target_registration_error,
)
from monai_rigidreg.evaluation.html_report import write_html_report
from monai_rigidreg.evaluation.overlays import DEFAULT_MAX_OVERLAYS, OVERLAY_DIR, OverlayGallery
from monai_rigidreg.evaluation.report import CaseResult, format_report, summarize, write_report
from monai_rigidreg.io.staging import check_replaceable, staged_output_dir
from monai_rigidreg.io.volumes import check_output_dir, load_volume
from monai_rigidreg.registration.classical import elastix_available, register_elastix, register_sitk
from monai_rigidreg.registration.peers import PEER_METHODS, peer_available, register_peer
from monai_rigidreg.registration.registrar import RigidRegistrar

__all__ = ["METHODS", "evaluate_datalist", "load_datalist", "body_points", "LoadedCase", "iter_cases",
           "checked_items", "register_cases", "report_cases", "REPORT_FILES"]

logger = logging.getLogger(__name__)

METHODS = ("network", "network-thorough", "network-regression", "network+refine", "sitk", "elastix", "ants",
           "greedy")
"""``network``: the shipped network (regression + fine stage) on the default path (network-led where the registrar's
``network_leads``); ``network-thorough``: the same network on the thorough path (``register(..., thorough=True)``:
the global search, further starts and the swapped-input estimate on every pair); ``network-regression``: its learned
regression alone (``register(..., fine_stage=False)``); ``network+refine``: the network then SimpleITK Mattes MI;
``sitk``, ``elastix``: the classical baselines from the identity; ``ants``, ``greedy``: the peer tools' rigid
registrations from the identity (:mod:`~monai_rigidreg.registration.peers`)."""


def load_datalist(path: str | Path, key: str | None = None) -> tuple[list[dict[str, Any]], Path]:
    """Items of a MONAI datalist (``key``, else the first of ``test``, ``validation``, ``training``), with paths
    resolved against the datalist's folder."""
    p = Path(path)
    if not p.is_file():
        raise InputError("datalist not found", p)
    try:
        data = json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON ({exc})", p) from exc
    keys = [key] if key else ["test", "validation", "training"]
    for k in keys:
        if isinstance(data, dict) and k in data:
            items = data[k]
            break
    else:
        raise InputError(f"datalist has none of the keys {keys}", p)
    if not isinstance(items, list) or not items:
        raise InputError(f"datalist key {k!r} holds no cases (expected a non-empty list of items with 'fixed', "
                         f"'moving' and the ground truth; got {json.dumps(items)[:60]})", p)
    out = []
    for i, item in enumerate(items):
        if not isinstance(item, dict):
            raise InputError(f"item {i} of {k!r} is not an object with 'fixed' and 'moving'", p)
        for need in ("fixed", "moving"):
            if need not in item:
                raise InputError(f"item {i} has no {need!r}", p)
        it = dict(item)
        for k in ("fixed", "moving", "moving_fov"):
            if k in it and not Path(it[k]).is_absolute():
                it[k] = str(p.parent.resolve() / it[k])
        out.append(it)
    return out, p.parent


def _finite(value: Any, shape: tuple[int, ...]) -> np.ndarray | None:
    """``value`` as a float64 array of ``shape`` with finite entries, else ``None``."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return a if a.shape == shape and bool(np.all(np.isfinite(a))) else None


def true_params(item: dict[str, Any], center: np.ndarray, name: str | None = None,
                path: str | Path | None = None) -> np.ndarray:
    """Ground truth of a datalist item expressed about ``center`` (the fixed image centre): its ``matrix`` (a rigid
    4x4, last row ``0 0 0 1``), else its ``params`` (six finite numbers, about its ``center`` where given).

    Raises:
        InputError: no ground truth or a malformed one, naming the item (``name``; default its ``case_id``) and the
            datalist ``path``.
    """
    name = name or f"datalist item {item.get('case_id', '?')}"
    if "matrix" in item:
        matrix = _finite(item["matrix"], (4, 4))
        if matrix is None or not np.allclose(matrix[3], [0, 0, 0, 1]):
            raise InputError(f"{name}: 'matrix' must be 4x4 finite numbers with a last row 0 0 0 1", path)
        try:
            return matrix_to_params(matrix, center)
        except ValueError as exc:
            raise InputError(f"{name}: 'matrix' is not a rigid transform ({exc})", path) from exc
    if "params" in item:
        params = _finite(item["params"], (6,))
        if params is None:
            raise InputError(f"{name}: 'params' must be six finite numbers (tx ty tz mm, rx ry rz degrees), got "
                             f"{item['params']!r}", path)
        c0 = _finite(item.get("center", center), (3,))
        if c0 is None:
            raise InputError(f"{name}: 'center' must be three finite numbers (LPS mm)", path)
        return recenter_params(params, c0, center)
    raise InputError(f"{name} has no ground truth ('params' or 'matrix')", path)


def check_ground_truth(items: Sequence[dict[str, Any]], path: str | Path | None = None) -> None:
    """Every item's ground truth usable (:func:`true_params`) before anything is registered.

    Raises:
        InputError: naming the first item that has none or a malformed one.
    """
    for i, item in enumerate(items):
        true_params(item, np.zeros(3), f"item {i} ({item.get('case_id', Path(str(item.get('moving', '?'))).name)})",
                    path)


def body_points(fixed: sitk.Image, threshold_hu: float = -400.0, max_points: int = 5000) -> np.ndarray:
    """Physical points (mm) inside the body of a CT: voxels above ``threshold_hu`` (subsampled)."""
    mask = sitk.BinaryThreshold(fixed, threshold_hu, 1e9, 1, 0)
    try:
        return mask_points(mask, max_points=max_points)
    except ValueError:
        logger.warning("no voxel above %g HU: TRE over the whole fixed grid instead", threshold_hu)
        return grid_points(Grid.from_sitk(fixed), 8)


@dataclass
class LoadedCase:
    """One datalist item read from disk, with its ground truth about the fixed image centre.

    Attributes:
        item: the datalist entry; case_id: its ``case_id`` (else the moving file's name).
        fixed, moving: the volumes (float32); fov: the CBCT field-of-view mask (uint8) if the item names one.
        center: fixed image centre (LPS mm); truth: ``(tx, ty, tz, rx, ry, rz)`` about it; points: the fixed
            image's body points (mm) over which TRE is measured.
    """

    item: dict[str, Any]
    case_id: str
    fixed: sitk.Image
    moving: sitk.Image
    fov: sitk.Image | None
    center: np.ndarray
    truth: np.ndarray
    points: np.ndarray


def iter_cases(items: Iterable[dict[str, Any]]) -> Iterator[LoadedCase]:
    """Read the items of :func:`load_datalist` one by one; a fixed image (and its body points) shared by
    consecutive items is read once (datalists group cases by object)."""
    fixed_path, fixed, points = None, None, None
    for item in items:
        if item["fixed"] != fixed_path:
            fixed_path, fixed = item["fixed"], load_volume(item["fixed"])
            points = body_points(fixed)
        moving = load_volume(item["moving"])
        fov = load_volume(item["moving_fov"], pixel_type=sitk.sitkUInt8) if "moving_fov" in item else None
        center = Grid.from_sitk(fixed).center()
        yield LoadedCase(item, str(item.get("case_id", Path(item["moving"]).name)), fixed, moving, fov, center,
                         true_params(item, center), points)


def evaluate_datalist(
    datalist: str | Path,
    methods: Sequence[str] = ("network",),
    output_dir: str | Path | None = None,
    bundle: str | Path | None = None,
    device: str = "auto",
    max_cases: int | None = None,
    key: str | None = None,
    registrar: Any = None,
    progress: bool = True,
    html: bool = True,
    max_overlays: int = DEFAULT_MAX_OVERLAYS,
    overwrite: bool = False,
    peer_mask: bool | None = None,
) -> dict[str, Any]:
    """Register every case with every method and report.

    Args:
        datalist: MONAI datalist JSON with ``fixed``, ``moving`` and ground truth (``params``/``matrix``/``center``).
        methods: any of :data:`METHODS`.
        output_dir: where ``cases.csv``, ``summary.json``, ``report.md`` and ``report.html`` go (nothing written
            if ``None``).
        bundle: bundle directory for the network methods (default: the shipped one).
        device: for the network.
        max_cases: evaluate only the first N cases.
        key: datalist key (default: ``test``, ``validation`` or ``training``, the first present).
        registrar: a ready :class:`~monai_rigidreg.registration.RigidRegistrar` (overrides ``bundle``).
        progress: show a progress bar.
        html: also write ``report.html``, with overlays in ``report_files/`` drawn while each case is loaded.
        max_overlays: overlays for cases that neither failed nor were flagged (those always get one).
        overwrite: replace an ``output_dir`` holding an earlier report (only one: a folder that also holds other
            files is refused). The report is written aside and moved into place at the end
            (:func:`~monai_rigidreg.io.staging.staged_output_dir`): a failed or interrupted run leaves ``output_dir``
            as it was.
        peer_mask: whether the peer tools (``ants``, ``greedy``) get the CBCT's field of view as their moving mask
            (``None``: each tool's :data:`~monai_rigidreg.registration.peers.PEER_FOV_MASK`).

    Returns:
        ``{"summary": ..., "report": markdown text, "cases": [CaseResult, ...], "paths": {...}}``.

    Raises:
        InputError: an unknown method, a bad ``max_cases`` / ``max_overlays``, a datalist that cannot be used.
        OutputExistsError: ``output_dir`` is not empty and ``overwrite`` is False, or holds files other than a
            report's (:data:`REPORT_FILES`).
    """
    items = checked_items(datalist, methods, output_dir, max_cases, key, max_overlays, overwrite)
    if any(m.startswith("network") for m in methods) and registrar is None:
        registrar = RigidRegistrar.from_bundle(bundle, device=device)
    if output_dir is None:
        return _evaluate_into(None, items, methods, registrar, progress, html, max_overlays, datalist, peer_mask)
    out = Path(output_dir)
    with staged_output_dir(out, overwrite, replaceable=REPORT_FILES) as tmp:
        result = _evaluate_into(tmp, items, methods, registrar, progress, html, max_overlays, datalist, peer_mask)
    result["paths"] = {k: out / Path(v).relative_to(tmp) for k, v in result["paths"].items()}
    return result


def checked_items(datalist: str | Path, methods: Sequence[str], output_dir: str | Path | None = None,
                  max_cases: int | None = None, key: str | None = None, max_overlays: int = DEFAULT_MAX_OVERLAYS,
                  overwrite: bool = False) -> list[dict[str, Any]]:
    """What :func:`evaluate_datalist` checks before anything slow, in its order: the methods (and their optional
    tools), ``max_cases`` and ``max_overlays``, the output folder, the datalist and every item's ground truth.
    Read-only, so that every process of a distributed evaluation makes the same checks with the same outcome.

    Returns:
        the datalist's items (the first ``max_cases``), paths resolved.

    Raises:
        InputError, OutputExistsError: as :func:`evaluate_datalist`.
    """
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise InputError(f"unknown method(s) {unknown}; choose from {METHODS}")
    if len(set(methods)) != len(methods):
        raise InputError(f"a method is named twice in {list(methods)}")
    if max_cases is not None and (isinstance(max_cases, bool) or not isinstance(max_cases, (int, np.integer))
                                  or max_cases < 1):
        raise InputError(f"max_cases must be a whole number >= 1, got {max_cases!r}")
    if isinstance(max_overlays, bool) or not isinstance(max_overlays, (int, np.integer)) or max_overlays < 0:
        raise InputError(f"max_overlays must be a whole number >= 0, got {max_overlays!r}")
    if output_dir is not None:  # before anything slow: a folder that may not be replaced is refused at once
        check_output_dir(output_dir, overwrite)
        if overwrite:
            check_replaceable(output_dir, REPORT_FILES)
    items, _ = load_datalist(datalist, key)
    if max_cases is not None:
        items = items[: int(max_cases)]
    check_ground_truth(items, datalist)  # all of them before the first registration
    if "elastix" in methods:
        if not elastix_available():
            raise InputError("method 'elastix' needs itk-elastix: pip install 'monai-rigidreg[elastix]'")
    for method in (m for m in methods if m in PEER_METHODS and not peer_available(m)):
        raise InputError(f"method {method!r} needs {'antspyx' if method == 'ants' else 'picsl-greedy'}: pip install "
                         "'monai-rigidreg[bench]'")
    return items


REPORT_FILES = ("cases.csv", "summary.json", "report.md", "report.html", OVERLAY_DIR)
"""What :func:`evaluate_datalist` writes into its ``output_dir`` (all that ``overwrite`` may replace)."""


def _evaluate_into(output_dir: Path | None, items: list[dict[str, Any]], methods: Sequence[str], registrar: Any,
                   progress: bool, html: bool, max_overlays: int, datalist: str | Path,
                   peer_mask: bool | None = None) -> dict[str, Any]:
    """The evaluation loop of :func:`evaluate_datalist`, its report written into ``output_dir`` (``None``:
    nowhere)."""
    gallery = (OverlayGallery(Path(output_dir) / OVERLAY_DIR, methods, max_others=max_overlays)
               if html and output_dir is not None else None)
    cases = register_cases(items, methods, registrar, progress, gallery, peer_mask=peer_mask)
    if gallery is not None:
        gallery.finish()
    return report_cases(cases, output_dir, datalist, gallery.images if gallery else None,
                        gallery.omitted if gallery else 0)


def register_cases(items: Sequence[dict[str, Any]], methods: Sequence[str], registrar: Any, progress: bool = False,
                   gallery: OverlayGallery | None = None, first_index: int = 0,
                   index_of: Sequence[int] | None = None, peer_mask: bool | None = None) -> list[CaseResult]:
    """Every item registered by every method, in that order (one :class:`CaseResult` per item and method), the
    overlays drawn into ``gallery`` while each case is loaded. A failed or interrupted run discards the gallery's
    images and raises.

    ``index_of``: each item's position in the whole evaluation (default ``first_index``, ``first_index + 1``...):
    a result's index, the key of its overlay, is ``position * len(methods) + method``, as in the merged list of a
    distributed evaluation. ``peer_mask``: as in :func:`evaluate_datalist`.
    """
    positions = list(index_of) if index_of is not None else [first_index + k for k in range(len(items))]
    cases: list[CaseResult] = []
    try:
        for k, case in enumerate(tqdm(iter_cases(items), total=len(items), desc="evaluate", disable=not progress,
                                      unit="case")):
            first = len(cases)
            for method in methods:
                pred, runtime, extra = _run_method(method, case.fixed, case.moving, case.fov, case.center, registrar,
                                                   peer_mask)
                tre = float(target_registration_error(pred, case.truth, case.points, center=case.center))
                cases.append(CaseResult(case.case_id, method, case.truth.tolist(), np.asarray(pred).tolist(), tre,
                                        runtime, str(case.item.get("group", "")), extra))
            if gallery is not None:  # drawn now, while the volumes are loaded
                base = positions[k] * len(methods)
                gallery.add(case.fixed, case.moving, case.center,
                            [(base + j, cases[first + j]) for j in range(len(methods))])
    except BaseException:
        if gallery is not None:  # a failed (or interrupted) run leaves no partial output
            gallery.discard()
        raise
    return cases


def report_cases(cases: list[CaseResult], output_dir: Path | None, datalist: str | Path,
                 overlays: dict[int, Path] | None = None, omitted_overlays: int = 0) -> dict[str, Any]:
    """The summary and report of ``cases``, written into ``output_dir`` (``None``: nowhere): ``cases.csv``,
    ``summary.json``, ``report.md`` and, where ``overlays`` is given (result index -> PNG), ``report.html``."""
    summary = summarize(cases)
    report = format_report(summary)
    paths = write_report(cases, output_dir) if output_dir is not None else {}
    if overlays is not None and output_dir is not None:
        paths["html"] = write_html_report(cases, Path(output_dir) / "report.html", summary=summary,
                                          overlays=overlays, datalist=datalist, omitted_overlays=omitted_overlays)
    return {"summary": summary, "report": report, "cases": cases, "paths": paths}


def _run_method(method: str, fixed: sitk.Image, moving: sitk.Image, fov: sitk.Image | None, center: np.ndarray,
                registrar: Any, peer_mask: bool | None = None) -> tuple[np.ndarray, float, dict[str, Any]]:
    t0 = time.perf_counter()
    if method.startswith("network"):
        res = registrar(fixed, moving, refine=method == "network+refine", resample_moving=False, moving_fov=fov,
                        assess=True, fine_stage=False if method == "network-regression" else None,
                        **({"thorough": True} if method == "network-thorough" else {}))
        details = getattr(res, "details", {})
        extra = {"confidence": res.confidence, "flagged": res.flagged, "start": details.get("start"),
                 "path": details.get("path"), "fallback": details.get("fallback"),
                 "lead_check": details.get("lead_check"), "fine_stage_choice": details.get("fine_stage_choice"),
                 "timings": {k: round(v, 4) for k, v in res.timings.items()}}
        return res.params, time.perf_counter() - t0, extra
    if method == "sitk":
        res = register_sitk(fixed, moving, center=center, moving_mask=fov)
    elif method in PEER_METHODS:
        res = register_peer(method, fixed, moving, center=center, moving_mask=fov, use_mask=peer_mask)
    else:
        res = register_elastix(fixed, moving, center=center)  # elastix's default rigid map, as specified
    return res.params, time.perf_counter() - t0, {"stop": res.stop_condition}
