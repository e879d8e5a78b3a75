"""Motion protocols: which rigid motions ``M`` the simulated CBCTs get.

Each :class:`MotionCase` holds user parameters ``(tx, ty, tz, rx, ry, rz)`` (mm, degrees, about the isocentre)
and a ``group`` label the evaluation report groups by:

* ``"translation"``: one axis, +-5, +-10, +-15 mm;
* ``"translation_multi"``: two or three axes at once;
* ``"rotation_x"``, ``"rotation_y"``, ``"rotation_z"``: one axis, +-10, +-20, +-30 degrees;
* ``"rotation"``: several rotation axes at once (up to 30 degrees);
* ``"multi"``: translations and rotations together (6 DoF);
* ``"random"``: the ``random`` protocol (continuous uniform ranges);
* ``"multi30"``: the ``multi30`` protocol, 6-DoF motions with ``|rx| = |ry| = |rz| = 30`` degrees (every sign
  pattern) and translations of 5-15 mm on all three axes;
* ``"given"``: a motion given by the caller (``simulate --motion``).

``condition`` names the reference study's table rows: ``"Translation (1.5 cm)"`` (15 mm translations, no
rotation) and ``"Rotation (theta_x = 30 deg)"`` (``rx = +-30``, nothing else).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

__all__ = ["MotionCase", "PROTOCOLS", "paper_cases", "multi30_cases", "random_cases", "protocol_cases"]

PROTOCOLS: tuple[str, ...] = ("paper", "random", "multi30")
TRANSLATION_15MM = "Translation (1.5 cm)"
ROTATION_X_30 = "Rotation (theta_x = 30 deg)"


@dataclass(frozen=True)
class MotionCase:
    """One motion: ``params`` ``(tx, ty, tz, rx, ry, rz)`` in mm / degrees, its ``group``, a readable ``label``
    and the reference-study ``condition`` it belongs to (or ``None``)."""

    params: tuple[float, float, float, float, float, float]
    group: str
    label: str
    condition: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (for JSON)."""
        return asdict(self)


def _label(p: np.ndarray) -> str:
    names = ("tx", "ty", "tz", "rx", "ry", "rz")
    parts = [f"{n}={v:+g}{'mm' if i < 3 else 'deg'}" for i, (n, v) in enumerate(zip(names, p)) if v != 0]
    return " ".join(parts) or "identity"


def _case(p: list[float] | tuple[float, ...], group: str) -> MotionCase:
    arr = np.asarray(p, dtype=np.float64)
    cond = None
    if not arr[3:].any() and arr[:3].any() and set(np.abs(arr[:3][arr[:3] != 0]).tolist()) == {15.0}:
        cond = TRANSLATION_15MM
    if not arr[:3].any() and abs(arr[3]) == 30.0 and not arr[4:].any():
        cond = ROTATION_X_30
    return MotionCase(tuple(float(v) for v in arr), group, _label(arr), cond)  # type: ignore[arg-type]


def paper_cases() -> list[MotionCase]:
    """The reference study's protocol: +-5/10/15 mm translations and rotations up to 30 degrees, single- and
    multi-axis, plus combined 6-DoF cases (63 cases). The first two are the study's showcase cases
    (``tx = +15 mm`` and ``rx = +30 deg``), so a short dataset still holds them."""
    cases = [_case([15, 0, 0, 0, 0, 0], "translation"), _case([0, 0, 0, 30, 0, 0], "rotation_x")]
    for axis in range(3):
        for mag in (5.0, 10.0, 15.0):
            for sign in (1.0, -1.0):
                p = [0.0] * 6
                p[axis] = sign * mag
                cases.append(_case(p, "translation"))
    for m in (5.0, 10.0, 15.0):
        for pattern in ((1, 1, 0), (1, 0, -1), (0, -1, 1), (1, 1, 1), (-1, 1, -1)):
            cases.append(_case([m * s for s in pattern] + [0.0, 0.0, 0.0], "translation_multi"))
    for axis, name in ((3, "rotation_x"), (4, "rotation_y"), (5, "rotation_z")):
        for mag in (10.0, 20.0, 30.0):
            for sign in (1.0, -1.0):
                p = [0.0] * 6
                p[axis] = sign * mag
                cases.append(_case(p, name))
    for r in ((10, 10, 0), (0, -15, 15), (20, 0, -10), (10, 10, 10), (-30, 15, 5), (15, -20, 30)):
        cases.append(_case([0.0, 0.0, 0.0, *r], "rotation"))
    for p in (
        (5, -5, 10, 5, 0, -5),
        (-10, 5, 0, 0, 10, 10),
        (15, 10, -5, -10, 5, 20),
        (0, -15, 15, 30, -10, 0),
        (-5, 0, -10, -20, 20, -15),
        (10, -10, 5, 15, -30, 10),
    ):
        cases.append(_case(list(p), "multi"))
    unique: dict[tuple[float, ...], MotionCase] = {}
    for c in cases:
        unique.setdefault(c.params, c)
    return list(unique.values())


