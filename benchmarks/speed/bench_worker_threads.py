"""The default path's worker threads (the global search beside the network from the identity, the swapped-input
estimate beside the last level) against the same path with each worker run in line (synchronously), on a quiet
machine and beside one single-threaded busy loop; and, beside the busy loop, the registrar's adaptive thread count
(``adapt_threads``, the default: one per core less the cores other work keeps busy) against fixed counts.

Prints the median seconds per case of each, registrar loaded once, volumes in memory, on the ``bench_speed.py``
pairs (``bench_out/speed``; run ``python -m benchmarks.speed.bench_speed`` first to create them) and their thorax CT.
The in-line variant replaces ``registration.state.Background`` by a class that runs its function at once: the same
estimates, the stages one after the other.

Usage::

    python -m benchmarks.speed.bench_worker_threads [--pairs bench_out/speed] [--cases 6] [--repeats 2]

Run it alone on the machine: it starts its own busy loop for the second half.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

import monai_rigidreg  # noqa: F401 (before torch: its thread policy applies before torch loads)


class InLine:
    """``registration.state.Background``'s interface, the function run at once in the calling thread."""

    def __init__(self, fn: Any, *args: Any, thread_name: str = "", **kwargs: Any) -> None:
        t = time.perf_counter()
        self._value: Any = None
        self._error: BaseException | None = None
        try:
            self._value = fn(*args, **kwargs)
        except BaseException as exc:  # noqa: BLE001 - re-raised by result(), as the worker's would be
            self._error = exc
        self.seconds = time.perf_counter() - t

    def result(self) -> Any:
        if self._error is not None:
            raise self._error
        return self._value

    def wait(self) -> None:
        return None


def seconds_per_case(registrar: Any, ct: sitk.Image, cbcts: list[sitk.Image]) -> list[float]:
    """Wall seconds of one registration per CBCT (no resampled output)."""
    out = []
    for cbct in cbcts:
        t = time.perf_counter()
        registrar(ct, cbct, resample_moving=False)
        out.append(time.perf_counter() - t)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=Path, default=Path("bench_out/speed"))
    ap.add_argument("--ct", type=Path, default=Path("../shared/data/thorax_4dct_phase00_itkelastix.nii.gz"))
    ap.add_argument("--cases", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=2, help="passes over the pairs per variant and condition")
    args = ap.parse_args()

    import torch

    import monai_rigidreg.registration.registrar as reg_mod

    cases = [args.pairs / f"case_{i}" / "cbct.nii.gz" for i in range(args.cases)]
    missing = [str(c) for c in cases if not c.is_file()] + ([] if args.ct.is_file() else [str(args.ct)])
    if missing:
        sys.exit(f"missing inputs (run benchmarks/speed/bench_speed.py first): {', '.join(missing)}")
    registrar = reg_mod.RigidRegistrar.from_bundle(device="cpu")
    ct = sitk.ReadImage(str(args.ct), sitk.sitkFloat32)
    cbcts = [sitk.ReadImage(str(c), sitk.sitkFloat32) for c in cases]
    registrar(ct, cbcts[0])  # warm-up: allocator, FFT plans, the CT's body mask
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, OMP_WAIT_POLICY="
          f"{os.environ.get('OMP_WAIT_POLICY')}; {len(cbcts)} pairs x {args.repeats} passes per variant; "
          f"load average at start {os.getloadavg()[0]:.2f}\n")
    threaded = reg_mod.Background
    print(f"{'condition':34s} {'worker threads s':>17s} {'in line s':>10s}")
    for condition in ("quiet", "beside a busy loop"):
        busy = None
        if condition != "quiet":
            busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
            time.sleep(1.0)
        times: dict[str, list[float]] = {"threads": [], "in line": []}
        try:
            for _ in range(args.repeats):
                for name, cls in (("threads", threaded), ("in line", InLine)):
                    reg_mod.Background = cls
                    times[name] += seconds_per_case(registrar, ct, cbcts)
        finally:
            reg_mod.Background = threaded
            if busy is not None:
                busy.kill()
        print(f"{condition:34s} {np.median(times['threads']):17.2f} {np.median(times['in line']):10.2f}")

    print(f"\nbeside a busy loop, worker threads on: {'threads':34s} {'s / case':>9s}")
    cores = torch.get_num_threads()
    variants = [("adaptive (default)", cores, True)] + [(f"fixed {n}", n, False) for n in range(cores, 0, -1)]
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    time.sleep(1.0)
    per: dict[str, list[float]] = {name: [] for name, _, _ in variants}
    try:
        for _ in range(args.repeats):
            for name, n, adapt in variants:
                torch.set_num_threads(n)
                sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(n)
                registrar.adapt_threads = adapt
                per[name] += seconds_per_case(registrar, ct, cbcts)
    finally:
        busy.kill()
        torch.set_num_threads(cores)
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(cores)
        registrar.adapt_threads = True
    for name, _, _ in variants:
        print(f"{'':39s}{name:34s} {np.median(per[name]):9.2f}")


if __name__ == "__main__":
    main()
