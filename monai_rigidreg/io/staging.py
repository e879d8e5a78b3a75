"""Output folders that appear complete or not at all: written aside, renamed into place without ever replacing a
folder another process filled meanwhile (``renameat2(RENAME_NOREPLACE)`` where available).

:func:`staged_output_dir` is what :func:`~monai_rigidreg.export.outputs.write_outputs` and the demo write through.
Ctrl-C or SIGTERM at any point leaves the finished folder or nothing: the steps that must not stop half-way (making
the staged folder and taking note of it, removing it after a failure, renaming it into place) run with the signals
held back (:func:`~monai_rigidreg.core.errors.signals_deferred`) and act on them right after. The writers call
:func:`step` between their steps: a test sets :data:`step_hook` to interrupt them at each
(``tests/io/test_staging_signals.py``).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import functools
import os
import secrets
import shutil
from collections.abc import Callable, Collection, Iterator
from pathlib import Path
from typing import Any

from monai_rigidreg.core.errors import InputError, OutputExistsError, signals_deferred, sigterm_raises
from monai_rigidreg.io.volumes import check_output_dir, make_dirs, remove_made_dirs

__all__ = ["staged_output_dir", "check_replaceable", "step", "step_hook"]

step_hook: Callable[[str], None] | None = None
"""Called by :func:`step` with the name of each step of an output writer (``None``: nothing). For tests: a hook
that raises ``KeyboardInterrupt`` or sends the process SIGINT / SIGTERM at a step checks that an interruption there
leaves the finished folder or nothing."""


def step(name: str) -> None:
    """A point between two steps of an output writer (``staged:<name>`` inside :func:`staged_output_dir`, the file
    just written in :func:`~monai_rigidreg.export.outputs.write_outputs`): :data:`step_hook`'s."""
    if step_hook is not None:
        step_hook(name)


@contextlib.contextmanager
def staged_output_dir(output_dir: str | Path, overwrite: bool = False,
                      replaceable: Collection[str] | None = None) -> Iterator[Path]:
    """``with staged_output_dir(out) as tmp:`` write into ``tmp``, a new hidden sibling of ``out``; at the end of
    the block ``tmp`` is renamed to ``out`` (as :func:`write_outputs` describes). If the block raises (including
    Ctrl-C, and SIGTERM where nothing else handles it), ``tmp`` and the parent folders made for it are removed and
    ``out`` is left as it was.

    ``overwrite`` replaces an existing ``out`` only where every entry in it is one of the names in ``replaceable``
    (the files this writer makes): a folder that also holds anything else (the input images, notes) is refused
    before anything runs, so ``--overwrite`` can never delete what it did not write. ``None``: any folder (callers
    that own the whole folder).

    Raises:
        OutputExistsError, InputError: as :func:`~monai_rigidreg.io.check_output_dir`, before the block runs, or
            :class:`~monai_rigidreg.core.errors.OutputExistsError` at the end where another process filled ``out``.
    """
    out = check_output_dir(output_dir, overwrite)
    if overwrite and replaceable is not None:
        check_replaceable(out, replaceable)
    if out.is_symlink():
        out = out.resolve()  # a link to a folder: the folder is what gets replaced, the link stays
    with sigterm_raises(only_if_default=True):  # the command line installs its own handler for the whole run
        made: list[Path] = []
        tmp = None
        try:
            with signals_deferred():  # made and tmp name every folder this makes, whenever a signal comes
                made = make_dirs(out.parent)
                tmp = _new_sibling(out, "tmp")
            step("staged:made")
            yield tmp
            step("staged:written")
            with signals_deferred():  # renamed into place, or not at all (an old folder put back)
                _move_into_place(tmp, out, overwrite)
                tmp = None
            step("staged:moved")
        except BaseException:
            with signals_deferred():  # a second Ctrl-C does not stop the clean-up half-way
                step("staged:cleanup")
                if tmp is not None:
                    shutil.rmtree(tmp, ignore_errors=True)
                remove_made_dirs(made)
            raise


