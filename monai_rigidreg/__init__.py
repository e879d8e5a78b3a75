"""monai-rigidreg: rigid 6-DoF CBCT-to-CT registration for adaptive radiotherapy, as a MONAI plugin.

``monai_rigidreg.register(fixed, moving, ...)`` is the registration function
(:func:`monai_rigidreg.registration.register`); build the network once with
``monai_rigidreg.RigidRegistrar.from_bundle()`` and pass it as ``model=``. Every public name is imported on first
use (PEP 562): the geometry conventions (:mod:`monai_rigidreg.core.geometry`, ``docs/conventions.md``) import torch
and the registration API the networks, and ``import monai_rigidreg`` itself imports neither, so the command line's
``--help`` and ``--version`` answer at once and ``register`` can start reading its inputs while torch is imported
(:mod:`monai_rigidreg.io.prefetch`). The subpackages are mapped in ``monai_rigidreg/README.md``.

Modules that moved in 0.5 (``monai_rigidreg.geometry`` is now :mod:`monai_rigidreg.core.geometry`, ...) are still
importable under their old names until 0.6, with a ``DeprecationWarning``: :data:`MOVED_MODULES` lists them, and an
import finder serves each old name with the new module itself (the same objects: bundle configs, user code and
pickles that name the old path keep working).
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import os
import sys
import types
import warnings
from typing import Any

__version__ = "0.6.2"

# Thread policy (before anything imports torch): PyTorch's OpenMP worker threads spin while they wait for work
# (libgomp's default), so beside another CPU-bound process each spinning thread steals the core the other process
# needs (docs/results.md, "Threads"). libgomp reads the variable when torch loads it, so this applies only where the
# caller has not imported torch yet and has not chosen a policy itself (``THREAD_POLICY_APPLIED`` says whether it
# did).
THREAD_POLICY_APPLIED = "torch" not in sys.modules and "OMP_WAIT_POLICY" not in os.environ
if THREAD_POLICY_APPLIED:
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

_LAZY = {
    **{name: "monai_rigidreg.core.geometry" for name in ("PARAM_NAMES", "Grid", "matrix_to_params",
                                                       "params_to_matrix", "params_to_sitk", "sitk_to_params",
                                                       "target_registration_error")},
    "register": "monai_rigidreg.registration",
    "RigidRegistrar": "monai_rigidreg.registration",
    "RegistrationResult": "monai_rigidreg.registration",
    "register_files": "monai_rigidreg.registration.files",
    "write_outputs": "monai_rigidreg.export.outputs",
    "NetworkGridSpec": "monai_rigidreg.core.network_grid",
}

__all__ = ["__version__", *_LAZY]

MOVED_MODULES: dict[str, str | tuple[str, ...]] = {
    "monai_rigidreg.batch": ("monai_rigidreg.registration.pairs", "monai_rigidreg.bundle.entry_points"),
    "monai_rigidreg.body": "monai_rigidreg.registration.body",
    "monai_rigidreg.bundle_config": "monai_rigidreg.bundle.config",
    "monai_rigidreg.classical": "monai_rigidreg.registration.classical",
    "monai_rigidreg.confidence": "monai_rigidreg.registration.confidence",
    "monai_rigidreg.couch": "monai_rigidreg.export.couch_shifts",
    "monai_rigidreg.data": "monai_rigidreg.io.shared_data",
    "monai_rigidreg.device": "monai_rigidreg.core.device",
    "monai_rigidreg.dicom_reg": "monai_rigidreg.export.dicom_reg",
    "monai_rigidreg.dicom_series": "monai_rigidreg.io.dicom_series",
    "monai_rigidreg.elastix_params": "monai_rigidreg.export.elastix_params",
    "monai_rigidreg.errors": "monai_rigidreg.core.errors",
    "monai_rigidreg.geometry": "monai_rigidreg.core.geometry",
    "monai_rigidreg.global_init": "monai_rigidreg.registration.search",
    "monai_rigidreg.grid_sampling": "monai_rigidreg.core.grid_sampling",
    "monai_rigidreg.image_ops": "monai_rigidreg.core.image_ops",
    "monai_rigidreg.json_safe": "monai_rigidreg.core.json_safe",
    "monai_rigidreg.match_region": "monai_rigidreg.registration.match_region",
    "monai_rigidreg.network_grid": "monai_rigidreg.core.network_grid",
    "monai_rigidreg.outputs": ("monai_rigidreg.export.outputs", "monai_rigidreg.registration.files",
                               "monai_rigidreg.registration.inputs", "monai_rigidreg.bundle.entry_points",
                               "monai_rigidreg.io.staging"),
    "monai_rigidreg.precision": "monai_rigidreg.registration.last_level",
    "monai_rigidreg.prefetch": "monai_rigidreg.io.prefetch",
    "monai_rigidreg.provenance": "monai_rigidreg.export.provenance",
    "monai_rigidreg.qc": "monai_rigidreg.export.qc_figure",
    "monai_rigidreg.region_check": "monai_rigidreg.registration.region_check",
    "monai_rigidreg.register_cli": "monai_rigidreg.registration.register_command",
    "monai_rigidreg.staging": "monai_rigidreg.io.staging",
    "monai_rigidreg.warp": "monai_rigidreg.core.warp",
    "monai_rigidreg.engine.cli": "monai_rigidreg.engine.train_command",
    "monai_rigidreg.evaluation.cli": "monai_rigidreg.evaluation.evaluate_command",
    "monai_rigidreg.simulation.cli": "monai_rigidreg.simulation.simulate_command",
}
"""Old module path -> its new module (the same module object under the old name), or the new modules its names
were split between (the old name is then a module that looks each name up in them, in this order)."""
REMOVED_IN = "0.6"


class _MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Serves each old module path of :data:`MOVED_MODULES`, with a ``DeprecationWarning`` at the import."""

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        if fullname not in MOVED_MODULES:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        new = MOVED_MODULES[spec.name]
        names = new if isinstance(new, str) else " and ".join(new)
        # stacklevel 2: the code doing the import (warnings skips the import machinery's frames when it counts)
        warnings.warn(f"{spec.name} is now {names}; the old path works until monai-rigidreg {REMOVED_IN}",
                      DeprecationWarning, stacklevel=2)
        if isinstance(new, str):
            module = importlib.import_module(new)
            # the import system sets __spec__ on the module it is given: exec_module puts the module's own back
            module.__dict__.setdefault("_monai_rigidreg_own_spec", module.__spec__)
            return module
        return _split_module(spec.name, new)

    def exec_module(self, module: types.ModuleType) -> None:
        own = module.__dict__.pop("_monai_rigidreg_own_spec", None)
        if own is not None:
            module.__spec__ = own


