"""The public API surface: nothing the 0.4.9 layout offered is lost (its ``__all__`` names and the names its bundle
configs referenced, committed in ``tests/api_surface/``), today's surface is frozen in a committed list, the bundle
configs name only current paths, and the old module paths work (with a warning) as the same objects.

A change of the surface shows as a failure of :func:`test_the_surface_is_the_committed_list`: when it is meant,
regenerate the list with ``python tests/test_api_surface.py > tests/api_surface/current.txt`` and review the diff.
"""

from __future__ import annotations

import importlib
import json
import pickle
import pkgutil
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

import monai_rigidreg

ROOT = Path(__file__).resolve().parents[1]
SURFACE = ROOT / "tests" / "api_surface"
CONFIGS = ROOT / "bundles" / "cbct_ct_rigid" / "configs"


def _entries(path: Path) -> list[tuple[str, str]]:
    lines = path.read_text(encoding="utf-8").splitlines()
    return [tuple(line.split()) for line in lines if line.strip() and not line.startswith("#")]  # type: ignore[misc]


def current_surface() -> list[str]:
    """Every module's ``__all__`` in the package (each module imported), and the package's, as ``module name``."""
    out = {f"monai_rigidreg {name}" for name in monai_rigidreg.__all__}
    for info in pkgutil.walk_packages(monai_rigidreg.__path__, "monai_rigidreg."):
        if info.name.startswith("monai_rigidreg._bundles"):
            continue
        module = importlib.import_module(info.name)
        out |= {f"{info.name} {name}" for name in getattr(module, "__all__", ())}
    return sorted(out)


def _resolve(module: str, name: str) -> object:
    return getattr(importlib.import_module(module), name)


def test_every_name_of_the_0_4_9_surface_still_resolves_where_it_was():
    missing = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the old module paths warn: that is their purpose
        for module, name in _entries(SURFACE / "0.4.9.txt"):
            try:
                _resolve(module, name)
            except (ImportError, AttributeError) as exc:
                missing.append(f"{module}.{name}: {exc}")
    assert not missing, "\n".join(missing)


def test_the_surface_is_the_committed_list():
    committed = [f"{m} {n}" for m, n in _entries(SURFACE / "current.txt")]
    now = current_surface()
    added, dropped = sorted(set(now) - set(committed)), sorted(set(committed) - set(now))
    assert not added and not dropped, f"added: {added}\ndropped: {dropped}\n(regenerate: {__doc__.split('``')[1]})"


def _config_references() -> set[str]:
    refs: set[str] = set()
    for path in CONFIGS.glob("*.json"):
        text = json.dumps(json.loads(path.read_text(encoding="utf-8")))
        refs |= set(re.findall(r"monai_rigidreg(?:\.\w+)+", text))
    return refs


def _resolve_reference(ref: str) -> object:
    """A config's ``monai_rigidreg...`` reference: a module (``$import monai_rigidreg.x``) or a name in one."""
    try:
        return importlib.import_module(ref)
    except ModuleNotFoundError:
        module, name = ref.rsplit(".", 1)
        return _resolve(module, name)


def test_every_name_the_0_4_9_bundle_configs_referenced_still_resolves():
    refs = [line for line in (SURFACE / "bundle_configs_0.4.9.txt").read_text(encoding="utf-8").splitlines()
            if line.strip() and not line.startswith("#")]
    assert "monai_rigidreg.batch.RegistrationEvaluator" in refs
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        for ref in refs:
            _resolve_reference(ref)


def test_every_name_the_bundle_configs_reference_resolves_without_a_deprecation():
    refs = _config_references()
    assert "monai_rigidreg.registration.RigidRegistrar" in refs and "monai_rigidreg.networks.TwoStageRigidNet" in refs
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        for ref in sorted(refs):
            _resolve_reference(ref)


def test_an_old_module_path_is_the_new_module_with_a_deprecation_warning(monkeypatch):
    from monai_rigidreg import MOVED_MODULES
    from monai_rigidreg.core import geometry

    code = ("import warnings, sys; warnings.simplefilter('always')\n"
            "with warnings.catch_warnings(record=True) as caught:\n"
            "    import monai_rigidreg.geometry as old\n"
            "import monai_rigidreg.core.geometry as new\n"
            "print(old is new, old.__spec__.name, [str(w.message) for w in caught if w.category is DeprecationWarning],"
            " caught[0].filename == '<string>')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out.startswith("True monai_rigidreg.core.geometry ['monai_rigidreg.geometry is now "
                          "monai_rigidreg.core.geometry; the old path works until monai-rigidreg 0.6']"), out
    assert out.endswith("True")  # the warning points at the importing code, not at the import machinery
    monkeypatch.delitem(sys.modules, "monai_rigidreg.image_ops", raising=False)  # as on a first import
    with pytest.warns(DeprecationWarning, match="monai_rigidreg.image_ops is now monai_rigidreg.core.image_ops"):
        from monai_rigidreg.image_ops import gaussian_smooth
    assert gaussian_smooth is importlib.import_module("monai_rigidreg.core.image_ops").gaussian_smooth
    # every old path imports (a module whose names were split looks each one up where it went)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        for old in MOVED_MODULES:
            importlib.import_module(old)
        outputs = importlib.import_module("monai_rigidreg.outputs")
    assert outputs.write_outputs is importlib.import_module("monai_rigidreg.export.outputs").write_outputs
    entry_points = importlib.import_module("monai_rigidreg.bundle.entry_points")
    assert outputs.bundle_check_inputs is entry_points.bundle_check_inputs
    assert geometry.__spec__.name == "monai_rigidreg.core.geometry"


def test_a_pickle_that_names_an_old_module_path_loads():
    from monai_rigidreg.core.geometry import Grid

    grid = Grid((4, 5, 6), (1.0, 2.0, 3.0), (0.0, -1.0, 2.0))
    data = pickle.dumps(grid, protocol=0).replace(b"monai_rigidreg.core.geometry", b"monai_rigidreg.geometry")
    assert b"monai_rigidreg.geometry\n" in data
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # (warned at the first import of the old path)
        back = pickle.loads(data)
    assert isinstance(back, Grid) and back.size == grid.size and back.spacing == grid.spacing


def test_the_tree_keeps_its_shape():
    """The layout rules of the 0.5 restructuring: few loose modules at the top, no package file over 500 lines
    (``core/geometry.py``, the conventions' one owner, aside), and benchmarks that run as modules."""
    package = ROOT / "monai_rigidreg"
    assert len(list(package.glob("*.py"))) <= 8
    long = {str(p.relative_to(ROOT)): n for p in package.rglob("*.py")
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > 500 and p.name != "geometry.py"}
    assert not long, long
    edits = [str(p.relative_to(ROOT)) for p in (ROOT / "benchmarks").rglob("*.py")
             if "sys.path" in p.read_text(encoding="utf-8")]
    assert not edits, edits


if __name__ == "__main__":
    print("# The public surface of monai-rigidreg as it is: every module's __all__ (and the package's), one 'module "
          "name' a line.\n# Regenerate with: python tests/test_api_surface.py > tests/api_surface/current.txt")
    print("\n".join(current_surface()))
