"""Torch's thread count for a CPU training run, chosen by measuring iterations as the machine's load changes.

A context-network training step on 2 cores with 2 intra-op threads took 1.65 s quiet, but 3.99 s beside one busy
single-threaded process (a benchmark, a test suite, an evaluation), where 1 thread took 2.47 s quiet and 2.29 s
beside it: every parallel region waits for the thread the other process pushed off its core
(``python -m benchmarks.speed.bench_training_threads``; ``docs/results.md``, "Training beside other work").
:class:`ThreadTuner` watches the seconds per iteration and tries the other thread count where the current one has
slowed down, and now and then anyway; it keeps whichever ran faster.
"""

from __future__ import annotations

import logging
import statistics
import time
from collections.abc import Callable
from typing import Any

import torch

__all__ = ["ThreadTuner"]

logger = logging.getLogger(__name__)


class ThreadTuner:
    """Switch ``torch.set_num_threads`` between ``max_threads`` and 1 by the measured seconds per iteration.

    Iterations are timed between calls of :meth:`tick` (one per iteration) in windows of ``window``. After a window
    at the current count, a probe window runs at the other count where the window was ``slowdown`` times slower
    than the current count's reference (the load changed), after the first ``first_probe`` windows (a run started
    beside other work has no faster window to compare with) and every ``probe_every`` windows otherwise (the load
    may have dropped, which a single thread does not show). The probe's count is kept where its median is more than
    ``margin`` below the window before it (the probe's median becomes the reference); otherwise the count before
    it comes back, with that window's median as the reference. Switches are logged. The first iteration after
    :meth:`restart` (a new epoch: validation and checkpoints ran in between) is not timed.

    Args:
        window: iterations per measurement.
        probe_every: windows between probes at the other count where nothing slowed down.
        first_probe: windows before the first probe.
        slowdown: the ratio of a window's median to the current count's reference that starts a probe at once.
        margin: how much faster (a share) the probe must be to be kept.
        max_threads: the larger count (default: ``torch.get_num_threads()`` when built).
        enabled: ``False``: :meth:`tick` does nothing (e.g. training on a GPU).
        clock: seconds, monotonic (tests pass their own).

    Example:
        >>> tuner = ThreadTuner(window=4, max_threads=2, enabled=False)
        >>> tuner.tick()  # once per training iteration, or tuner.attach(trainer) for an ignite engine
        >>> tuner.threads
        2
    """

    def __init__(self, window: int = 8, probe_every: int = 12, slowdown: float = 1.3, margin: float = 0.1,
                 max_threads: int | None = None, enabled: bool = True, first_probe: int = 2,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        self.window = max(2, int(window))
        self.probe_every = max(1, int(probe_every))
        self.first_probe = max(1, int(first_probe))
        self._probes = 0
        self.slowdown = float(slowdown)
        self.margin = float(margin)
        self.max_threads = int(max_threads or torch.get_num_threads())
        self.enabled = bool(enabled) and self.max_threads > 1
        self.clock = clock
        self.threads = self.max_threads
        self.switches = 0
        self._times: list[float] = []
        self._last: float | None = None
        self._baseline: float | None = None  # the current count's reference median (see the class doc)
        self._before_probe: float | None = None  # the median of the window before a running probe
        self._windows = 0

    def attach(self, engine: Any) -> None:
        """Call :meth:`tick` after every iteration of an ignite ``engine`` and :meth:`restart` at each epoch."""
        from ignite.engine import Events

        engine.add_event_handler(Events.EPOCH_STARTED, lambda _: self.restart())
        engine.add_event_handler(Events.ITERATION_COMPLETED, lambda _: self.tick())

    def restart(self) -> None:
        """Do not time the next iteration (something other than training ran since the last one)."""
        self._last = None

    def tick(self) -> None:
        """One iteration ended."""
        if not self.enabled:
            return
        now = self.clock()
        if self._last is not None:
            self._times.append(now - self._last)
        self._last = now
        if len(self._times) >= self.window:
            median = statistics.median(self._times)
            self._times = []
            self._window_done(median)

    def _set(self, threads: int) -> None:
        torch.set_num_threads(threads)
        self.threads = threads

    def _window_done(self, median: float) -> None:
        if self._before_probe is not None:  # a probe window ended
            before, probe_threads = self._before_probe, self.threads
            self._before_probe = None
            self._windows = 0
            if median < before * (1.0 - self.margin):
                logger.info("thread tuner: %d -> %d threads (%.2f s per iteration against %.2f s)",
                            self._other(probe_threads), probe_threads, median, before)
                self.switches += 1
                self._baseline = median
            else:  # the count before the probe stays, its latest window the new reference
                self._set(self._other(probe_threads))
                self._baseline = before
            return
        self._windows += 1
        if self._baseline is None:
            self._baseline = median
        every = self.first_probe if self._probes == 0 else self.probe_every
        if median > self._baseline * self.slowdown or self._windows >= every:
            self._before_probe = median
            self._probes += 1
            self._set(self._other(self.threads))

    def _other(self, threads: int) -> int:
        return 1 if threads == self.max_threads else self.max_threads
