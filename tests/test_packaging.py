"""Packaging: every subpackage is listed in pyproject.toml, the bundle is package data, the CLI has its commands."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import pytest

from monai_rigidreg.cli import build_parser, log_level, main

ROOT = Path(__file__).resolve().parents[1]


def _pyproject() -> dict:
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover
        tomllib = pytest.importorskip("tomli")
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def test_every_subpackage_is_listed():
    listed = set(_pyproject()["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "monai_rigidreg").rglob("__init__.py")}
    assert found <= listed, f"add to [tool.setuptools] packages: {sorted(found - listed)}"
    assert "monai_rigidreg._bundles" in listed


def test_runtime_dependencies_are_declared_with_lower_bounds():
    deps = _pyproject()["project"]["dependencies"]
    assert "torch>=2.2" in deps and "monai>=1.4" in deps and "SimpleITK>=2.3" in deps
    assert not any("==" in d for d in deps), "no pins in the package's own requirements"


def test_cli_commands_and_help(capsys):
    parser = build_parser()
    commands = set(parser._subparsers._group_actions[0].choices)  # noqa: SLF001
    assert {"simulate", "train", "register", "evaluate", "demo"} <= commands
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert "monai-rigidreg" in capsys.readouterr().out


def test_default_bundle_is_found():
    from monai_rigidreg.bundle import bundle_settings, default_bundle_path

    path = default_bundle_path()
    assert (path / "configs" / "inference.json").is_file()
    assert bundle_settings(path)["network_size"] == [64, 64, 64]


@pytest.mark.parametrize(("argv", "level"), [
    ([], logging.INFO), (["-v"], logging.DEBUG), (["-q"], logging.WARNING), (["-qq"], logging.ERROR),
])
def test_verbosity_before_or_after_the_sub_command(argv, level):
    parser = build_parser()
    rest = ["--fixed", "a", "--moving", "b", "--output-dir", "c"]
    for args in (parser.parse_args([*argv, "register", *rest]), parser.parse_args(["register", *argv, *rest])):
        assert log_level(args.verbose, args.quiet) == level


def test_licence_file_ships_with_the_package_metadata():
    text = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert "Apache License" in text and "Version 2.0" in text
    assert _pyproject()["project"]["license"] == {"text": "Apache-2.0"}
