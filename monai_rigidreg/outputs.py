"""The files of a registration: ``transform.tfm``, ``registered.nii.gz``, ``result.json`` and ``qc.png``.

:func:`write_outputs` writes them for a :class:`~monai_rigidreg.registration.RegistrationResult`;
:func:`register_files` reads, registers and writes (the ``register`` command and the bundle's ``inference.json``).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import functools
import json
import logging
import os
import secrets
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import SimpleITK as sitk

from monai_rigidreg.errors import InputError, OutputExistsError, RigidRegError, Terminated, sigterm_raises
from monai_rigidreg.geometry import PARAM_NAMES
from monai_rigidreg.io import (
    check_distinct_inputs,
    check_output_dir,
    load_volume,
    resample,
    save_volume,
    write_transform,
)
from monai_rigidreg.qc import qc_figure
from monai_rigidreg.registration import RegistrationResult, RigidRegistrar, _check_steps

__all__ = ["OUTPUT_FILES", "write_outputs", "register_files", "check_register_inputs", "bundle_check_inputs",
           "bundle_register_files"]

logger = logging.getLogger(__name__)

OUTPUT_FILES: tuple[str, ...] = ("transform.tfm", "registered.nii.gz", "result.json", "qc.png")
"""The files :func:`write_outputs` writes (``qc.png`` only with ``qc=True``)."""


def write_outputs(
    result: RegistrationResult,
    fixed: sitk.Image,
    moving: sitk.Image,
    output_dir: str | Path,
    overwrite: bool = False,
    qc: bool = True,
) -> dict[str, Path]:
    """Write :data:`OUTPUT_FILES` for ``result`` into ``output_dir``.

    Everything is written to a hidden sibling folder first and renamed into place at the end, so a failure, Ctrl-C
    or SIGTERM leaves no partial output and no temporary folder (nor the parent folders this call created). An
    existing non-empty ``output_dir`` is refused unless ``overwrite``, a file of that name always
    (:func:`~monai_rigidreg.io.check_output_dir`). The final rename never replaces a folder that another process
    filled meanwhile (two runs into one new folder: one wins, the other is refused and the winner's files are
    kept); with ``overwrite`` the old folder is renamed aside and removed only once the new one is in place.

    Returns:
        ``{file name: path}`` of the files written.

    Raises:
        OutputExistsError: ``output_dir`` exists (or appeared while this call ran) and is not empty.
    """
    out = check_output_dir(output_dir, overwrite)
    with sigterm_raises(only_if_default=True):  # the command line installs its own handler for the whole run
        made = _make_parents(out.parent)
        tmp = None
        try:
            tmp = _new_sibling(out, "tmp")
            write_transform(result.transform, tmp / "transform.tfm")
            registered = (result.registered if result.registered is not None
                          else resample(moving, fixed, result.transform))
            save_volume(registered, tmp / "registered.nii.gz")
            (tmp / "result.json").write_text(json.dumps(result.to_dict(), indent=2))
            if qc:
                p = result.params
                title = (f"tx={p[0]:.2f} ty={p[1]:.2f} tz={p[2]:.2f} mm   rx={p[3]:.2f} ry={p[4]:.2f} "
                         f"rz={p[5]:.2f} deg   confidence={result.confidence:.2f}"
                         f"{'  FLAGGED' if result.flagged else ''}")
                qc_figure(fixed, moving, registered, tmp / "qc.png", title=title)
            _move_into_place(tmp, out, overwrite)
        except BaseException:
            if tmp is not None:
                shutil.rmtree(tmp, ignore_errors=True)
            _remove_made(made)
            raise
    return {name: out / name for name in OUTPUT_FILES if (out / name).exists()}


def _make_parents(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; return the ones created, deepest first."""
    missing = []
    for d in (folder, *folder.parents):
        if d.exists():
            break
        missing.append(d)
    folder.mkdir(parents=True, exist_ok=True)
    return missing


def _remove_made(made: list[Path]) -> None:
    for d in made:  # deepest first; a folder something else has written into meanwhile stays
        with contextlib.suppress(OSError):
            d.rmdir()


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
    aside = None
    if out.is_dir() and not out.is_symlink():
        if overwrite and any(out.iterdir()):
            aside = _sibling_name(out, "old")
            os.rename(out, aside)  # a new random name: nothing is replaced
        else:
            try:
                out.rmdir()  # an empty folder (given, or made by hand); refused if it was filled meanwhile
            except OSError as exc:
                raise OutputExistsError(out, "another process wrote into it while this one ran; its files are "
                                        "kept") from exc
    try:
        _rename_noreplace(tmp, out)
    except BaseException as exc:
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


