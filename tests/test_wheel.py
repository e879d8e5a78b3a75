"""The built wheel works on its own: installed into a fresh venv, it imports, finds its bundle and registers.

The checkout is an editable install on the development machines, so every check runs the venv's interpreter
from a folder outside the repository and asserts that the venv's copy of the package is the one imported.
The venv sees the machine's site-packages (``--system-site-packages``) for torch, MONAI and SimpleITK; the
wheel itself is installed with ``--no-deps``. The source is copied to a temporary folder first, so the build writes
nothing into the checkout.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import site
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import SimpleITK as sitk

from monai_rigidreg.simulation.toy import blob_ct

ROOT = Path(__file__).resolve().parents[1]
SHIFT_X_MM = 4.0
"""Known motion of the toy pair: the moving image's content sits 4 mm further along +x (LPS) than the fixed's."""


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(PIP_NO_INDEX="1", PIP_DISABLE_PIP_VERSION_CHECK="1", PYTHONNOUSERSITE="1", OMP_NUM_THREADS="2")
    return env


def _run(cmd: list, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=_env(), capture_output=True, text=True,
                          encoding="utf-8", errors="replace",
                          timeout=timeout)
    assert proc.returncode == 0, f"{cmd} exited {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    return proc


def _source_copy(dest: Path) -> Path:
    """The files a wheel is built from, copied so that the build leaves no ``build/`` folder in the checkout."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, dest / name)
    for name in ("monai_rigidreg", "bundles"):
        shutil.copytree(ROOT / name, dest / name, ignore=ignore)
    return dest


def _can_build_without_isolation() -> bool:
    """setuptools >= 64 and a ``bdist_wheel`` command (built in from setuptools 70.1, else the ``wheel`` package)."""
    try:
        import setuptools
    except ImportError:
        return False
    version = tuple(int(v) for v in setuptools.__version__.split(".")[:2] if v.isdigit())
    return version >= (70, 1) or (version >= (64,) and importlib.util.find_spec("wheel") is not None)


def _build_wheel(src: Path, wheels: Path, cwd: Path) -> Path:
    """Build the wheel with this interpreter's setuptools (offline); without one that can, let pip fetch it."""
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-w", wheels, src]
    if _can_build_without_isolation():
        _run([*cmd[:4], "--no-build-isolation", *cmd[4:]], cwd)
    else:
        env = {k: v for k, v in _env().items() if k != "PIP_NO_INDEX"}
        proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True,
                              encoding="utf-8", errors="replace", timeout=300)
        if proc.returncode != 0:
            pytest.skip(f"no offline build (setuptools/wheel missing) and pip could not fetch: {proc.stderr[-2000:]}")
    (wheel,) = wheels.glob("monai_rigidreg-*.whl")
    return wheel


def test_wheel_installs_into_a_fresh_venv_and_registers(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    wheel = _build_wheel(_source_copy(src), tmp_path / "wheels", tmp_path)
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
    assert "monai_rigidreg/_bundles/cbct_ct_rigid/models/model.pt" in names
    # docs/ are pages of the repository, not package data
    assert not [n for n in names if n.startswith("docs/") or n.endswith(("conventions.md", "architecture.md"))]

    venv = (tmp_path / "venv").resolve()
    _run([sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", venv], tmp_path)
    py = venv / "bin" / "python"
    if sys.prefix != sys.base_prefix:
        # this interpreter is itself a venv (e.g. the CI's): --system-site-packages reaches only the base
        # interpreter's packages, so point the new venv at this one's as well (torch, MONAI, SimpleITK, pip)
        purelib = _run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path).stdout
        Path(purelib.strip(), "_outer_site_packages.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    # the machine's pip (seen through --system-site-packages) installs into the venv it runs in; --ignore-installed
    # leaves the machine's editable install alone instead of trying to uninstall it
    _run([py, "-m", "pip", "install", "--no-deps", "--ignore-installed", wheel], tmp_path)

    work = tmp_path / "elsewhere"
    work.mkdir()
    probe = ("import json, sys, monai_rigidreg; from monai_rigidreg.bundle import default_bundle_path; "
             "print(json.dumps({'prefix': sys.prefix, 'file': monai_rigidreg.__file__, "
             "'bundle': str(default_bundle_path())}))")
    info = json.loads(_run([py, "-c", probe], work).stdout.strip().splitlines()[-1])
    assert Path(info["prefix"]).resolve() == venv
    for key in ("file", "bundle"):
        path = Path(info[key]).resolve()
        assert path.is_relative_to(venv), f"{key} {path} is not inside the venv {venv}"
        assert not path.is_relative_to(ROOT), f"{key} {path} comes from the checkout"
    assert (Path(info["bundle"]) / "models" / "model.pt").is_file()

    # a tiny real registration through the installed console script: the moving image is the fixed one with its
    # content moved by +4 mm along x, so the transform (fixed points -> moving points, docs/conventions.md) has
    # tx = +4 mm and every other parameter 0
    fixed = blob_ct()
    moving = sitk.Resample(fixed, fixed, sitk.TranslationTransform(3, (-SHIFT_X_MM, 0.0, 0.0)), sitk.sitkLinear,
                           -1000.0)
    sitk.WriteImage(fixed, str(work / "A.nii.gz"))
    sitk.WriteImage(moving, str(work / "B.nii.gz"))
    out = work / "OUT"
    _run([venv / "bin" / "monai-rigidreg", "register", "--fixed", "A.nii.gz", "--moving", "B.nii.gz",
          "--output-dir", out, "--device", "cpu"], work)
    result = json.loads((out / "result.json").read_text())
    params = result["params"]
    assert abs(params["tx"] - SHIFT_X_MM) < 1.0, params
    assert abs(params["ty"]) < 1.0 and abs(params["tz"]) < 1.0, params
    for name in ("transform.tfm", "registered.nii.gz", "qc.png"):
        assert (out / name).is_file(), name
