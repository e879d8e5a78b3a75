"""A sub-command's ``--help`` text from its module's docstring: one text for the API docs and the command line.

A command module's docstring starts ``"``monai-rigidreg NAME``: one-line summary."``; the paragraphs after it, up to
the first literal block (a paragraph ending ``::``), describe the command. :func:`add_command` makes the summary the
command's ``help`` (the line of ``monai-rigidreg --help``) and the description its ``--help`` text, without reST's
double back-quotes. :func:`outputs_listing` is the list of written files a command prints at its end. Imports nothing
beyond ``argparse`` (``monai-rigidreg --help`` builds every parser).
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable, Mapping

__all__ = ["command_help", "add_command", "outputs_listing"]


def command_help(doc: str) -> tuple[str, str]:
    """``(summary, description)`` of a command module's docstring, as plain text.

    >>> command_help('''``monai-rigidreg x``: do X.
    ...
    ... Reads ``A`` and writes B.
    ...
    ... Example::
    ...
    ...     monai-rigidreg x A''')
    ('do X', 'Reads A and writes B.')
    """
    paragraphs = [p.strip() for p in re.split(r"\n\s*\n", doc.strip())]
    summary = re.sub(r"^``[^`]*``:\s*", "", paragraphs[0]).rstrip(".")
    body = []
    for p in paragraphs[1:]:
        if p.endswith("::"):
            break
        body.append(" ".join(p.split()))
    return _plain(" ".join(summary.split())), _plain("\n\n".join(body))


def _plain(text: str) -> str:
    return text.replace("``", "")


def add_command(subparsers: argparse._SubParsersAction, name: str, doc: str | None,
                run: Callable[[argparse.Namespace], int], epilog: str | None = None) -> argparse.ArgumentParser:
    """Add sub-command ``name`` to ``subparsers``, its help text from ``doc`` (:func:`command_help`), ``func=run``."""
    summary, description = command_help(doc or "")
    p = subparsers.add_parser(name, help=summary, description=description or None, epilog=epilog)
    p.set_defaults(func=run)
    return p


def outputs_listing(paths: Mapping[str, object]) -> str:
    """``outputs:`` and one line per written file, its name aligned before its path (``register``, ``demo``).

    >>> print(outputs_listing({"a.txt": "out/a.txt", "result.json": "out/result.json"}))
    outputs:
      a.txt        out/a.txt
      result.json  out/result.json
    """
    width = max(map(len, paths), default=0)
    return "\n".join(["outputs:", *(f"  {name:{width}s}  {path}" for name, path in paths.items())])
