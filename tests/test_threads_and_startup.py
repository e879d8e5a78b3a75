"""The package's thread policy, ``--threads`` and what ``monai-rigidreg register`` imports (the speed issue)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import SimpleITK as sitk
import torch

from monai_rigidreg.core.device import set_cpu_threads
from monai_rigidreg.core.errors import InputError


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


NOT_ON_THE_REGISTER_PATH = {
    "numpy.ma": "np.percentile's np.unique imports it (the QC window: export.qc_figure.percentiles instead)",
    "tqdm.auto": "the batch's progress bar (registration.pairs, imported for --datalist only; tqdm itself comes "
                 "with torch.hub)",
    "monai_rigidreg.registration.pairs": "the batch (--datalist)",
    "monai_rigidreg.networks.rigid_net": "the reference design (ablation)",
    "monai_rigidreg.networks.transformer": "training's spatial transformer",
    "monai_rigidreg.evaluation": "the evaluation",
    "monai_rigidreg.simulation": "the simulator",
    "matplotlib": "the QC figure is drawn with Pillow",
}
"""Modules a one-pair ``monai-rigidreg register`` does not import, and why each is not needed
(``python -X importtime``; ``benchmarks/README.md``)."""


def test_register_command_runs_without_importing_monai(fast_pair, tmp_path):
    """The whole ``monai-rigidreg register`` (bundle, network, registration, every default output, QC figure
    included) imports no MONAI module: ``import monai`` alone costs about 6 s on 2 cores (the speed issue); nor
    sympy, which torch imports on its first argument check of some functions (0.24 s; torch.unravel_index did);
    nor what one pair does not need (:data:`NOT_ON_THE_REGISTER_PATH`).
    The estimate is the shipped model's on the known motion (as in ``tests/test_register.py``)."""
    import json

    from conftest import KNOWN_MOTION

    out = tmp_path / "out"
    code = ("import sys; from monai_rigidreg.cli import main; "
            f"rc = main(['register', '--fixed', {str(fast_pair['fixed'])!r}, '--moving', "
            f"{str(fast_pair['moving'])!r}, '--output-dir', {str(out)!r}, '--threads', '2', '-q']); "
            "print(rc, sorted(m for m in sys.modules if m == 'monai' or m.startswith('monai.')), "
            f"'sympy' in sys.modules, sorted(set({sorted(NOT_ON_THE_REGISTER_PATH)!r}) & set(sys.modules)))")
    assert _python(code).splitlines()[-1] == "0 [] False []"  # the command prints its result first
    result = json.loads((out / "result.json").read_text())
    assert result["details"]["cpu_threads"] == 2  # --threads 2: exactly 2, whatever else runs (no adapting)
    assert {"registered.nii.gz", "qc.png", "transform.tfm"} <= {p.name for p in out.iterdir()}
    est = [result["params"][k] for k in ("tx", "ty", "tz", "rx", "ry", "rz")]
    assert max(abs(a - b) for a, b in zip(est[:3], KNOWN_MOTION[:3])) < 1.5
    assert max(abs(a - b) for a, b in zip(est[3:], KNOWN_MOTION[3:])) < 1.0


def test_command_detection_skips_global_options():
    from monai_rigidreg.cli import _command_in

    assert _command_in(["-v", "register", "--fixed", "x"]) == "register"
    assert _command_in(["--version"]) is None
    assert _command_in(["nonsense", "register"]) is None  # argparse reports the bad command


