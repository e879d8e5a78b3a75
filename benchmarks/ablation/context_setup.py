"""What the context network's ablation scripts share: the train config with ``--set`` overrides of the network, and
the training sampler's sources (the training data and CTs of ``scripts/train_context_model.sh``)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from monai_rigidreg.io.shared_data import training_ct_paths

CONFIGS = ["bundles/cbct_ct_rigid/configs/train.json", "bundles/cbct_ct_rigid/configs/train_context.json"]


def train_config(overrides: Sequence[str] = ()) -> Any:
    """The bundle's train config (``train.json`` + ``train_context.json``) with ``KEY=VALUE`` overrides of the
    regression network's arguments (the value as JSON where it parses, else a string)."""
    from monai.bundle import ConfigParser

    parser = ConfigParser()
    parser.read_config(CONFIGS)
    for item in overrides:
        key, _, value = item.partition("=")
        try:
            parsed = json.loads(value)
        except json.JSONDecodeError:
            parsed = value
        parser[f"network_def#regression#{key}"] = parsed
    return parser


def sampler_sources(parser: Any, data: Path, shared: Path, lists: Sequence[str] = ("train.json",)
                    ) -> tuple[list[Any], tuple[int, ...], tuple[float, ...], int]:
    """``(sources, network size, network spacing, context factor)`` for a
    :class:`~monai_rigidreg.engine.RigidPairSampler` over the datalists ``lists`` in ``data`` (those that exist) and
    the training CTs in ``shared``."""
    from monai_rigidreg.engine import load_sources

    size = tuple(int(s) for s in parser["network_size"])
    spacing = tuple(float(s) for s in parser["network_spacing"])
    factor = int(parser["context_factor"])
    cts = [str(p) for p in training_ct_paths(shared)]
    datalists = [str(data / name) for name in lists if (data / name).is_file()]
    sources = load_sources(datalists=datalists, cts=cts, network_spacing=spacing[0],
                           context_spacing=spacing[0] * factor, isocenter_max=float(parser["isocenter_max"]))
    return sources, size, spacing, factor