def check_replaceable(out: str | Path, replaceable: Collection[str]) -> None:
    """Refuse to replace ``out`` (with ``--overwrite``) where it holds anything but entries named in
    ``replaceable``: it would delete what this package did not write (the input images, for example)."""
    p = Path(out)
    if not p.is_dir():
        return
    foreign = sorted(e.name for e in p.iterdir() if e.name not in set(replaceable))
    if foreign:
        raise OutputExistsError(p, f"--overwrite replaces only a folder of earlier outputs, and this one also holds "
                                   f"{', '.join(foreign[:5])}{' ...' if len(foreign) > 5 else ''}; choose another "
                                   "--output-dir")


def _sibling_name(out: Path, tag: str) -> Path:
    stem = out.name.encode()[:200].decode(errors="ignore")  # the name stays under the 255-byte limit
    return out.with_name(f".{stem}.{tag}-{secrets.token_hex(4)}")


def _new_sibling(out: Path, tag: str) -> Path:
    """A new hidden folder next to ``out`` (``os.mkdir``: the permissions the final folder should have, unlike
    ``tempfile.mkdtemp``'s 0700)."""
    for _ in range(100):
        path = _sibling_name(out, tag)
        try:
            path.mkdir()
        except FileExistsError:
            continue
        return path
    raise FileExistsError(errno.EEXIST, "could not create a temporary folder", str(out.parent))  # pragma: no cover


@functools.cache
def _renameat2() -> Any:
    """glibc's ``renameat2`` (Linux), or ``None`` where the C library has none."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


_AT_FDCWD, _RENAME_NOREPLACE = -100, 1


def _rename_noreplace(src: Path, dst: Path) -> None:
    """Rename ``src`` to ``dst``, failing (``FileExistsError`` / ``OSError(ENOTEMPTY)``) where ``dst`` exists.

    ``renameat2(RENAME_NOREPLACE)`` where the kernel and file system offer it; otherwise ``os.rename`` after a
    check: POSIX ``rename`` replaces at most an empty directory, never one holding files.
    """
    fn = _renameat2()
    if fn is not None:
        if fn(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst), _RENAME_NOREPLACE) == 0:
            return
        err = ctypes.get_errno()
        if err not in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP):
            raise OSError(err, os.strerror(err), str(src), None, str(dst))
    if os.path.lexists(dst):
        raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(dst))
    os.rename(src, dst)


def _move_into_place(tmp: Path, out: Path, overwrite: bool) -> None:
    """Publish the finished folder ``tmp`` as ``out`` without ever deleting files another process put there."""
    aside, was_empty = None, False
    if out.is_dir():
        if overwrite and any(out.iterdir()):
            aside = _sibling_name(out, "old")
            os.rename(out, aside)  # a new random name: nothing is replaced
        else:
            try:
                out.rmdir()  # an empty folder (given, or made by hand); refused if it was filled meanwhile
            except OSError as exc:
                if exc.errno in (errno.ENOTEMPTY, errno.EEXIST):
                    raise OutputExistsError(out, "another process wrote into it while this one ran; its files are "
                                            "kept") from exc
                raise InputError(f"cannot replace the empty output folder ({exc.strerror})", out) from exc
            was_empty = True
    try:
        _rename_noreplace(tmp, out)
    except BaseException as exc:
        if was_empty:
            with contextlib.suppress(OSError):
                out.mkdir()  # the empty folder as it was
        if aside is not None:
            try:
                _rename_noreplace(aside, out)  # put the old folder back
            except OSError:
                shutil.rmtree(aside, ignore_errors=True)  # another run replaced it, as both were asked to
        if isinstance(exc, OSError) and exc.errno in (errno.EEXIST, errno.ENOTEMPTY):
            raise OutputExistsError(out, "another process created it while this one ran; its files are kept") from exc
        raise
    if aside is not None:
        shutil.rmtree(aside, ignore_errors=True)
