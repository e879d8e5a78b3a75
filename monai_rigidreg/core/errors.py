"""Exceptions raised for bad user input, with messages that name the file and the problem, and the interruption
that a SIGTERM becomes (so that the cleanup of an ``except BaseException`` / ``finally`` runs, as for Ctrl-C)."""

from __future__ import annotations

import contextlib
import re
import signal
import threading
from collections.abc import Iterator
from pathlib import Path

__all__ = ["RigidRegError", "InputError", "OutputExistsError", "Terminated", "sigterm_raises", "signals_deferred",
           "first_line", "read_error_reason"]


class RigidRegError(Exception):
    """Base class of the errors monai-rigidreg raises on purpose."""


class InputError(RigidRegError, ValueError):
    """An input (file, image, transform or argument) is missing, unreadable or unsuitable.

    Args:
        message: what is wrong (kept as ``reason``).
        path: the offending file, if any; it is named in the message.
    """

    def __init__(self, message: str, path: str | Path | None = None) -> None:
        self.reason = message
        self.path = None if path is None else Path(path)
        super().__init__(f"{self.path}: {message}" if self.path is not None else message)


class OutputExistsError(RigidRegError, FileExistsError):
    """An output would overwrite an existing file or directory and overwriting was not asked for."""

    def __init__(self, path: str | Path, hint: str = "--overwrite on the command line, overwrite=True from Python"
                 ) -> None:
        self.path = Path(path)
        super().__init__(f"{self.path}: already exists; refusing to overwrite it ({hint})")


class Terminated(KeyboardInterrupt):
    """Raised in the main thread when the process receives SIGTERM inside :func:`sigterm_raises`.

    A ``KeyboardInterrupt``, so that every clean-up written for Ctrl-C (temporary folders, half-written files)
    also runs when a scheduler or ``kill`` stops the process; the command line exits with 143 (128 + SIGTERM).
    """


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated(f"terminated by signal {signum}")


@contextlib.contextmanager
def sigterm_raises(only_if_default: bool = False) -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`Terminated` instead of killing the process outright.

    Does nothing outside the main thread (Python delivers signals there only). With ``only_if_default`` the
    handler is installed only where SIGTERM still has its default action (library code: an application's own
    handler is left alone). The previous handler is restored on exit.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGTERM)
    if only_if_default and previous is not signal.SIG_DFL:  # None: a handler not set from Python, also kept
        yield
        return
    signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


DEFERRED_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""The signals :func:`signals_deferred` holds back: Ctrl-C and a scheduler's or ``kill``'s stop."""


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM are recorded instead of acted on; on leaving it the previous handlers are
    restored and a recorded signal is delivered to them (the first one received), so it interrupts what follows
    the block instead of the block itself.

    For the few steps that must not stop half-way: creating a folder and taking note of it, removing a staged
    folder, renaming the finished one into place. Python runs signal handlers in the main thread whichever thread
    the operating system hands the signal to, so replacing the handlers (not the thread's signal mask) holds them
    back. Outside the main thread (where Python cannot set handlers) the block runs as it is.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def record(signum: int, frame: object) -> None:
        received.append(signum)

    previous = {}
    try:
        for signum in DEFERRED_SIGNALS:
            previous[signum] = signal.signal(signum, record)
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)
        if received:
            _deliver(received[0], previous.get(received[0]))


def _deliver(signum: int, handler: object) -> None:
    """Act on a signal held back by :func:`signals_deferred` as its own handler would have."""
    if callable(handler):
        handler(signum, None)  # Python's default SIGINT handler raises KeyboardInterrupt, sigterm_raises' Terminated
    elif handler == signal.SIG_DFL or handler is None:
        signal.raise_signal(signum)  # the default action: the process ends, its clean-up done
    # SIG_IGN: ignored, as it would have been


def first_line(exc: BaseException) -> str:
    """The useful sentence of a library exception for a one-line message (SimpleITK's is its last line)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    # SimpleITK errors end with the useful sentence; keep it short
    return lines[-1] if lines else type(exc).__name__


def read_error_reason(exc: BaseException, path: str | Path) -> str:
    """:func:`first_line` of SimpleITK's error for a file it could not read, made true where ITK's is not: its
    MetaImage reader ends a short read of an existing file with ``Reason: No such file or directory`` (the errno text
    of an unrelated call), and its "no reader" error carries a ``sitk::ERROR:`` prefix."""
    reason = first_line(exc)
    p = Path(path)
    if reason.startswith("Reason:") and p.is_file():
        data = _metaimage_data_file(p)
        if data is not None and not data.is_file():
            return f"its voxel data file {data} does not exist (or is not a file)"
        return "its voxel data could not be read: the file ends early or is damaged"
    return re.sub(r"^sitk::ERROR: ", "", reason)


def _metaimage_data_file(path: Path) -> Path | None:
    """The separate data file a MetaImage header (``.mhd``) names in ``ElementDataFile``; ``None`` for data in the
    file itself (``LOCAL``, ``.mha``), a list of files, or a header that cannot be read."""
    try:
        with open(path, "rb") as f:
            head = f.read(65536).decode("latin-1")
    except OSError:
        return None
    match = re.search(r"^\s*ElementDataFile\s*=\s*(.+?)\s*$", head, re.MULTILINE)
    if match is None or match.group(1).upper() == "LOCAL" or match.group(1).upper().startswith("LIST") \
            or "%" in match.group(1):
        return None
    return path.parent / match.group(1)