def register_files(
    registrar: RigidRegistrar,
    fixed: str | Path,
    moving: str | Path,
    output_dir: str | Path,
    refine: bool = False,
    overwrite: bool = False,
    qc: bool = True,
    cascade_steps: int | None = None,
    fixed_series_uid: str | None = None,
    moving_series_uid: str | None = None,
) -> dict[str, Path]:
    """Load both volumes, register them and write the standard outputs.

    The inputs and the output folder are checked (:func:`check_register_inputs`) before anything is read or
    computed, so a refused run costs nothing and writes nothing.

    Args:
        registrar: the loaded network (:meth:`~monai_rigidreg.registration.RigidRegistrar.from_bundle`).
        fixed, moving: CT and CBCT: NIfTI, MHA, NRRD or a DICOM folder.
        output_dir: the folder to write (must not exist or be empty unless ``overwrite``).
        refine, cascade_steps: as for :func:`~monai_rigidreg.registration.register`.
        overwrite, qc: as for :func:`write_outputs`.
        fixed_series_uid, moving_series_uid: DICOM series to read from a folder holding several.

    Returns:
        ``{file name: path}`` of the files written (the result itself is in ``result.json``).
    """
    check_register_inputs(fixed, moving, output_dir, overwrite, cascade_steps)
    check_distinct_inputs(fixed, moving, fixed_series_uid, moving_series_uid)
    fixed_img = load_volume(fixed, series_uid=fixed_series_uid)
    moving_img = load_volume(moving, series_uid=moving_series_uid)
    result = registrar(fixed_img, moving_img, refine=refine, cascade_steps=cascade_steps)
    paths = write_outputs(result, fixed_img, moving_img, output_dir, overwrite=overwrite, qc=qc)
    logger.info("registered %s to %s: %s (confidence %.2f)", moving, fixed,
                ", ".join(f"{n}={v:.2f}" for n, v in zip(PARAM_NAMES, result.params)), result.confidence)
    return paths


def check_register_inputs(
    fixed: str | Path | None,
    moving: str | Path | None,
    output_dir: str | Path,
    overwrite: bool = False,
    cascade_steps: Any = None,
) -> Path:
    """The checks of a registration run, done once before anything is loaded: both inputs given and present, the
    cascade steps (if given) a whole number >= 1, and an output folder that may be written
    (:func:`~monai_rigidreg.io.check_output_dir`). The ``register`` command and the bundle's ``inference.json``
    both go through it.

    Returns:
        ``output_dir`` as a ``Path``.

    Raises:
        InputError: a missing input (naming it), a bad ``cascade_steps``, an output folder that cannot be made.
        OutputExistsError: the output folder is a file, or not empty and ``overwrite`` is False.
    """
    for name, path in (("fixed", fixed), ("moving", moving)):
        if path is None or not str(path).strip():
            raise InputError(f"no {name} image given: both 'fixed' (the CT) and 'moving' (the CBCT) are needed "
                             "(e.g. --fixed CT.nii.gz --moving CBCT.nii.gz)")
        if not Path(path).exists():
            raise InputError(f"no such file or directory (the {name} image)", path)
    if cascade_steps is not None:
        _check_steps(cascade_steps)
    return check_output_dir(output_dir, overwrite)


@contextlib.contextmanager
def _bundle_errors() -> Iterator[None]:
    """``python -m monai.bundle run`` prints a traceback for anything raised in a config expression, ending with
    MONAI's "Failed to evaluate ConfigExpression"; the package's own errors end the run instead with their message
    on one line and the exit status of the command line (2; 130 for Ctrl-C, 143 for SIGTERM)."""
    try:
        with sigterm_raises(only_if_default=True):
            yield
    except RigidRegError as exc:
        print(f"monai-rigidreg bundle: error: {exc}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None
    except KeyboardInterrupt as exc:
        print("monai-rigidreg bundle: " + ("terminated" if isinstance(exc, Terminated) else "interrupted"),
              file=sys.stderr, flush=True)
        raise SystemExit(143 if isinstance(exc, Terminated) else 130) from None


def bundle_check_inputs(fixed: str | Path | None, moving: str | Path | None, output_dir: str | Path,
                        overwrite: bool = False, cascade_steps: Any = None) -> None:
    """:func:`check_register_inputs` for the bundle's ``inference.json`` (its first ``initialize`` step, before the
    network is built): a bad input ends the run with one line naming the problem and exit status 2.

    For ``python -m monai.bundle run``: it raises ``SystemExit`` rather than an exception.
    """
    with _bundle_errors():
        check_register_inputs(fixed, moving, output_dir, overwrite, cascade_steps)


def bundle_register_files(registrar: RigidRegistrar, fixed: str | Path, moving: str | Path, output_dir: str | Path,
                          **kwargs: Any) -> dict[str, Path]:
    """:func:`register_files` for the bundle's ``inference.json`` (``run``): errors as in :func:`bundle_check_inputs`
    (an unreadable image, for example, ends the run with one line and exit status 2)."""
    with _bundle_errors():
        return register_files(registrar, fixed, moving, output_dir, **kwargs)
