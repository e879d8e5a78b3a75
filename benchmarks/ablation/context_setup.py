"""What the context network's ablation scripts share: the train config with ``--set`` overrides of the network, the
training sampler's sources (the training data and CTs of ``scripts/train_context_model.sh``) and their common
command-line options."""

from __future__ import annotations

import argparse
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


def add_common_options(ap: argparse.ArgumentParser, seed: int = 0, data_help: str | None = None) -> None:
    """``--data`` (the training data folder), ``--shared`` (the real CTs), ``--threads``, ``--seed`` (default
    ``seed``) and ``--results`` (a file for the printed report)."""
    ap.add_argument("--data", type=Path, default=Path("data"), help=data_help)
    ap.add_argument("--shared", type=Path, default=Path("../shared/data"))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=seed)
    ap.add_argument("--results", type=Path, default=None)
