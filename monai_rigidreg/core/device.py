"""The one place that turns a user's device choice (``"auto"``, ``"cpu"``, ``"cuda:1"``, ...) into a ``torch.device``,
and a thread count into the CPU thread settings of torch and SimpleITK.

Every part of the package (registration, simulation, training glue) calls :func:`resolve_device`, so a bad device
string is reported the same way everywhere: as :class:`~monai_rigidreg.core.errors.InputError` naming the value.
:func:`set_cpu_threads` is what ``monai-rigidreg register --threads N`` calls (the OpenMP wait policy is set when the
package is imported, see ``monai_rigidreg/__init__.py``); without it each registration runs inside
:func:`adapted_cpu_threads`, fewer threads while other work keeps cores busy.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator

import SimpleITK as sitk
import torch

from monai_rigidreg.core.errors import InputError

__all__ = ["resolve_device", "set_cpu_threads", "busy_cores", "adaptive_threads", "adapted_cpu_threads"]


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    """``"auto"`` (or ``None``) -> CUDA when available, else CPU; anything else is parsed by ``torch.device``.

    Raises:
        InputError: the string is not a device torch knows (e.g. ``"gpu7"``), or CUDA (or the given CUDA index) was
            asked for on a machine that does not have it.
    """
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError) as exc:
        raise InputError(f"device {str(device)!r} is not a device name (use auto, cpu, cuda or cuda:N)") from exc
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise InputError(f"device {str(device)!r} was asked for but CUDA is not available")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise InputError(f"device {str(device)!r} was asked for but only {torch.cuda.device_count()} CUDA "
                             "device(s) exist")
    return dev


def set_cpu_threads(threads: int | None) -> int:
    """Use ``threads`` CPU threads in torch's intra-op pool and in SimpleITK's filters (``None``: leave both as they
    are: torch's default is one per core). Returns the torch thread count now in effect.

    Raises:
        InputError: ``threads`` < 1.
    """
    if threads is None:
        return torch.get_num_threads()
    if int(threads) < 1:
        raise InputError(f"threads must be at least 1, got {threads}")
    torch.set_num_threads(int(threads))
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(int(threads))
    return torch.get_num_threads()


def _runnable_tasks() -> int | None:
    """Runnable tasks on the machine now (the fourth field of ``/proc/loadavg``, ``running/total``), the caller's own
    thread included; ``None`` where the file is missing (not Linux)."""
    try:
        with open("/proc/loadavg", encoding="ascii") as f:
            return int(f.read().split()[3].split("/")[0])
    except (OSError, ValueError, IndexError):
        return None


def busy_cores(samples: int = 3, interval_s: float = 0.002) -> int | None:
    """How many cores other work keeps busy right now: the fewest runnable tasks over ``samples`` reads of
    ``/proc/loadavg`` ``interval_s`` apart, less the calling thread (a momentary task is not counted; a process that
    computes all along, such as a busy loop, is; another registration is while it computes). ``None`` where this
    cannot be read."""
    counts = []
    for k in range(samples):
        if k:
            time.sleep(interval_s)
        n = _runnable_tasks()
        if n is None:
            return None
        counts.append(n)
    return max(0, min(counts) - 1)


def adaptive_threads(current: int) -> int:
    """The intra-op thread count for work starting now: ``current`` less the cores other work keeps busy
    (:func:`busy_cores`), at least 1; ``current`` where that cannot be read.

    Why: on 2 cores beside a single-threaded busy loop a registration took 1.76 s per case with one thread against
    1.91 s with two (the second thread waits for a core at every parallel region), while on a quiet machine two are
    faster (``benchmarks/speed/bench_worker_threads.py``, its thread-count table).
    """
    busy = busy_cores()
    if busy is None:
        return current
    available = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(int(current), available - busy))


@contextlib.contextmanager
def adapted_cpu_threads(adapt: bool = True) -> Iterator[int]:
    """torch's and SimpleITK's thread counts lowered to :func:`adaptive_threads` for the ``with`` block (``adapt``;
    never raised) and restored on exit; yields the torch thread count in use."""
    current = torch.get_num_threads()
    n = adaptive_threads(current) if adapt else current
    if n >= current:
        yield current
        return
    itk = sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
    set_cpu_threads(n)
    try:
        yield n
    finally:
        torch.set_num_threads(current)
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(itk)
