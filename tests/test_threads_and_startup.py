"""The package's thread policy, ``--threads`` and what ``monai-rigidreg register`` imports (the speed issue)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import SimpleITK as sitk
import torch

from monai_rigidreg.device import set_cpu_threads
from monai_rigidreg.errors import InputError


def _python(code: str, **env: str | None) -> str:
    environ = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    environ.update({k: v for k, v in env.items() if v is not None})
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=environ, check=True)
    return out.stdout.strip()


SHOW = "import os, monai_rigidreg as m; print(os.environ.get('OMP_WAIT_POLICY'), m.THREAD_POLICY_APPLIED)"


def test_import_sets_a_passive_wait_policy_unless_the_caller_chose():
    assert _python(SHOW) == "PASSIVE True"
    assert _python(SHOW, OMP_WAIT_POLICY="ACTIVE") == "ACTIVE False"  # the caller's choice stands
    # torch already loaded libgomp: setting the variable now would do nothing, so the package leaves it alone
    assert _python("import torch; " + SHOW) == "None False"


def test_set_cpu_threads_sets_torch_and_simpleitk_and_rejects_zero():
    before_torch, before_itk = torch.get_num_threads(), sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
    try:
        assert set_cpu_threads(1) == 1
        assert torch.get_num_threads() == 1
        assert sitk.ProcessObject.GetGlobalDefaultNumberOfThreads() == 1
        assert set_cpu_threads(None) == 1  # None leaves the settings as they are
        with pytest.raises(InputError, match="at least 1"):
            set_cpu_threads(0)
    finally:
        torch.set_num_threads(before_torch)
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(before_itk)


def test_register_command_builds_its_own_parser_only():
    code = ("import sys; from monai_rigidreg.cli import build_parser; "
            "p = build_parser('register'); a = p.parse_args(['register', '--fixed', 'f', '--moving', 'm', "
            "'--output-dir', 'o', '--threads', '1']); "
            "print(a.threads, sorted(p._subparsers._group_actions[0].choices), "
            "'monai_rigidreg.simulation' in sys.modules, 'monai' in sys.modules)")
    assert _python(code) == "1 ['register'] False False"
    # without a command every sub-command is there (the main --help)
    code = ("from monai_rigidreg.cli import build_parser, COMMANDS; "
            "print(sorted(build_parser()._subparsers._group_actions[0].choices) == sorted(COMMANDS))")
    assert _python(code) == "True"


def test_command_detection_skips_global_options():
    from monai_rigidreg.cli import _command_in

    assert _command_in(["-v", "register", "--fixed", "x"]) == "register"
    assert _command_in(["--version"]) is None
    assert _command_in(["nonsense", "register"]) is None  # argparse reports the bad command
