"""The ``monai-rigidreg`` command line: simulate, train, register, evaluate, demo.

Each sub-command lives with its feature (``add_parser(subparsers)`` + ``run(args) -> int``); this module only
collects them, sets up logging, and turns failures into one readable line and the exit codes of
:data:`EXIT_CODES` (documented in every command's ``--help`` and in the README's "Exit codes").
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import logging
import os
import sys
import traceback
from collections.abc import Sequence

from monai_rigidreg import __version__
from monai_rigidreg.core.errors import RigidRegError, Terminated, sigterm_raises

__all__ = ["main", "console", "build_parser", "log_level", "EXIT_CODES", "PROMPT_EXIT_COMMANDS"]

EXIT_OK, EXIT_INTERNAL, EXIT_INPUT, EXIT_FLAGGED, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 1, 2, 3, 130, 143
EXIT_CODES = {
    EXIT_OK: "success (a registration flagged as a likely failure too, unless --fail-on-flag)",
    EXIT_INTERNAL: "internal failure (a bug: rerun with -v for the traceback and report it)",
    EXIT_INPUT: "usage error or bad input: a missing, unreadable or unsuitable file, a bad option value, an output "
                "folder that exists or cannot be made",
    EXIT_FLAGGED: "register --fail-on-flag: the registration was flagged as a likely failure (outputs written; "
                  "why: result.json details.flag_reasons; swapped-looking inputs flag unless --allow-swapped)",
    EXIT_INTERRUPTED: "interrupted (Ctrl-C)",
    EXIT_TERMINATED: "terminated (SIGTERM)",
}
"""The exit status of ``monai-rigidreg``, the same for every sub-command."""

EXIT_CODES_HELP = ("exit status: " + "; ".join(f"{code} {text}" for code, text in EXIT_CODES.items())
                   + ". A failed run leaves no partial output (simulate keeps the finished cases of an interrupted "
                   "run, to resume; its dataset.json appears only when the dataset is complete; train keeps its "
                   "checkpoints).")

# sub-command name -> its module, in the order they appear in --help
COMMANDS = {
    "simulate": "monai_rigidreg.simulation.simulate_command",
    "train": "monai_rigidreg.engine.train_command",
    "register": "monai_rigidreg.registration.register_command",
    "evaluate": "monai_rigidreg.evaluation.evaluate_command",
    "demo": "monai_rigidreg.demo",
    "serve": "monai_rigidreg.serve.cli",
}
COMMAND_MODULES = tuple(COMMANDS.values())


def _command_in(argv: Sequence[str]) -> str | None:
    """The sub-command named in ``argv`` (the first word that is not an option), if it is one of :data:`COMMANDS`."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


