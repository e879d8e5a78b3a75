"""The README's Python snippets run as written (on a simulated pair instead of the placeholder file names)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from conftest import KNOWN_MOTION

README = Path(__file__).resolve().parents[1] / "README.md"


def _snippet(after: str) -> str:
    text = README.read_text(encoding="utf-8")
    start = text.index(after)
    return re.search(r"```python\n(.*?)```", text[start:], re.S).group(1)


def test_register_snippet_runs_and_recovers_the_motion(fast_pair):
    code = _snippet("From Python:").replace('"ct.nii.gz"', "CT").replace('"cbct.nii.gz"', "CBCT")
    scope = {"CT": str(fast_pair["fixed"]), "CBCT": str(fast_pair["moving"]),
             "pairs": [(str(fast_pair["fixed"]), str(fast_pair["moving"]))]}
    exec(compile(code, "README.md", "exec"), scope)  # noqa: S102 - the documented snippet itself
    result = scope["result"]
    assert isinstance(result.transform, sitk.Euler3DTransform)
    assert isinstance(result.registered, sitk.Image)
    np.testing.assert_allclose(result.params, KNOWN_MOTION, atol=1.0)  # within 1 mm / 1 degree per axis