def multi30_cases() -> list[MotionCase]:
    """Large multi-axis motions beyond the paper protocol's: every sign pattern of ``|rx| = |ry| = |rz| = 30``
    degrees, each with another permutation of the translations 5 / 15 / -10 mm (8 cases; the first is
    ``(5, 15, -10, 30, 30, -30)``)."""
    translations = ((5, 15, -10), (-10, 5, 15), (15, -10, 5), (-5, -15, 10), (10, -5, -15), (-15, 10, -5),
                    (5, -10, 15), (-5, 15, -10))
    signs = ((1, 1, -1), (-1, 1, 1), (1, -1, 1), (-1, -1, -1), (1, 1, 1), (-1, -1, 1), (1, -1, -1), (-1, 1, -1))
    return [_case([*t, *(30.0 * s for s in r)], "multi30") for t, r in zip(translations, signs)]


def random_cases(
    num_cases: int, seed: int = 0, max_translation: float = 15.0, max_rotation: float = 30.0
) -> list[MotionCase]:
    """``num_cases`` motions with every parameter uniform in ``[-max, max]`` (mm / degrees), from ``seed``."""
    if num_cases < 1:
        raise ValueError(f"num_cases must be >= 1, got {num_cases}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7]))
    t = rng.uniform(-max_translation, max_translation, (num_cases, 3))
    r = rng.uniform(-max_rotation, max_rotation, (num_cases, 3))
    p = np.round(np.concatenate([t, r], 1), 3)
    return [MotionCase(tuple(float(v) for v in row), "random", _label(row)) for row in p]  # type: ignore[arg-type]


def protocol_cases(
    protocol: str,
    num_cases: int | None = None,
    seed: int = 0,
    max_translation: float = 15.0,
    max_rotation: float = 30.0,
    motion: Any = None,
) -> list[MotionCase]:
    """Cases of a protocol, or of one given motion.

    Args:
        protocol: ``"paper"`` or ``"random"``.
        num_cases: number of cases. ``paper``: ``None`` gives all of them; fewer keeps the two showcase
            cases and an evenly spread subset of the rest; more repeats the list (each repeat is a new CBCT
            realisation, of another object where there are several). ``random``: required (default 64).
        seed: seed of the ``random`` protocol.
        max_translation: ``random`` range, mm.
        max_rotation: ``random`` range, degrees.
        motion: ``(tx, ty, tz, rx, ry, rz)``: every case has this motion (group ``"given"``; ``num_cases``
            default 1, each case its own CBCT realisation) and the protocol is not used.
    """
    if motion is not None:
        if num_cases is not None and num_cases < 1:
            raise ValueError(f"num_cases must be >= 1, got {num_cases}")
        return [_case(list(motion), "given")] * (1 if num_cases is None else num_cases)
    if protocol == "random":
        return random_cases(64 if num_cases is None else num_cases, seed, max_translation, max_rotation)
    if protocol not in ("paper", "multi30"):
        raise ValueError(f"unknown protocol {protocol!r}; choose one of {PROTOCOLS}")
    if protocol == "multi30":
        cases = multi30_cases()
        if num_cases is None:
            return cases
        if num_cases < 1:
            raise ValueError(f"num_cases must be >= 1, got {num_cases}")
        return [cases[i % len(cases)] for i in range(num_cases)]
    cases = paper_cases()
    if num_cases is None:
        return cases
    if num_cases < 1:
        raise ValueError(f"num_cases must be >= 1, got {num_cases}")
    if num_cases <= len(cases):
        head, rest = cases[:2], cases[2:]
        k = num_cases - len(head[:num_cases])
        pick = np.linspace(0, len(rest) - 1, k).round().astype(int) if k > 0 else []
        return head[:num_cases] + [rest[i] for i in pick]
    return [cases[i % len(cases)] for i in range(num_cases)]