def _split_module(name: str, homes: tuple[str, ...]) -> types.ModuleType:
    """A module ``name`` whose attributes are looked up in ``homes`` (imported on first use), in order."""
    module = types.ModuleType(name, f"Moved: the names of {name} are now in {', '.join(homes)}.")

    def __getattr__(attr: str) -> Any:
        if attr.startswith("__"):
            raise AttributeError(attr)
        for home in homes:
            found = importlib.import_module(home)
            if attr in getattr(found, "__all__", ()) or (not attr.startswith("_") and hasattr(found, attr)):
                return getattr(found, attr)
        raise AttributeError(f"module {name!r} has no attribute {attr!r}")

    module.__getattr__ = __getattr__  # type: ignore[method-assign]
    module.__all__ = _SPLIT_ALL.get(name, [])  # type: ignore[attr-defined]
    return module


_SPLIT_ALL = {
    "monai_rigidreg.batch": ["registration_pairs", "RegistrationEvaluator", "BatchFailures", "bundle_run"],
    "monai_rigidreg.outputs": ["OUTPUT_FILES", "DEFAULT_OUTPUT_FILES", "TRANSFORM_FORMATS", "REG_MODES",
                               "write_outputs", "staged_output_dir", "register_files", "dicom_references",
                               "check_bundle_options", "bundle_evaluate", "check_register_inputs",
                               "bundle_check_inputs", "bundle_errors", "bundle_register_files"],
}
"""The ``__all__`` the split modules had (``from monai_rigidreg.outputs import *`` gives the same names)."""


if not any(isinstance(f, _MovedModuleFinder) for f in sys.meta_path):
    sys.meta_path.insert(0, _MovedModuleFinder())


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value  # later look-ups skip this hook
        return value
    # a submodule named as an attribute (``monai_rigidreg.core`` after a plain ``import monai_rigidreg``, as in a
    # MONAI config's "$monai_rigidreg.core.geometry..." expression) is imported then, as an eager import would; a
    # moved module's old name too (with its warning)
    if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module 'monai_rigidreg' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
