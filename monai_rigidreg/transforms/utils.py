"""Small helpers shared by the transforms of :mod:`monai_rigidreg.transforms` (not public API).

Geometry always goes through :mod:`monai_rigidreg.core.geometry` and :mod:`monai_rigidreg.core.warp`; these helpers only
adapt MONAI data (``MetaTensor`` / tensors / arrays, channel first ``[C, x, y, z]``) to them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.core.grid_sampling import PaddingValue, resample_physical  # re-exported: they live there

__all__ = [
    "PaddingValue",
    "grid_of",
    "resample_physical",
    "as_matrix",
    "as_vector",
    "like",
    "ensure_range_pairs",
    "ensure_interval",
]

_IDENTITY_RAS = np.eye(4)


def grid_of(img: Any) -> Grid:
    """Grid (LPS, mm) of a channel-first image ``[C, x, y, z]``.

    A ``MetaTensor`` gives its affine (RAS unless ``meta["space"]`` says LPS); a plain tensor/array is taken to
    have an identity RAS affine (1 mm voxels at the origin).
    """
    if hasattr(img, "affine") and getattr(img, "meta", None) is not None:
        return Grid.from_metatensor(img)
    return Grid.from_affine(_IDENTITY_RAS, tuple(img.shape[-3:]), space="RAS")


def as_matrix(value: Any) -> np.ndarray:
    """A 4x4 float64 matrix from a tensor/array/nested list (a leading batch axis of 1 is dropped)."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    m = np.asarray(value, dtype=np.float64)
    if m.shape == (1, 4, 4):
        m = m[0]
    if m.shape != (4, 4):
        raise ValueError(f"expected a 4x4 matrix, got shape {m.shape}")
    return m


def as_vector(value: Any, n: int) -> np.ndarray:
    """An ``n``-vector (float64) from a tensor/array/list (a leading batch axis of 1 is dropped)."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    v = np.asarray(value, dtype=np.float64).reshape(-1)
    if v.shape != (n,):
        raise ValueError(f"expected {n} values, got shape {np.shape(value)}")
    return v


def like(value: np.ndarray, template: Any) -> Any:
    """``value`` converted to the container type of ``template`` (tensor, ndarray, list or tuple)."""
    if isinstance(template, torch.Tensor):
        return torch.as_tensor(value, dtype=template.dtype if template.is_floating_point() else torch.float64)
    if isinstance(template, np.ndarray):
        return np.asarray(value, dtype=template.dtype if template.dtype.kind == "f" else np.float64)
    out = np.asarray(value).tolist()
    return tuple(out) if isinstance(template, tuple) else out


def ensure_range_pairs(value: Any, n: int, name: str) -> np.ndarray:
    """``[n, 2]`` (low, high) ranges from a scalar ``a`` (``(-a, a)`` for all), ``n`` scalars or ``n`` pairs."""
    if isinstance(value, (int, float)):
        a = abs(float(value))
        return np.tile([-a, a], (n, 1))
    seq = list(value)
    if len(seq) != n:
        raise ValueError(f"{name} needs a number, {n} numbers or {n} (low, high) pairs, got {value!r}")
    out = np.zeros((n, 2))
    for i, v in enumerate(seq):
        if isinstance(v, Sequence) or (isinstance(v, np.ndarray) and v.size == 2):
            lo, hi = (float(x) for x in v)
        else:
            lo, hi = -abs(float(v)), abs(float(v))
        if lo > hi:
            raise ValueError(f"{name}[{i}] has low > high: {v!r}")
        out[i] = (lo, hi)
    return out


def ensure_interval(value: Any, name: str) -> tuple[float, float]:
    """``(low, high)`` from a number (degenerate interval) or a pair."""
    if isinstance(value, (int, float)):
        return float(value), float(value)
    lo, hi = (float(v) for v in value)
    if lo > hi:
        raise ValueError(f"{name} has low > high: {value!r}")
    return lo, hi
