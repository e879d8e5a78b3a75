"""Simulation of a paired Sim-CT / CBCT dataset with known rigid ground truth: :func:`simulate_dataset`.

For every object (a phantom or a real CT) the planning CT ("Sim-CT") is simulated once, unmoved: fan-beam
projection slice by slice and FBP. For every case of the protocol the object is moved by a rigid motion ``M``
(a body point at ``p`` goes to ``M(p)``; ``M`` about the isocentre = the Sim-CT centre = the origin), then the
CBCT is projected (cone beam), degraded (:class:`~monai_rigidreg.simulation.physics.CBCTPhysics`) and
reconstructed with FDK (one case: :func:`~monai_rigidreg.simulation.volumes.simulate_case`). With fixed = Sim-CT
and moving = CBCT, the registration transform (fixed -> moving points, ``sitk.Resample(cbct, simct, T)`` aligns
them) is ``T = M``; it is stored as parameters about the Sim-CT centre, as a 4x4 matrix and with its centre.

Resumable: finished cases of the same configuration found in the output folder are kept (``simulation.json``
holds the configuration it is compared with); cases can run in worker processes.

Output layout under ``output_dir``::

    dataset.json              MONAI datalist {"training": [...]} (load_decathlon_datalist)
    simulation.json           full configuration, package versions
    objects/objNNN_simct.nii.gz      Sim-CT per object (int16, HU)
    cases/caseNNNN_cbct.nii.gz       CBCT per case (int16, HU)
    cases/caseNNNN_cbct_fov.nii.gz   CBCT field of view (uint8 mask on the CBCT grid)

The volumes have identity direction (LPS). With a built-in phantom they are centred on the isocentre (0, 0, 0); with
a CT they keep the CT's frame (the Sim-CT centred on the CT's centre, the isocentre there; ``ct_frame=False``: on the
origin, as before 0.5), so that a CBCT registers against the input CT itself. ``dataset.json`` says which
(``"frame"``, ``"frame_offset_mm"``); every case's ``params`` are about its ``center``, the Sim-CT centre, either way.
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import json
import logging
import math
import os
import platform
import re
import shutil
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch
from tqdm.auto import tqdm

import monai_rigidreg
from monai_rigidreg.core.device import resolve_device
from monai_rigidreg.core.errors import InputError, OutputExistsError
from monai_rigidreg.core.geometry import params_to_matrix
from monai_rigidreg.io.volumes import check_output_dir, make_dirs, remove_made_dirs
from monai_rigidreg.simulation.config import SimulationConfig, make_config
from monai_rigidreg.simulation.phantoms import PHANTOMS, ct_center, load_ct
from monai_rigidreg.simulation.protocols import MotionCase, protocol_cases
from monai_rigidreg.simulation.volumes import frame_offset, simulate_case, stream_seed, write_simct

__all__ = ["simulate_dataset"]

logger = logging.getLogger(__name__)


PHANTOM_FAMILIES: tuple[str, ...] = ("random", "synth")
"""Phantom names that stand for a family: one object per seed (``num_objects`` of them in a dataset)."""


def _num_objects(cfg: SimulationConfig, num_cases: int) -> int:
    if cfg.phantom not in PHANTOM_FAMILIES:
        return 1
    if cfg.num_objects is not None:
        return max(1, min(int(cfg.num_objects), num_cases))
    return max(1, math.ceil(num_cases / 8))


def _object_name(cfg: SimulationConfig, k: int) -> str:
    if cfg.phantom in PHANTOM_FAMILIES:
        return f"{cfg.phantom}-seed{stream_seed(cfg.seed, 0, k)}"
    if cfg.phantom in PHANTOMS:
        return cfg.phantom
    return Path(cfg.phantom).name


_OBJECTS: dict[tuple, Any] = {}
"""The last object volume of this process (see ``simulate_case``'s ``object_cache``)."""


def _run_case(cfg_dict: dict[str, Any], case: dict[str, Any], out_dir: str) -> str:
    """Simulate and write one CBCT (top-level so that worker processes can run it)."""
    simulate_case(SimulationConfig(**cfg_dict), case, out_dir, write_fixed=False, object_cache=_OBJECTS)
    return case["case_id"]


def _worker_init() -> None:
    torch.set_num_threads(1)


def _versions() -> dict[str, str]:
    return {
        "monai_rigidreg": monai_rigidreg.__version__,
        "torch": torch.__version__,
        "monai": importlib.metadata.version("monai"),  # recorded without importing MONAI (seconds)
        "SimpleITK": sitk.Version.VersionString(),
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


def _prepare_output(out: Path, cfg: SimulationConfig, overwrite: bool) -> None:
    """Check that ``out`` may receive the dataset of ``cfg``: a new or empty folder, or one holding (part of) the
    same dataset (resumed), or anything with ``overwrite``."""
    check_output_dir(out, overwrite=overwrite, allow_existing=True)
    meta = out / "simulation.json"
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        if not meta.is_file():
            raise OutputExistsError(
                out, "it is a non-empty directory that is not a simulated dataset; --overwrite (overwrite=True) to "
                "use it"
            )
        try:
            old = json.loads(meta.read_text())["config"]
        except (ValueError, KeyError) as exc:
            raise OutputExistsError(out, f"its simulation.json is unreadable ({exc}); --overwrite (overwrite=True) to "
                                         "replace it") from exc
        if old != cfg.identity():
            diff = sorted(k for k in set(old) | set(cfg.identity()) if old.get(k) != cfg.identity().get(k))
            raise OutputExistsError(
                out,
                f"it holds a dataset of another configuration (differs in {diff}); "
                "--overwrite (overwrite=True) or choose another directory",
            )


def simulate_dataset(
    output_dir: str | Path,
    phantom: str | Path = "shepp-logan",
    protocol: str = "paper",
    num_cases: int | None = None,
    preset: str = "fast",
    seed: int = 0,
    device: str = "auto",
    overwrite: bool = False,
    workers: int = 0,
    progress: bool = True,
    **overrides: Any,
) -> Path:
    """Simulate a paired Sim-CT (fixed) / CBCT (moving) dataset with ground-truth rigid transforms.

    Deterministic for a seed (on one device); resumable: finished cases found in ``output_dir`` (same
    configuration) are kept and skipped.

    Args:
        output_dir: output directory (created).
        phantom: ``"shepp-logan"``, ``"shepp-logan-asym"``, ``"random"``, ``"synth"`` (synthetic anatomy for domain
            randomization, :mod:`monai_rigidreg.simulation.synth`) or a path to a CT (NIfTI file or
            DICOM directory, HU).
        protocol: ``"paper"`` or ``"random"``.
        num_cases: number of cases (``None``: all 63 ``paper`` cases, 64 ``random`` ones, 1 with ``motion=``).
        preset: ``"paper"`` (Sim-CT 256^3 at 1 mm, CBCT 128^3 at 1 mm) or ``"fast"`` (Sim-CT 64^3 at 4 mm,
            CBCT 48^3 at 5 mm).
        seed: master seed.
        device: ``"cpu"``, ``"cuda"`` or ``"auto"``.
        overwrite: recompute everything even where files exist (the previous dataset's ``dataset.json``,
            ``simulation.json`` and volumes are removed first), and accept a directory holding something else.
        workers: worker processes for the CBCTs (0: this process).
        progress: show a tqdm progress bar.
        **overrides: any :class:`SimulationConfig` or :class:`CBCTPhysics` field (e.g. ``cbct_spacing=2.0``,
            ``cbct_views=180``, ``photons=1e4``, ``scatter_to_primary=0``; ``motion=(tx, ty, tz, rx, ry, rz)``: that
            motion for every case instead of the protocol's; ``ct_frame=False``: a CT's pairs centred on the origin).

    Returns:
        Path of ``dataset.json`` (a MONAI datalist: ``load_decathlon_datalist(path, data_list_key="training")``).

    Raises:
        InputError: bad options (a value of the wrong type, e.g. ``cbct_views="many"``), a missing or unsuitable
            CT, an ``output_dir`` that cannot be made (a parent of it is a file, a name longer than 255 bytes).
        OutputExistsError: ``output_dir`` is a file, or holds other data and ``overwrite`` is False.
    """
    cfg = make_config(
        preset,
        phantom=str(phantom),
        protocol=protocol,
        num_cases=num_cases,
        seed=seed,
        device=device,
        workers=workers,
        **overrides,
    )
    out = Path(output_dir).expanduser()
    _prepare_output(out, cfg, overwrite)
    dev = resolve_device(cfg.device)
    if cfg.phantom not in PHANTOMS:
        if any(Path(cfg.phantom).resolve().is_relative_to((out / sub).resolve()) for sub in _OWN_VOLUMES):
            raise InputError("the CT to simulate from lies in a folder this simulation writes (its cases/ or "
                             "objects/): copy it elsewhere first", cfg.phantom)
        # read once here (again per object later) so that a corrupt, 2D or non-finite CT is refused before anything
        # is written
        load_ct(cfg.phantom)
    fresh = not out.exists() or not any(out.iterdir())
    made = make_dirs(out)
    try:
        return _simulate_into(out, cfg, dev, overwrite, progress)
    except BaseException:
        if fresh and not _finished_volumes(out):  # nothing worth resuming: leave no trace of this run
            if made:
                shutil.rmtree(out, ignore_errors=True)
                remove_made_dirs(made[1:])
            else:
                for child in list(out.iterdir()):
                    if child.is_dir():
                        shutil.rmtree(child, ignore_errors=True)
                    else:
                        child.unlink(missing_ok=True)
        raise


def _frame(cfg: SimulationConfig, center: np.ndarray) -> str:
    """One line on where the volumes lie (``dataset.json``'s ``"frame"``, and the log)."""
    at = "(" + ", ".join(f"{v:.1f}" for v in center) + ") mm LPS"
    if cfg.phantom in PHANTOMS:
        return f"built-in phantom: the Sim-CT is centred on the origin {at}, the motions are about it"
    if cfg.ct_frame:
        return (f"the input CT's frame: the Sim-CT is centred on the CT's centre {at}, the motions are about it; "
                "the CBCTs register against the input CT itself")
    return (f"centred on the origin (ct_frame=False): the Sim-CT centre {at} stands for the CT's centre "
            f"{tuple(round(float(v), 1) for v in ct_center(cfg.phantom))}; register the CBCTs against the Sim-CT")


def _finished_volumes(out: Path) -> list[Path]:
    """The Sim-CTs and CBCTs of ``out`` that are complete (written under their final names)."""
    return [p for p in out.glob("*/*.nii.gz") if not p.name.startswith(".")]


_OWN_VOLUMES = {"cases": re.compile(r"case\d{4,}_cbct(_fov)?\.nii\.gz"),
                "objects": re.compile(r"obj\d{3,}_simct\.nii\.gz")}
"""The volumes a dataset folder holds, by subfolder: what ``overwrite`` removes before it writes anything."""


def _remove_previous(out: Path) -> None:
    """Before an ``overwrite``: the previous dataset's datalist, record and volumes go first, so that an interrupted
    run can never leave another configuration's volumes to be taken for finished cases of this one (a resume keeps
    any volume it finds under its name). Files this writer does not make are left (an input CT among the volumes
    was refused before: :func:`simulate_dataset`)."""
    for name in ("dataset.json", "simulation.json"):  # the datalist first: no stale ground truth survives
        (out / name).unlink(missing_ok=True)
    for sub, pattern in _OWN_VOLUMES.items():
        folder = out / sub
        if folder.is_dir():
            for f in folder.iterdir():
                if pattern.fullmatch(f.name) and f.is_file():
                    f.unlink()


def _simulate_into(out: Path, cfg: SimulationConfig, dev: torch.device, overwrite: bool, progress: bool) -> Path:
    """The writing part of :func:`simulate_dataset`, into the checked folder ``out``."""
    if overwrite:
        _remove_previous(out)
    meta = {"config": cfg.identity(), "runtime": {"device": str(dev), "workers": cfg.workers}, "versions": _versions()}
    (out / "simulation.json").write_text(json.dumps(meta, indent=2))

    cases: list[MotionCase] = protocol_cases(
        cfg.protocol, cfg.num_cases, cfg.seed, cfg.max_translation, cfg.max_rotation, motion=cfg.motion
    )
    n_obj = _num_objects(cfg, len(cases))
    offset = frame_offset(cfg)
    center = cfg.simct_grid.center() + offset
    frame = _frame(cfg, center)
    logger.info("simulating %d case(s): %s", len(cases), frame)
    items, todo = [], []
    for i, case in enumerate(cases):
        k = i % n_obj
        cid = f"case{i:04d}"
        item = {
            "fixed": f"objects/obj{k:03d}_simct.nii.gz",
            "moving": f"cases/{cid}_cbct.nii.gz",
            "moving_fov": f"cases/{cid}_cbct_fov.nii.gz",
            "params": [float(v) for v in case.params],
            "matrix": params_to_matrix(case.params, center).tolist(),
            "center": [float(v) for v in center],
            "case_id": cid,
            "object": _object_name(cfg, k),
            "group": case.group,
            "label": case.label,
            "condition": case.condition,
        }
        items.append(item)
        if overwrite or not ((out / item["moving"]).is_file() and (out / item["moving_fov"]).is_file()):
            todo.append({**item, "index": i, "object_index": k})

    # the Sim-CTs: one per object, unmoved (fan-beam FBP of every slice: the longest single step)
    simct_todo = [k for k in range(n_obj)
                  if overwrite or not (out / f"objects/obj{k:03d}_simct.nii.gz").is_file()]
    for k in tqdm(simct_todo, desc="Sim-CTs", unit="volume", disable=not progress or not simct_todo):
        write_simct(cfg, k, out / f"objects/obj{k:03d}_simct.nii.gz")
    cfg_dict = dataclasses.asdict(cfg)
    bar = tqdm(total=len(todo), desc="CBCT cases", unit="case", disable=not progress)
    if cfg.workers > 0 and len(todo) > 1:
        ctx = torch.multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(cfg.workers, mp_context=ctx, initializer=_worker_init) as pool:
            for _ in pool.map(_run_case, [cfg_dict] * len(todo), todo, [str(out)] * len(todo)):
                bar.update()
    else:
        for case in todo:
            _run_case(cfg_dict, case, str(out))
            bar.update()
    bar.close()
    _OBJECTS.clear()
    path = out / "dataset.json"
    tmp = out / ".dataset.json.tmp"
    try:
        tmp.write_text(json.dumps({"name": "monai-rigidreg simulated CBCT/Sim-CT pairs", "frame": frame,
                                   "frame_offset_mm": [float(v) for v in offset], "training": items}, indent=1))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
