"""Names a package exports from its modules, imported on first use (PEP 562).

A package whose modules import torch or SimpleITK can still be imported at the cost of its ``__init__``: the
``register`` command imports :mod:`monai_rigidreg.io.prefetch` and starts reading its inputs before torch is loaded,
and ``monai-rigidreg --help`` builds every sub-command's parser without the stacks behind them.

>>> getattr_, dir_ = lazy_exports("pkg", {"sqrt": "math"})
>>> getattr_("sqrt")(4.0)
2.0
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(package: str, table: Mapping[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for ``package``: ``table`` maps each exported name to the module that defines it.

    The first look-up of a name imports its module and stores the value in the package, so later look-ups are
    plain attribute reads. A submodule's name imports the submodule (``monai_rigidreg.core.geometry`` after a plain
    ``import monai_rigidreg``, as a MONAI config's ``"$monai_rigidreg.core.geometry.PARAM_NAMES"`` reads it); any
    other name raises ``AttributeError``.
    """

    def __getattr__(name: str) -> Any:
        if name not in table:
            if not name.startswith("_") and importlib.util.find_spec(f"{package}.{name}") is not None:
                return importlib.import_module(f"{package}.{name}")
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(table[name]), name)
        module = sys.modules.get(package)
        if module is not None:
            setattr(module, name, value)
        return value

    def __dir__() -> list[str]:
        module = sys.modules.get(package)
        return sorted(set(vars(module)) | set(table)) if module is not None else sorted(table)

    return __getattr__, __dir__
