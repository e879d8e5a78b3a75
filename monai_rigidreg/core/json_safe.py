"""Values made ready for strict JSON (``result.json``, an evaluation's ``summary.json``).

Strict JSON has no NaN or Infinity (Python's ``json`` writes them as bare ``NaN`` / ``Infinity`` unless told not to,
and many readers refuse the file). Here a non-finite float, a value that was not measured, becomes ``None``
(``null``); numpy scalars and arrays become Python numbers and lists; tuples become lists.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["json_safe"]


def json_safe(x: Any) -> Any:
    """``x`` (nested dicts, lists, tuples, numpy arrays and scalars, plain values) with numpy values as Python ones,
    non-finite floats as ``None`` and dict keys as strings."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
