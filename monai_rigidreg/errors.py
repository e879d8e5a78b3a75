"""Exceptions raised for bad user input, with messages that name the file and the problem."""

from __future__ import annotations

from pathlib import Path

__all__ = ["RigidRegError", "InputError", "OutputExistsError"]


class RigidRegError(Exception):
    """Base class of the errors monai-rigidreg raises on purpose."""


class InputError(RigidRegError, ValueError):
    """An input (file, image, transform or argument) is missing, unreadable or unsuitable.

    Args:
        message: what is wrong.
        path: the offending file, if any; it is named in the message.
    """

    def __init__(self, message: str, path: str | Path | None = None) -> None:
        self.path = None if path is None else Path(path)
        super().__init__(f"{self.path}: {message}" if self.path is not None else message)


class OutputExistsError(RigidRegError, FileExistsError):
    """An output would overwrite an existing file or directory and overwriting was not asked for."""

    def __init__(self, path: str | Path, hint: str = "pass overwrite=True (--overwrite on the command line)") -> None:
        self.path = Path(path)
        super().__init__(f"{self.path}: already exists; refusing to overwrite it ({hint})")
