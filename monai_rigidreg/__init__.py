"""monai-rigidreg: rigid 6-DoF CBCT-to-CT registration for adaptive radiotherapy, as a MONAI plugin.

``monai_rigidreg.register(fixed, moving, ...)`` is the registration function
(:func:`monai_rigidreg.registration.register`); build the network once with
``monai_rigidreg.RigidRegistrar.from_bundle()`` and pass it as ``model=``. Every public name is imported on first
use (PEP 562): the geometry conventions (:mod:`monai_rigidreg.geometry`, ``docs/conventions.md``) import torch
(about 0.9 s) and the registration API MONAI's pieces and the networks, and ``import monai_rigidreg`` itself imports
neither, so the command line's ``--help`` and ``--version`` answer at once and ``register`` can start reading its
inputs while torch is imported (:mod:`monai_rigidreg.prefetch`).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from typing import Any

__version__ = "0.4.9"

# Thread policy (before anything imports torch): PyTorch's OpenMP worker threads spin while they wait for work
# (libgomp's default), so beside another CPU-bound process on a 2-core machine each spinning thread steals the
# core the other process needs: measured by ``benchmarks/bench_speed.py`` (a registration beside one
# single-threaded busy loop took 1.95x its quiet time with the default policy, 1.18x with ``PASSIVE``; beside a
# second registration 3.17x and 1.36x; no measurable cost on a quiet machine). libgomp reads the variable when
# torch loads it, so this applies only where the caller has not imported torch yet and has not chosen a policy
# itself (``THREAD_POLICY_APPLIED`` says whether it did).
THREAD_POLICY_APPLIED = "torch" not in sys.modules and "OMP_WAIT_POLICY" not in os.environ
if THREAD_POLICY_APPLIED:
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

_LAZY = {
    **{name: "monai_rigidreg.geometry" for name in ("PARAM_NAMES", "Grid", "matrix_to_params", "params_to_matrix",
                                                  "params_to_sitk", "sitk_to_params", "target_registration_error")},
    "register": "monai_rigidreg.registration",
    "RigidRegistrar": "monai_rigidreg.registration",
    "RegistrationResult": "monai_rigidreg.registration",
    "register_files": "monai_rigidreg.outputs",
    "write_outputs": "monai_rigidreg.outputs",
    "NetworkGridSpec": "monai_rigidreg.network_grid",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value  # later look-ups skip this hook
        return value
    # a submodule named as an attribute (``monai_rigidreg.geometry`` after a plain ``import monai_rigidreg``, as in a
    # MONAI config's "$monai_rigidreg.geometry..." expression) is imported then, as the eager import used to provide
    if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module 'monai_rigidreg' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
