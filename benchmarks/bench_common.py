"""Helpers shared by the benchmark scripts: printing with a copy for ``--results``, the machine load while a
benchmark runs, and finding the real CTs of ``../shared/data`` (or a user's paths)."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


class Tee:
    """Print and keep every line, for ``--results``."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def __call__(self, text: str = "") -> None:
        print(text, flush=True)
        self.lines.append(text)


class LoadMonitor(threading.Thread):
    """Samples the 1-minute load average every ``period`` seconds while the benchmark runs."""

    def __init__(self, period: float = 10.0) -> None:
        super().__init__(daemon=True)
        self.period = period
        self.samples: list[float] = [os.getloadavg()[0]]
        self._stop_event = threading.Event()

    def run(self) -> None:
        while not self._stop_event.wait(self.period):
            self.samples.append(os.getloadavg()[0])

    def stop(self) -> None:
        self._stop_event.set()
        self.samples.append(os.getloadavg()[0])

    def describe(self) -> str:
        s = np.asarray(self.samples)
        return f"min {s.min():.2f}, mean {s.mean():.2f}, max {s.max():.2f} over {len(s)} samples"


def ct_name(path: Path) -> str:
    name = path.name
    for suffix in (".nii.gz", ".nii", ".mha", ".mhd", ".nrrd"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name


def find_cts(requested: list[str] | None, out: Tee, defaults: tuple[str, ...]) -> list[Path]:
    """The CTs to use (paths, or names of files in the data folder); absent ones are skipped with the reason."""
    from monai_rigidreg.data import shared_data_dir

    dirs = [d for d in (shared_data_dir(), REPO.parent / "shared" / "data", Path("../shared/data")) if d is not None]
    found = []
    for r in requested or defaults:
        p = Path(r).expanduser()
        if p.exists():
            found.append(p.resolve())
            continue
        names = [r] if r.endswith((".nii.gz", ".nii", ".mha", ".nrrd")) else [r, f"{r}.nii.gz"]
        hit = next((d / n for n in names for d in dirs if (d / n).is_file()), None)
        if hit is None:
            where = ", ".join(str(d) for d in dict.fromkeys(dirs)) or "no data folder ($MONAI_RIGIDREG_DATA unset)"
            out(f"skipped {r}: not found in {where}")
        else:
            found.append(hit.resolve())
    return found


def set_threads(threads: int) -> None:
    """torch, SimpleITK and ITK thread counts (and the OpenMP/MKL environment) before the libraries start their
    pools: benchmarks compare methods at the same number of threads."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"):
        os.environ[var] = str(threads)
    import SimpleITK as sitk
    import torch

    torch.set_num_threads(threads)
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(threads)



def median_time(fn: Callable[[], object], repeats: int, warm_up: bool = False) -> float:
    """Median wall seconds of ``repeats`` calls of ``fn`` (after one untimed call with ``warm_up``: the process's
    first-use costs)."""
    if warm_up:
        fn()
    times = []
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))
