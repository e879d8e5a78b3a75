"""Read the plain part of a MONAI bundle config without importing MONAI; anything else goes to MONAI's parser.

``monai-rigidreg register`` needs two things from ``configs/inference.json``: the network (``network_def``, nested
``_target_`` dicts whose arguments are literals or ``@id`` references) and a few settings (literals). Parsing them
with :class:`monai.bundle.ConfigParser` means importing MONAI, about 6 s on 2 cores (see
:mod:`monai_rigidreg.networks.blocks`) for what is a JSON lookup. :class:`PlainConfig` resolves that subset itself:

* literals (numbers, strings, booleans, null, lists and dicts of them);
* ``"@id"`` / ``"@id#key#0"``: the parsed content of another entry (MONAI's reference syntax, ``#`` separating nested
  keys and list indices);
* ``{"_target_": "package.module.Class", **kwargs}``: ``Class(**parsed kwargs)``.

Everything else MONAI's parser understands (``$`` expressions, ``%`` macros, ``_disabled_``, ``_requires_``,
``_mode_``, ``_args_``, YAML files, ...) raises :class:`NotPlain`, and :func:`open_config` then falls back to
``monai.bundle.ConfigParser`` so that a user's bundle still loads as MONAI would load it. ``tests/test_bundle.py``
checks that the shipped bundle gives the same network, weights and settings through both readers.
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path
from typing import Any

__all__ = ["NotPlain", "PlainConfig", "open_config"]

_SEP = "#"


class NotPlain(ValueError):
    """The requested entry uses MONAI config syntax beyond the plain subset (the caller falls back to MONAI)."""


def _locate(path: str) -> Any:
    """The object at a dotted path (``package.module.Name``, or a nested attribute after the module)."""
    parts = path.split(".")
    for cut in range(len(parts) - 1, 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for name in parts[cut:]:
            obj = getattr(obj, name)
        return obj
    raise NotPlain(f"cannot locate {path!r}")


class PlainConfig:
    """A JSON bundle config whose requested entries use only literals, ``@`` references and ``_target_``.

    Mirrors the two methods of :class:`monai.bundle.ConfigParser` that the package uses:
    ``key in config`` and :meth:`get_parsed_content`; ``config[key] = value`` sets an entry (as
    ``parser["bundle_root"] = ...``).

    Args:
        path: the ``.json`` config file.

    Raises:
        NotPlain: for a file that is not JSON (MONAI also reads YAML).
    """

    def __init__(self, path: str | Path) -> None:
        path = Path(path)
        if path.suffix.lower() != ".json":
            raise NotPlain(f"{path.name}: only JSON configs are read without MONAI")
        with open(path, encoding="utf-8") as f:
            self.config: dict[str, Any] = json.load(f)

    def __contains__(self, key: str) -> bool:
        try:
            self._raw(key)
        except KeyError:
            return False
        return True

    def __setitem__(self, key: str, value: Any) -> None:
        self.config[key] = value

    def _raw(self, key: str) -> Any:
        node: Any = self.config
        for part in key.split(_SEP):
            if isinstance(node, list):
                if not part.lstrip("-").isdigit() or not -len(node) <= int(part) < len(node):
                    raise KeyError(key)
                node = node[int(part)]
            elif isinstance(node, dict) and part in node:
                node = node[part]
            else:
                raise KeyError(key)
        return node

    def get_parsed_content(self, key: str) -> Any:
        """The entry ``key`` (``#``-separated path) with references resolved and ``_target_`` dicts instantiated.

        Raises:
            KeyError: no such entry.
            NotPlain: the entry (or one it refers to) uses syntax outside the plain subset.
        """
        return self._parse(self._raw(key), (key,))

    def check(self, key: str) -> None:
        """Raise :class:`NotPlain` (or ``KeyError``) where :meth:`get_parsed_content` would, building nothing:
        the syntax is walked and every ``_target_`` located, none instantiated."""
        self._parse(self._raw(key), (key,), build=False)

    def _parse(self, node: Any, stack: tuple[str, ...], build: bool = True) -> Any:
        if isinstance(node, str):
            if node.startswith("@"):
                ref = node[1:]
                if ref in stack:
                    raise NotPlain(f"circular reference {' -> '.join((*stack, ref))}")
                try:
                    target = self._raw(ref)
                except KeyError as exc:
                    raise NotPlain(f"unresolved reference {node!r}") from exc
                return self._parse(target, (*stack, ref), build)
            if node.startswith(("$", "%")):
                raise NotPlain(f"expression or macro {node[:40]!r}")
            return node
        if isinstance(node, list):
            return [self._parse(v, stack, build) for v in node]
        if isinstance(node, dict):
            special = [k for k in node if isinstance(k, str) and k.startswith("_") and k != "_target_"]
            if special:
                raise NotPlain(f"component keys {special}")
            kwargs = {k: self._parse(v, stack, build) for k, v in node.items() if k != "_target_"}
            if "_target_" not in node:
                return kwargs
            target = node["_target_"]
            if not isinstance(target, str) or target.startswith(("$", "@", "%")):
                raise NotPlain(f"_target_ {target!r}")
            component = _locate(target)
            return component(**kwargs) if build else None
        return node


def open_config(path: str | Path, keys: tuple[str, ...] = ()) -> Any:
    """A reader for ``path``: :class:`PlainConfig` when every entry in ``keys`` that the file has parses as plain
    (:meth:`PlainConfig.check`), else MONAI's :class:`monai.bundle.ConfigParser` (imported only then)."""
    try:
        plain = PlainConfig(path)
        for key in keys:
            if key in plain:
                plain.check(key)
        return plain
    except NotPlain:
        from monai.bundle import ConfigParser

        parser = ConfigParser()
        parser.read_config(str(path))
        return parser