def build_parser(command: str | None = None, with_commands: bool = True) -> argparse.ArgumentParser:
    """The argument parser with every available sub-command, or with ``command`` alone (``with_commands=False``:
    none, the global options only, e.g. for ``--version``).

    A sub-command's module defines its parser without its stack (torch, MONAI, the simulator are imported in its
    ``run``), so ``monai-rigidreg --help`` imports neither torch nor MONAI; ``monai-rigidreg register`` builds its
    own parser only (``python -X importtime -m monai_rigidreg.cli --help``; ``benchmarks/speed/bench_speed.py`` times
    the command).
    """
    parser = argparse.ArgumentParser(
        prog="monai-rigidreg",
        description="Rigid 6-DoF CBCT to planning-CT registration (MONAI plugin).",
        epilog=EXIT_CODES_HELP,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    _add_verbosity(parser, defaults=True)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in ([COMMANDS[command]] if command in COMMANDS else COMMAND_MODULES) if with_commands else ():
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name is not None and name.startswith(exc.name):
                continue  # this sub-command is not part of this installation
            raise
        _add_verbosity(module.add_parser(sub), defaults=False)
    for command in sub.choices.values():
        command.epilog = f"{command.epilog}\n\n{EXIT_CODES_HELP}" if command.epilog else EXIT_CODES_HELP
    return parser


def _add_verbosity(parser: argparse.ArgumentParser, defaults: bool) -> None:
    """``-v`` / ``-q`` on the main parser and on every sub-command (``monai-rigidreg register -q ...`` works too);
    the sub-commands' copies leave the main parser's value alone unless given (``argparse.SUPPRESS``), and replace
    it when given."""
    default = 0 if defaults else argparse.SUPPRESS
    parser.add_argument("-v", "--verbose", action="count", default=default,
                        help="more log output (-v: debug)")
    parser.add_argument("-q", "--quiet", action="count", default=default,
                        help="less log output (-q: warnings and errors only, -qq: errors only)")


def _unrecognized(parser: argparse.ArgumentParser, command: str | None, extra: Sequence[str]) -> None:
    """Exit as argparse does for unrecognized arguments, with the usage of the sub-command they were given to and,
    for an option, the closest option it has (``register --fixd``: did you mean --fixed?)."""
    target = parser
    for action in parser._actions:  # noqa: SLF001 - argparse keeps its sub-parsers in a private action
        if isinstance(action, argparse._SubParsersAction) and command in action.choices:
            target = action.choices[command]
    options = [o for a in target._actions for o in a.option_strings if o.startswith("--")]  # noqa: SLF001
    hints = []
    for word in extra:
        if not word.startswith("--"):
            continue
        close = difflib.get_close_matches(word.split("=", 1)[0], options, n=1, cutoff=0.75)
        if close:
            hints.append(f"{word}: did you mean {close[0]}?")
    target.error(f"unrecognized arguments: {' '.join(extra)}" + (f" ({'; '.join(hints)})" if hints else ""))


def log_level(verbose: int, quiet: int) -> int:
    """The logging level for ``-v``/``-q`` counts: info by default, debug with ``-v``, warning with ``-q``,
    error with ``-qq``."""
    return {1: logging.DEBUG, 0: logging.INFO, -1: logging.WARNING}.get(max(-2, min(1, verbose - quiet)),
                                                                         logging.ERROR)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``monai-rigidreg`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    command = _command_in(argv)
    # --version among options alone needs no sub-command parser; with a word that is no command, or --help,
    # argparse needs them all to say what the commands are (their modules import no torch or MONAI: the parsers
    # are built in about 0.1 s, tests/test_threads_and_startup.py)
    version_only = ("--version" in argv and all(a.startswith("-") for a in argv)
                    and not {"-h", "--help"} & set(argv))
    parser = build_parser(command, with_commands=not version_only)
    args, extra = parser.parse_known_args(argv)
    if extra:  # a mistyped option: the sub-command's usage, not the top level's (argparse's own error, exit 2)
        _unrecognized(parser, getattr(args, "command", None), extra)
    logging.basicConfig(
        level=log_level(args.verbose, args.quiet),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return EXIT_INPUT  # a usage error, as argparse's own
    prog = f"monai-rigidreg {args.command}"
    try:
        with sigterm_raises():  # SIGTERM runs the same clean-up as Ctrl-C: no temporary folders left behind
            return int(args.func(args) or 0)
    except RigidRegError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except Terminated:
        print(f"{prog}: terminated", file=sys.stderr)
        return EXIT_TERMINATED
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as exc:  # the file system refused (permissions, disk full, ...): the user's to fix
        where = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
        print(f"{prog}: error: {where + ': ' if where else ''}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_INPUT
    except Exception as exc:  # noqa: BLE001 - the last line of defence: one line, the traceback on request
        if getattr(args, "verbose", 0) > 0:
            traceback.print_exc()
        first = str(exc).strip().splitlines()
        print(f"{prog}: internal error: {type(exc).__name__}: {first[0] if first else ''} (a bug; rerun with -v "
              "for the traceback and report it)", file=sys.stderr)
        return EXIT_INTERNAL


PROMPT_EXIT_COMMANDS = frozenset({"register"})
"""Sub-commands after which the console script ends the process at once (``os._exit``) instead of tearing the
interpreter down: once torch is loaded, the teardown (module and object finalisation) takes a few tenths of a
second on a 2-core machine (``benchmarks/speed/bench_speed.py``'s command rows with and without
``MONAI_RIGIDREG_FULL_EXIT=1``: 2.90 s against 3.10 s; ``docs/results.md``, "Speed").
Everything a command writes is closed by then, its worker threads joined, and logging and the standard streams are
flushed first. ``MONAI_RIGIDREG_FULL_EXIT=1`` (or a loaded ``coverage``) keeps the normal
exit, for tools that act at interpreter exit."""


def console(argv: Sequence[str] | None = None) -> None:
    """The ``monai-rigidreg`` console script: :func:`main`, then the process exits with its code (promptly after the
    commands of :data:`PROMPT_EXIT_COMMANDS`; an exception :func:`main` does not handle, e.g. ``SystemExit`` from
    ``--help``, exits as usual)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    code = main(argv)
    if (_command_in(argv) in PROMPT_EXIT_COMMANDS and not os.environ.get("MONAI_RIGIDREG_FULL_EXIT")
            and "coverage" not in sys.modules):
        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a closed or broken pipe: nothing more to say
                pass
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    console()
