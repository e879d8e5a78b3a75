"""Ctrl-C and SIGTERM at every step of writing an output folder leave the finished folder or nothing (issue 35).

The writers call :func:`monai_rigidreg.io.staging.step` between their steps;
:data:`~monai_rigidreg.io.staging.step_hook`
interrupts them there: by raising ``KeyboardInterrupt`` in the writer, by sending the process SIGINT or SIGTERM, and
with a second signal during the clean-up. Then through the command: ``monai-rigidreg register`` in a subprocess,
held at a step, stopped by a signal from outside.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import in_main_thread, listing

from monai_rigidreg.core.errors import Terminated, signals_deferred, sigterm_raises
from monai_rigidreg.export.outputs import write_outputs
from monai_rigidreg.io import load_volume, staging

TESTS = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def interactive_sigint():
    """Ctrl-C as at a terminal: Python's ``KeyboardInterrupt`` handler for SIGINT during each test. A shell starts a
    background job (``cmd &`` without job control, ``nohup``) with SIGINT ignored, and Python then keeps it ignored
    (as it should for such a job); the tests here are about a user's Ctrl-C, wherever pytest itself was started."""
    before = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def _sigint_as_at_a_terminal() -> None:
    """``preexec_fn`` of the command's subprocess: SIGINT's default action, so that the child's Python installs its
    ``KeyboardInterrupt`` handler even when pytest runs with SIGINT ignored (see :func:`interactive_sigint`)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture(scope="module")
def result(pair, small_registrar):
    fixed, moving = load_volume(pair["fixed"]), load_volume(pair["moving"])
    return small_registrar(fixed, moving, assess=False), fixed, moving


def _steps(result, tmp_path, monkeypatch) -> tuple[list[str], list[str]]:
    """The writer's steps in order, and the files of a finished folder."""
    res, fixed, moving = result
    seen: list[str] = []
    monkeypatch.setattr(staging, "step_hook", seen.append)
    write_outputs(res, fixed, moving, tmp_path / "reference")
    monkeypatch.setattr(staging, "step_hook", None)
    return seen, sorted(p.name for p in (tmp_path / "reference").iterdir())


def _complete_or_nothing(root: Path, out: Path, files: list[str]) -> str:
    """``"complete"`` or ``"nothing"`` (asserting one of them, and no hidden sibling anywhere under ``root``)."""
    left = listing(root)
    assert not [p for p in left if Path(p).name.startswith(".")], left  # no .out.tmp-*/.out.old-* debris
    if not out.exists():
        assert left == [], left  # nor the parent folders the writer made
        return "nothing"
    assert sorted(p.name for p in out.iterdir()) == files, left
    return "complete"


@pytest.mark.parametrize("how", ["raise", "sigint", "sigterm", "sigint-twice"])
def test_an_interruption_at_any_step_of_the_writer_leaves_the_folder_or_nothing(result, tmp_path, monkeypatch, how):
    in_main_thread()
    steps, files = _steps(result, tmp_path / "ref", monkeypatch)
    assert steps[0] == "staged:made" and steps[-1] == "staged:moved" and "result.json" in steps and len(steps) >= 7
    res, fixed, moving = result
    outcomes = {}
    for at in steps:
        root = tmp_path / at.replace(":", "_").replace(" ", "_")
        out = root / "new" / "out"

        def hook(name: str, at: str = at) -> None:
            if name == "staged:cleanup" and how == "sigint-twice":
                os.kill(os.getpid(), signal.SIGINT)  # a second Ctrl-C while the staged folder is removed
            if name != at:
                return
            if how == "raise":
                raise KeyboardInterrupt
            os.kill(os.getpid(), signal.SIGTERM if how == "sigterm" else signal.SIGINT)
            time.sleep(5)  # the handler raises in this thread before this ends

        monkeypatch.setattr(staging, "step_hook", hook)
        with pytest.raises(Terminated if how == "sigterm" else KeyboardInterrupt):
            with sigterm_raises():
                write_outputs(res, fixed, moving, out)
        outcomes[at] = _complete_or_nothing(root, out, files)
    monkeypatch.setattr(staging, "step_hook", None)
    # only an interruption after the rename finds the folder in place
    assert outcomes == {at: "complete" if at == "staged:moved" else "nothing" for at in steps}


def test_signals_held_back_are_delivered_after_the_block():
    in_main_thread()
    order = []
    with pytest.raises(KeyboardInterrupt):
        with signals_deferred():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
            order.append("block finished")
    assert order == ["block finished"]
    with pytest.raises(Terminated):
        with sigterm_raises(), signals_deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


WRAPPER = """
import os, sys, time
sys.path.insert(0, {tests!r})
from conftest import small_registrar_for_tests
from monai_rigidreg.io import staging
from monai_rigidreg.registration import RigidRegistrar
from monai_rigidreg import cli

RigidRegistrar.from_bundle = classmethod(lambda cls, *a, **k: small_registrar_for_tests())
at, marker = sys.argv[1], sys.argv[2]

def hold(name):
    if name == at:
        open(marker, "w").close()
        time.sleep(60)

staging.step_hook = hold
cli.console(sys.argv[3:])
"""


@pytest.mark.parametrize(("at", "sig"), [
    ("registered.nii.gz (started)", signal.SIGINT),  # the volume's worker still writing into the staged folder
    ("result.json", signal.SIGTERM),
    pytest.param("staged:made", signal.SIGTERM, marks=pytest.mark.slow),
    pytest.param("staged:written", signal.SIGINT, marks=pytest.mark.slow),
], ids=["sigint-while-the-volume-is-written", "sigterm-after-result.json", "sigterm-staged", "sigint-before-rename"])
def test_register_command_stopped_by_a_signal_from_outside_leaves_nothing(pair, tmp_path, at, sig):
    """The command as a user runs it, held at one step of writing its outputs and stopped there by ``kill`` (SIGTERM)
    or Ctrl-C (SIGINT) from outside: the signal handlers remove the staged folder."""
    work = tmp_path / "work"
    work.mkdir()
    marker = tmp_path / "held"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS.parent), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen(
        [sys.executable, "-c", WRAPPER.format(tests=str(TESTS)), at, str(marker), "register", "--fixed",
         str(pair["fixed"]), "--moving", str(pair["moving"]), "--output-dir", str(work / "new" / "out"),
         "--threads", "1"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=_sigint_as_at_a_terminal)
    try:
        deadline = time.monotonic() + 120
        while not marker.exists():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the command never reached the step"
            time.sleep(0.05)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == (130 if sig == signal.SIGINT else 143), err
    assert err.strip().splitlines()[-1] == ("monai-rigidreg register: interrupted" if sig == signal.SIGINT else
                                            "monai-rigidreg register: terminated"), err
    assert listing(work) == []  # no output, no .out.tmp-* folder, not even the parent it made
