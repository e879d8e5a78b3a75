"""The ``monai-rigidreg`` command line: simulate, train, register, evaluate, demo.

Each sub-command lives with its feature (``add_parser(subparsers)`` + ``run(args) -> int``); this module only
collects them, sets up logging, and turns the package's own errors into one readable line and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from monai_rigidreg import __version__
from monai_rigidreg.errors import RigidRegError

__all__ = ["main", "build_parser"]

# sub-command modules, in the order they appear in --help
COMMAND_MODULES = (
    "monai_rigidreg.simulation.cli",
    "monai_rigidreg.engine.cli",
    "monai_rigidreg.register_cli",
    "monai_rigidreg.evaluation.cli",
    "monai_rigidreg.demo",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every available sub-command."""
    parser = argparse.ArgumentParser(
        prog="monai-rigidreg",
        description="Rigid 6-DoF CBCT to planning-CT registration (MONAI plugin).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name is not None and name.startswith(exc.name):
                continue  # this sub-command is not part of this installation
            raise
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``monai-rigidreg`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose + 1, 2),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        return int(args.func(args) or 0)
    except RigidRegError as exc:
        print(f"monai-rigidreg {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