def test_console_script_ends_register_promptly_with_complete_outputs_and_its_exit_code(fast_pair, tmp_path):
    """The console script (``python -m monai_rigidreg.cli``, as the installed ``monai-rigidreg``) ends ``register``
    with ``os._exit`` (no interpreter teardown: no atexit handler runs) after flushing: the outputs are complete,
    the printed listing is whole, and the exit code is the command's (2 for a bad input, whose message arrives);
    ``MONAI_RIGIDREG_FULL_EXIT=1`` and other commands exit normally (atexit handlers run)."""
    import json

    import SimpleITK as sitk_

    hook = "import atexit; atexit.register(lambda: print('ATEXIT', flush=True)); "
    run = "from monai_rigidreg.cli import console; console()"
    out = tmp_path / "out"
    env = {k: v for k, v in os.environ.items() if k != "MONAI_RIGIDREG_FULL_EXIT"}
    argv = ["register", "--fixed", str(fast_pair["fixed"]), "--moving", str(fast_pair["moving"]), "--output-dir",
            str(out), "--threads", "2"]
    done = subprocess.run([sys.executable, "-c", hook + run, *argv], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    assert "ATEXIT" not in done.stdout and "result.json" in done.stdout and "qc.png" in done.stdout
    assert json.loads((out / "result.json").read_text())["params"]
    fixed_size = sitk_.ReadImage(str(fast_pair["fixed"])).GetSize()
    assert sitk_.ReadImage(str(out / "registered.nii.gz")).GetSize() == fixed_size
    bad = subprocess.run([sys.executable, "-c", hook + run, "register", "--fixed", str(tmp_path / "missing.nii.gz"),
                          "--moving", str(fast_pair["moving"]), "--output-dir", str(tmp_path / "o2")],
                         capture_output=True, text=True, env=env)
    assert bad.returncode == 2 and "missing.nii.gz" in bad.stderr and "ATEXIT" not in bad.stdout
    full = subprocess.run([sys.executable, "-c", hook + run, "register", "--fixed", str(tmp_path / "missing.nii.gz"),
                           "--moving", str(fast_pair["moving"]), "--output-dir", str(tmp_path / "o3")],
                          capture_output=True, text=True, env={**env, "MONAI_RIGIDREG_FULL_EXIT": "1"})
    assert full.returncode == 2 and "ATEXIT" in full.stdout
    version = subprocess.run([sys.executable, "-c", hook + run, "--version"], capture_output=True, text=True, env=env)
    assert version.returncode == 0 and "ATEXIT" in version.stdout


@pytest.mark.skipif(not os.path.exists("/proc/loadavg"), reason="busy_cores reads /proc/loadavg (Linux)")
def test_busy_cores_sees_a_busy_loop_and_adaptive_threads_leaves_it_its_core():
    """A process computing all along (a busy loop) keeps a core busy: busy_cores counts it in every reading and
    adaptive_threads leaves it that core (at least one thread always); the reading ends when the loop does."""
    from monai_rigidreg.core.device import adaptive_threads, busy_cores

    available = len(os.sched_getaffinity(0))
    loop = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        import time

        time.sleep(0.5)
        readings = [busy_cores() for _ in range(5)]
        assert min(readings) >= 1
        assert adaptive_threads(64) <= max(1, available - 1)
        assert adaptive_threads(1) == 1
    finally:
        loop.kill()
        loop.wait()


def test_adaptive_threads_without_a_reading_keeps_the_count(monkeypatch):
    import monai_rigidreg.core.device as device

    monkeypatch.setattr(device, "_runnable_tasks", lambda: None)
    assert device.busy_cores() is None and device.adaptive_threads(3) == 3
    counts = iter([5, 2, 4])  # the fewest of the readings, less the caller's own thread
    monkeypatch.setattr(device, "_runnable_tasks", lambda: next(counts))
    assert device.busy_cores(samples=3, interval_s=0.0) == 1


def test_top_level_help_imports_neither_torch_nor_monai():
    """``monai-rigidreg --help``, ``monai-rigidreg`` alone and every sub-command's ``--help`` answer without torch or
    MONAI (they took 6-9 s on 2 cores when the parsers imported the simulator, the training stack and the evaluation):
    every sub-command is still listed, and ``simulate --help`` names every built-in phantom."""
    from monai_rigidreg.cli import COMMANDS
    from monai_rigidreg.simulation.phantoms import PHANTOMS

    code = ("import sys, contextlib, io; from monai_rigidreg.cli import main\n"
            "for argv in (['--help'], [], *([c, '--help'] for c in sys.argv[1:])):\n"
            "    out = io.StringIO()\n"
            "    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):\n"
            "        try:\n            code = main(argv)\n        except SystemExit as e:\n            code = e.code\n"
            "    print(repr(out.getvalue()), code)\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'monai', 'SimpleITK', 'numpy')))")
    done = subprocess.run([sys.executable, "-c", code, *COMMANDS], capture_output=True, text=True, check=True)
    *helps, imported = done.stdout.strip().splitlines()
    assert imported == "[]"
    top, bare, *commands = [(eval(text), int(code)) for text, code in (h.rsplit(" ", 1) for h in helps)]  # noqa: S307
    assert top[1] == 0 and bare[1] == 2  # no command: a usage error, with the help on stderr
    for name in COMMANDS:
        assert name in top[0] and name in bare[0]
    assert all(code == 0 for _, code in commands)
    simulate = " ".join(commands[list(COMMANDS).index("simulate")][0].split())
    assert all(name in simulate for name in PHANTOMS)


def test_version_and_package_import_do_not_import_torch():
    """``import monai_rigidreg`` and ``monai-rigidreg --version`` import neither torch nor MONAI (the public names
    load on first use); the geometry names still resolve, to the geometry module's own objects."""
    import monai_rigidreg

    code = ("import sys, contextlib, io; import monai_rigidreg as m; from monai_rigidreg.cli import main\n"
            "out = io.StringIO()\n"
            "with contextlib.redirect_stdout(out):\n"
            "    try:\n        main(['--version'])\n    except SystemExit as e:\n        code = e.code\n"
            "print(out.getvalue().strip(), code, 'torch' in sys.modules, 'monai' in sys.modules)\n"
            "from monai_rigidreg import Grid, params_to_matrix\n"
            "import monai_rigidreg.core.geometry as g\n"
            "print(Grid is g.Grid, params_to_matrix is g.params_to_matrix, 'torch' in sys.modules)")
    lines = _python(code).splitlines()
    assert lines[-2] == f"monai-rigidreg {monai_rigidreg.__version__} 0 False False"
    assert lines[-1] == "True True True"
    # a submodule as an attribute after a plain import (a MONAI config's "$monai_rigidreg.core.geometry.PARAM_NAMES")
    code = ("import monai_rigidreg as m; print(m.core.geometry.PARAM_NAMES, m.core.geometry is "
            "__import__('sys').modules['monai_rigidreg.core.geometry'])")
    assert _python(code) == "('tx', 'ty', 'tz', 'rx', 'ry', 'rz') True"
    assert len(monai_rigidreg.__all__) == len(set(monai_rigidreg.__all__))
    with pytest.raises(AttributeError, match="no attribute 'no_such_thing'"):
        monai_rigidreg.no_such_thing  # noqa: B018
    # a mistyped command with --version still lists the commands
    done = subprocess.run([sys.executable, "-m", "monai_rigidreg.cli", "regster", "--version"], capture_output=True,
                          text=True)
    assert done.returncode == 2 and "choose from 'simulate', 'train', 'register'" in done.stderr
