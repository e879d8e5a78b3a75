"""The training run's thread tuner (``engine/threads.py``): on a simulated clock where two threads are fast on a quiet
machine and slow beside a busy process, it follows the faster count both ways."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from monai_rigidreg.engine.threads import ThreadTuner

COST = {"quiet": {2: 1.2, 1: 2.3}, "busy": {2: 4.8, 1: 2.3}}
"""Seconds per iteration by the load and the thread count (the shape of ``bench_training_threads``' 1.65 / 2.47 s
quiet and 3.99 / 2.29 s beside one busy process, two / one threads)."""


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _run(tuner: ThreadTuner, clock: _Clock, load: str, iterations: int) -> list[int]:
    """``iterations`` iterations under ``load``; the thread count each one ran with."""
    used = []
    for _ in range(iterations):
        threads = torch.get_num_threads()
        used.append(threads)
        clock.now += COST[load][threads]
        tuner.tick()
    return used


def test_the_tuner_follows_the_faster_thread_count_as_the_load_comes_and_goes(restore_threads):
    torch.set_num_threads(2)
    clock = _Clock()
    tuner = ThreadTuner(window=4, probe_every=5, max_threads=2, clock=clock)
    quiet = _run(tuner, clock, "quiet", 120)
    # quiet: two threads, apart from the probe windows at one (the first after two windows, then one window in
    # six), none kept
    assert tuner.switches == 0 and quiet[:9].count(1) == 0 and quiet[9:13] == [1, 1, 1, 1]
    assert quiet.count(1) <= 120 // 6 + 8
    busy = _run(tuner, clock, "busy", 120)
    # the load comes: one window at two threads is slow enough to probe one at once, and one thread stays, apart
    # from the periodic probes at two
    assert tuner.threads == 1 and tuner.switches == 1
    assert busy[: 2 * 4 + 1].count(2) >= 4 and busy[2 * 4 + 1:].count(2) <= (120 - 9) // 6 + 4
    again = _run(tuner, clock, "quiet", 120)
    # the load goes: the next periodic probe at two threads is faster, and two threads stay
    assert tuner.threads == 2 and tuner.switches == 2
    assert again.index(2) <= 5 * 4 + 1 and again[-40:].count(1) <= 2 * 4 + 1  # a probe window at most


def test_a_run_started_beside_other_work_finds_one_thread_at_the_first_probe(restore_threads):
    torch.set_num_threads(2)
    clock = _Clock()
    tuner = ThreadTuner(window=4, probe_every=12, max_threads=2, clock=clock)
    used = _run(tuner, clock, "busy", 40)
    # no slow-down to see (the first window is already slow): the early probe after two windows finds it
    assert tuner.threads == 1 and tuner.switches == 1 and used[:9] == [2] * 9 and used[9:] == [1] * 31


def test_the_tuner_does_nothing_when_disabled_or_with_one_thread(restore_threads):
    torch.set_num_threads(2)
    clock = _Clock()
    off = ThreadTuner(window=2, max_threads=2, enabled=False, clock=clock)
    _run(off, clock, "busy", 40)
    assert torch.get_num_threads() == 2 and off.switches == 0
    single = ThreadTuner(window=2, max_threads=1, clock=clock)
    assert not single.enabled


def test_the_context_training_config_attaches_the_tuner_on_cpu_only():
    config = Path(__file__).resolve().parents[2] / "bundles" / "cbct_ct_rigid" / "configs" / "train_context.json"
    handlers = json.loads(config.read_text())["train#handlers"]
    tuner = [h for h in handlers if isinstance(h, dict) and h["_target_"] == "monai_rigidreg.engine.ThreadTuner"]
    assert tuner == [{"_target_": "monai_rigidreg.engine.ThreadTuner", "max_threads": "@num_threads",
                      "enabled": "$@device.type == 'cpu'"}]
