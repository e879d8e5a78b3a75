"""The ``>>>`` examples of the docstrings run as written: ``register``, ``RigidRegistrar``, the geometry conversions
and the smaller helpers that carry one (the same check as ``python -m pytest --doctest-modules`` on these modules)."""

from __future__ import annotations

import doctest
import importlib

import pytest

MODULES = [
    "monai_rigidreg.core.command_text",
    "monai_rigidreg.core.geometry",
    "monai_rigidreg.core.lazy_exports",
    "monai_rigidreg.registration.inputs",
    "monai_rigidreg.registration.api",
    "monai_rigidreg.registration.registrar",
    "monai_rigidreg.export.transform_files",
    "monai_rigidreg.simulation.toy",
    "monai_rigidreg.networks.blocks",
    "monai_rigidreg.networks.context_net",
    "monai_rigidreg.losses.match_loss",
    "monai_rigidreg.engine.sampler",
    "monai_rigidreg.engine.sources",
    "benchmarks.accuracy.bench_generalisation_gap",
]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.attempted > 0, f"{name} has no example"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples of {name} failed (details above)"
