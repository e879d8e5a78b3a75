"""The command line as a whole (monai_rigidreg.cli): device strings refused up front, exit codes documented in every
help and the README, internal failures in one line.

Split from the former tests/test_reliability.py (same assertions).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import last_line, listing, run_cli

from monai_rigidreg.cli import EXIT_CODES, main

ROOT = Path(__file__).resolve().parents[1]


def test_bad_device_strings_are_refused_before_any_work(pair, tmp_path, capsys):
    out = tmp_path / "out"
    for args in (["register", "--fixed", pair["fixed"], "--moving", pair["moving"], "--output-dir", out],
                 ["demo", "--output-dir", out]):
        code, err = run_cli(capsys, [*args, "--device", "gpu7"])
        assert code == 2 and "device 'gpu7' is not a device name (use auto, cpu, cuda or cuda:N)" in last_line(err)
        assert "Traceback" not in err
    datalist = tmp_path / "one.json"
    datalist.write_text(json.dumps({"training": [{"fixed": pair["fixed"], "moving": pair["moving"],
                                                  "params": [0.0] * 6}]}))
    code, err = run_cli(capsys, ["evaluate", "--datalist", datalist, "--output-dir", out, "--device", "gpu7"])
    assert code == 2 and "'gpu7' is not a device name" in last_line(err)
    assert listing(tmp_path) == ["one.json"]


def test_exit_codes_are_documented_in_every_help_and_the_readme(capsys):
    for command in ("simulate", "train", "register", "evaluate", "demo"):
        with pytest.raises(SystemExit) as info:
            main([command, "--help"])
        assert info.value.code == 0
        text = " ".join(capsys.readouterr().out.split())
        for code in EXIT_CODES:
            assert f" {code} " in text.split("exit status:")[1], (command, code)
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme.split("### Exit codes", 1)[1].split("\n#", 1)[0]
    for code in EXIT_CODES:
        assert f"| {code} |" in section, code
    assert main([]) == 2  # no command: a usage error, as argparse's own
    with pytest.raises(SystemExit) as info:
        main(["register", "--fixed"])
    assert info.value.code == 2


def test_every_option_of_every_command_says_what_it_does():
    import argparse

    from monai_rigidreg.cli import build_parser

    silent = []

    def walk(parser: argparse.ArgumentParser, path: list[str]) -> None:
        for action in parser._actions:  # noqa: SLF001 - argparse keeps sub-parsers in a private list
            if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
                for name, sub in action.choices.items():
                    walk(sub, [*path, name])
            elif action.option_strings and not action.help:
                silent.append(f"{' '.join(path)} {action.option_strings[-1]}")

    walk(build_parser(), ["monai-rigidreg"])
    assert silent == []


def test_the_demo_s_help_names_every_built_in_phantom():
    import argparse

    from monai_rigidreg.cli import build_parser
    from monai_rigidreg.simulation.phantoms import PHANTOMS

    sub = next(a for a in build_parser("demo")._actions if isinstance(a, argparse._SubParsersAction))  # noqa: SLF001
    phantom = next(a for a in sub.choices["demo"]._actions if "--phantom" in a.option_strings)  # noqa: SLF001
    named = {part.split("(")[0].strip() for part in phantom.help.split("|")}
    assert set(PHANTOMS) <= named, (PHANTOMS, named)


def test_internal_failures_are_one_line_with_exit_1_and_file_system_errors_exit_2(monkeypatch, capsys):
    import monai_rigidreg.registration.register_command as register_cli

    args = ["register", "--fixed", "ct", "--moving", "cbct", "--output-dir", "out"]

    def bug(_):
        raise ZeroDivisionError("float division by zero")

    monkeypatch.setattr(register_cli, "run", bug)
    code, err = run_cli(capsys, args)
    assert code == 1 and "Traceback" not in err
    assert last_line(err).startswith("monai-rigidreg register: internal error: ZeroDivisionError: float division by "
                                     "zero (a bug; rerun with -v")
    code, err = run_cli(capsys, ["-v", *args])
    assert code == 1 and "Traceback" in err

    def denied(_):
        raise PermissionError(13, "Permission denied", "/data/out")

    monkeypatch.setattr(register_cli, "run", denied)
    code, err = run_cli(capsys, args)
    assert (code, last_line(err)) == (2, "monai-rigidreg register: error: /data/out: Permission denied")


def test_a_mistyped_option_gets_the_sub_commands_usage_and_the_closest_option(capsys):
    """``register --fixd`` printed the top-level usage, which does not list register's options."""
    for argv, usage, hint in ((["register", "--fixd", "ct.nii.gz", "--output-dir", "out"], "monai-rigidreg register",
                               "did you mean --fixed?"),
                              (["simulate", "--output-dir", "o", "--phantm", "synth"], "monai-rigidreg simulate",
                               "did you mean --phantom?"),
                              (["--bogus"], "monai-rigidreg [-h]", None)):
        with pytest.raises(SystemExit) as info:
            main(argv)
        err = capsys.readouterr().err
        assert info.value.code == 2 and err.startswith(f"usage: {usage}"), err
        assert "unrecognized arguments" in last_line(err)
        assert (hint in last_line(err)) if hint else "did you mean" not in err
