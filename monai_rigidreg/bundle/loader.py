"""Locate the shipped MONAI bundle and load its network with the settings its ``inference.json`` declares.

The bundle is the single source of the model's configuration: the register API, the CLI and
``python -m monai.bundle run`` all read the same ``configs/inference.json`` and ``models/model.pt``.
"""

from __future__ import annotations

import importlib.resources
import logging
from pathlib import Path
from typing import Any

import torch
from torch import nn

from monai_rigidreg.bundle.config import open_config
from monai_rigidreg.core.errors import InputError

__all__ = ["DEFAULT_BUNDLE_NAME", "default_bundle_path", "load_bundle_network", "bundle_settings",
           "refuse_package_folders"]

logger = logging.getLogger(__name__)

DEFAULT_BUNDLE_NAME = "cbct_ct_rigid"
PACKAGE_DIR = Path(__file__).resolve().parents[1]
"""The installed ``monai_rigidreg`` package folder."""
SETTING_KEYS = ("network_size", "network_spacing", "cascade_steps", "global_init", "search_starts", "native_level",
                "native_bias_degree", "native_bias_degree_roi", "native_highpass_sigma_mm", "network_leads",
                "native_max_voxels", "native_final_norm_mm", "lead_passes", "fine_stage_choice_mm")


def default_bundle_path() -> Path:
    """Directory of the shipped ``cbct_ct_rigid`` bundle (installed package data, or the source checkout)."""
    try:
        root = importlib.resources.files("monai_rigidreg._bundles") / DEFAULT_BUNDLE_NAME
        candidate = Path(str(root))
        if (candidate / "configs" / "inference.json").is_file():
            return candidate
    except (ModuleNotFoundError, TypeError):
        pass
    candidate = PACKAGE_DIR.parent / "bundles" / DEFAULT_BUNDLE_NAME  # a source checkout
    if (candidate / "configs" / "inference.json").is_file():
        return candidate
    raise InputError(f"the shipped bundle {DEFAULT_BUNDLE_NAME!r} was not found; pass a bundle directory")


def _parser(bundle: Path, config: str = "inference.json", keys: tuple[str, ...] = SETTING_KEYS) -> Any:
    """The bundle's config reader: :class:`~monai_rigidreg.bundle.config.PlainConfig` when ``keys`` use only
    literals, ``@`` references and ``_target_`` (the shipped bundle: no MONAI import, which costs seconds), else
    MONAI's ``ConfigParser``; ``bundle_root`` set to the bundle directory either way."""
    cfg = bundle / "configs" / config
    if not cfg.is_file():
        raise InputError(f"not a MONAI bundle: {cfg} is missing", bundle)
    parser = open_config(cfg, keys)
    parser["bundle_root"] = str(bundle)
    return parser


def bundle_settings(bundle: str | Path | None = None) -> dict[str, Any]:
    """Network-grid size/spacing and cascade steps declared by the bundle's ``inference.json``."""
    b = default_bundle_path() if bundle is None else Path(bundle)
    return _settings(_parser(b))


def _settings(parser: Any) -> dict[str, Any]:
    return {k: parser.get_parsed_content(k) for k in SETTING_KEYS if k in parser}


def load_bundle_network(
    bundle: str | Path | None = None, device: torch.device | str = "cpu", weights: str | Path | None = None
) -> tuple[nn.Module, dict[str, Any]]:
    """Instantiate the bundle's ``network_def`` and load its weights.

    Args:
        bundle: bundle directory (default: the shipped one).
        device: where to put the network.
        weights: checkpoint path (default ``<bundle>/models/model.pt``); a plain ``state_dict`` or a MONAI
            checkpoint dict with a ``"network"`` / ``"model"`` entry.

    Returns:
        ``(network in eval mode, settings dict)``.
    """
    b = default_bundle_path() if bundle is None else Path(bundle)
    if not b.is_dir():
        raise InputError("bundle directory not found", b)
    parser = _parser(b, keys=(*SETTING_KEYS, "network_def"))
    net = parser.get_parsed_content("network_def")
    w = Path(weights) if weights is not None else b / "models" / "model.pt"
    if not w.is_file():
        raise InputError("model weights not found (train the bundle or pass weights=...)", w)
    try:
        state = torch.load(str(w), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many types for corrupt files
        raise InputError(f"could not load model weights ({exc})", w) from exc
    if isinstance(state, dict) and ("network" in state or "model" in state):
        state = state.get("network", state.get("model"))
    try:
        net.load_state_dict(state)
    except RuntimeError as exc:
        raise InputError(f"weights do not fit the bundle's network_def ({str(exc).splitlines()[0]})", w) from exc
    return net.to(device).eval(), _settings(parser)


def refuse_package_folders(*folders: str | Path) -> None:
    """Refuse output folders inside the installed package (its sources or the shipped bundle, which in an editable
    install is the checkout's ``bundles/``): training there would replace the shipped weights.

    Called by ``monai-rigidreg train`` and by the bundle's ``train.json`` (``initialize``) before anything is written.

    Raises:
        InputError: naming the first such folder.
    """
    roots = [PACKAGE_DIR, default_bundle_path().resolve()]
    for folder in folders:
        p = Path(folder).resolve()
        if any(p == r or r in p.parents for r in roots):
            raise InputError("this output folder is inside the installed monai-rigidreg package: training must not "
                             "replace the shipped bundle or its weights; choose a folder of your own", p)
