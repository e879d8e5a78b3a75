"""Configuration of a simulated dataset: :class:`SimulationConfig`, the grid/view :data:`PRESETS` and
:func:`make_config` (a preset plus overrides, e.g. the ``--set KEY=VALUE`` options of ``monai-rigidreg simulate``).

Every value is checked when the configuration is made: a value of the wrong type (``--set cbct_views=many``) or out
of range is an :class:`~monai_rigidreg.core.errors.InputError` that names the option and the value.
"""

from __future__ import annotations

import functools
import json
import math
import numbers
import os
import typing
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch

from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.simulation.phantoms import PHANTOMS
from monai_rigidreg.simulation.physics import CBCTPhysics
from monai_rigidreg.simulation.protocols import PROTOCOLS
from monai_rigidreg.simulation.reconstruction import FILTERS

__all__ = ["PRESETS", "SimulationConfig", "make_config"]

_RUNTIME_KEYS = ("device", "workers", "volume_dtype")


@dataclass
class SimulationConfig:
    """Everything that determines a simulated dataset (units in the field names' docs).

    Args:
        phantom: ``"shepp-logan"``, ``"shepp-logan-asym"``, ``"random"``, ``"synth"`` or a path to a CT
            (NIfTI/DICOM).
        protocol: ``"paper"`` or ``"random"`` (see :mod:`monai_rigidreg.simulation.protocols`).
        num_cases: number of cases (``None``: the whole ``paper`` protocol, 64 for ``random``).
        preset: name of the preset the defaults came from (``"paper"`` or ``"fast"``).
        seed: master seed (objects of the random family, noise, random motions).
        num_objects: number of distinct objects the cases cycle over (random family only; ``None``: one per
            8 cases).
        simct_size, simct_spacing: Sim-CT grid, voxels ``(nx, ny, nz)`` and mm.
        cbct_size, cbct_spacing: CBCT grid, voxels and mm.
        simct_views, cbct_views: number of projections over 360 degrees.
        sod, sdd: source-isocentre and source-detector distances, mm (both scanners).
        simct_filter, cbct_filter: reconstruction filter windows (see ``FILTERS``).
        projection_spacing: voxel size (mm) of the object volume the CBCT is projected from; it also sets the
            detector pitch at the isocentre (``None``: the CBCT spacing).
        object_margin_mm: margin added around the Sim-CT extent for the moved object, mm.
        supersample: sub-samples per voxel and axis when analytic phantoms are voxelized.
        phantom_radius_mm: half-size of analytic phantoms, mm (``None``: half the Sim-CT extent).
        simct_photons: photons per detector pixel of the Sim-CT projections (``None``: noise-free reference).
        physics: CBCT degradations (:class:`CBCTPhysics` fields).
        mask_outside_fov: set CBCT voxels outside the field of view to air (-1000 HU).
        max_translation, max_rotation: ranges of the ``random`` protocol (mm, degrees).
        motion: one motion ``(tx, ty, tz, rx, ry, rz)`` (mm, degrees, about the Sim-CT centre) for every case,
            instead of the protocol's (``num_cases`` defaults to 1; ``simulate --motion``).
        ct_frame: with a CT as the phantom, the volumes keep the CT's physical frame: the Sim-CT and the CBCT are
            centred on the CT's centre (:func:`~monai_rigidreg.simulation.phantoms.ct_center`), so that a CBCT
            registers against the input CT itself; ``False``: centred on the origin (0, 0, 0), as before 0.5. The
            built-in phantoms are always centred on the origin.
        device: ``"cpu"``, ``"cuda"`` or ``"auto"`` (does not change the configuration identity).
        workers: worker processes for the cases (0: in this process).
        volume_dtype: how the volumes are stored: ``"int16"`` whole HU (default, as scanners store CT) or
            ``"float32"`` (see :func:`~monai_rigidreg.simulation.save_volume_hu`; a storage choice, not part of the
            configuration identity).

    Raises:
        InputError: a value of the wrong type or out of range (the message names the field and the value).
    """

    phantom: str = "shepp-logan"
    protocol: str = "paper"
    num_cases: int | None = None
    preset: str = "fast"
    seed: int = 0
    num_objects: int | None = None
    simct_size: tuple[int, int, int] = (64, 64, 64)
    simct_spacing: tuple[float, float, float] = (4.0, 4.0, 4.0)
    cbct_size: tuple[int, int, int] = (48, 48, 48)
    cbct_spacing: tuple[float, float, float] = (5.0, 5.0, 5.0)
    simct_views: int = 180
    cbct_views: int = 120
    sod: float = 800.0
    sdd: float = 1200.0
    simct_filter: str = "shepp-logan"
    cbct_filter: str = "shepp-logan"
    projection_spacing: float | None = None
    object_margin_mm: float = 32.0
    supersample: int = 2
    phantom_radius_mm: float | None = None
    simct_photons: float | None = None
    physics: dict[str, Any] = field(default_factory=lambda: CBCTPhysics().to_dict())
    mask_outside_fov: bool = True
    max_translation: float = 15.0
    max_rotation: float = 30.0
    motion: tuple[float, ...] | None = None
    ct_frame: bool = True
    device: str = "auto"
    workers: int = 0
    volume_dtype: str = "int16"

    def __post_init__(self) -> None:
        _check_types(self, _field_types(SimulationConfig))
        self.simct_size = _triple(self.simct_size, int, "simct_size")
        self.cbct_size = _triple(self.cbct_size, int, "cbct_size")
        self.simct_spacing = _triple(self.simct_spacing, float, "simct_spacing")
        self.cbct_spacing = _triple(self.cbct_spacing, float, "cbct_spacing")
        if min(self.simct_size + self.cbct_size) < 2 or min(self.simct_spacing + self.cbct_spacing) <= 0:
            raise InputError("grid sizes must be >= 2 voxels and spacings > 0 mm")
        if self.volume_dtype not in ("int16", "float32"):
            raise InputError(f"volume_dtype must be 'int16' or 'float32', got {self.volume_dtype!r}")
        if self.protocol not in PROTOCOLS:
            raise InputError(f"unknown protocol {self.protocol!r}; choose one of {PROTOCOLS}")
        for name in ("simct_filter", "cbct_filter"):
            if getattr(self, name) not in FILTERS + ("ramp",):
                raise InputError(f"unknown {name} {getattr(self, name)!r}; choose one of {FILTERS}")
        if self.num_cases is not None and self.num_cases < 1:
            raise InputError(f"num_cases must be >= 1, got {self.num_cases}")
        if min(self.simct_views, self.cbct_views) < 1:
            raise InputError("the number of views must be >= 1")
        if self.projection_spacing is not None and self.projection_spacing <= 0:
            raise InputError(f"projection_spacing must be > 0 mm, got {self.projection_spacing}")
        if str(self.device) not in ("auto", "cpu") and not str(self.device).startswith("cuda"):
            raise InputError(f"device must be 'cpu', 'cuda' or 'auto', got {self.device!r}")
        if str(self.device).startswith("cuda") and not torch.cuda.is_available():
            raise InputError("device 'cuda' was asked for but CUDA is not available (use --device cpu or auto)")
        self.physics = _physics_dict(self.physics)
        ranges = (("seed", self.seed, 0, "a whole number >= 0"), ("max_translation", self.max_translation, 0,
                  "a number >= 0 (mm)"), ("max_rotation", self.max_rotation, 0, "a number >= 0 (degrees)"),
                  ("object_margin_mm", self.object_margin_mm, 0, "a number >= 0 (mm)"),
                  ("supersample", self.supersample, 1, "a whole number >= 1"),
                  ("workers", self.workers, 0, "a whole number >= 0"))
        for name, value, least, what in ranges:
            if not (_finite(value) and value >= least):
                raise _value_error(name, value, what)
        for name in ("num_objects", "phantom_radius_mm", "simct_photons"):
            value = getattr(self, name)
            if value is not None and not (_finite(value) and value > 0):
                raise _value_error(name, value, "a number > 0 (or None)")
        if not (math.isfinite(self.sod) and math.isfinite(self.sdd) and 0 < self.sod < self.sdd):
            raise InputError(f"the source-isocentre and source-detector distances need 0 < sod < sdd, got sod "
                             f"{self.sod} and sdd {self.sdd} mm")
        if self.motion is not None:
            try:
                motion = tuple(float(v) for v in self.motion)
            except (TypeError, ValueError) as exc:
                raise _value_error("motion", self.motion, "six numbers (tx, ty, tz mm, rx, ry, rz degrees)") from exc
            if len(motion) != 6 or not all(math.isfinite(v) for v in motion):
                raise _value_error("motion", self.motion, "six finite numbers (tx, ty, tz mm, rx, ry, rz degrees)")
            self.motion = motion
        self.ct_frame = bool(self.ct_frame)
        if self.phantom not in PHANTOMS:
            p = Path(self.phantom).expanduser()
            if not p.exists():
                raise InputError(f"CT file or DICOM directory not found (built-in phantoms: {', '.join(PHANTOMS)})", p)
            self.phantom = str(p.resolve())

    # -- derived ----------------------------------------------------------------------------------------------
    @property
    def simct_grid(self) -> Grid:
        """Sim-CT grid, centred on the isocentre."""
        return Grid.centered(self.simct_size, self.simct_spacing)

    @property
    def cbct_grid(self) -> Grid:
        """CBCT grid, centred on the isocentre."""
        return Grid.centered(self.cbct_size, self.cbct_spacing)

    @property
    def cbct_physics(self) -> CBCTPhysics:
        """The :class:`CBCTPhysics` of this configuration."""
        return CBCTPhysics(**self.physics)

    @property
    def radius_mm(self) -> float:
        """Half-size of analytic phantoms, mm."""
        if self.phantom_radius_mm is not None:
            return float(self.phantom_radius_mm)
        return 0.5 * min(n * s for n, s in zip(self.simct_size, self.simct_spacing))

    def object_grid(self) -> Grid:
        """Grid of the object volume the CBCT is projected from (Sim-CT extent plus margin, isotropic)."""
        sp = float(self.projection_spacing or min(self.cbct_spacing))
        ext = [n * s + 2 * self.object_margin_mm for n, s in zip(self.simct_size, self.simct_spacing)]
        return Grid.centered([max(2, math.ceil(e / sp)) for e in ext], (sp, sp, sp))

    def identity(self) -> dict[str, Any]:
        """The fields that define the dataset (everything but the runtime ones), JSON-able.

        The fields added since 0.5 are left out where they change nothing (``motion`` when not given, ``ct_frame``
        for a built-in phantom, the physics' ``exposure_reference`` when off), so a dataset of an earlier release
        resumes; a CT's dataset of an earlier release was centred on the origin and differs in ``ct_frame``.
        """
        d = asdict(self)
        for k in _RUNTIME_KEYS:
            d.pop(k)
        if self.motion is None:
            d.pop("motion")
        if self.phantom in PHANTOMS:
            d.pop("ct_frame")
        if isinstance(d.get("physics"), dict) and d["physics"].get("exposure_reference") is None:
            d["physics"].pop("exposure_reference", None)
        return json.loads(json.dumps(d))


# ---------------------------------------------------------------------------------------------------------------
# Value checks
# ---------------------------------------------------------------------------------------------------------------
@functools.cache
def _field_types(cls: type) -> dict[str, Any]:
    """``{field name: resolved annotation}`` of a dataclass."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in fields(cls)}


def _finite(value: Any) -> bool:
    """A finite number within what seeds and counts take: an integer below 2^63 (``math.isfinite`` overflows on huge
    ones, and the random generators take 64 bits), a float that is not NaN or infinite."""
    return abs(int(value)) < 2**63 if isinstance(value, numbers.Integral) else math.isfinite(value)


def _value_error(name: str, value: Any, expected: str) -> InputError:
    return InputError(f"simulation option {name!r} must be {expected}, got {value!r}")


def _check_value(name: str, value: Any, hint: Any) -> None:
    """Raise :class:`InputError` when ``value`` is not of the kind the annotation ``hint`` asks for.

    Only the kind is checked (ranges are the caller's): ``int`` fields take integers, ``float`` fields any real
    number, ``str`` fields strings (or paths), ``bool`` fields ``True``/``False`` (or 0/1); ``X | None`` also
    takes ``None``. Tuples and dicts are checked where they are converted.
    """
    args = typing.get_args(hint)
    if type(None) in args:
        if value is None:
            return
        hint = next(a for a in args if a is not type(None))
    if hint is bool:
        if not (isinstance(value, (numbers.Integral, np.bool_)) and value in (0, 1)):
            raise _value_error(name, value, "True or False")
    elif hint is int:
        if not isinstance(value, numbers.Integral):
            raise _value_error(name, value, "an integer")
    elif hint is float:
        if not isinstance(value, numbers.Real):
            raise _value_error(name, value, "a number")
    elif hint is str and not isinstance(value, (str, os.PathLike, torch.device)):
        raise _value_error(name, value, "a string")


def _check_types(obj: Any, types: dict[str, Any]) -> None:
    for name, hint in types.items():
        _check_value(name, getattr(obj, name), hint)


def _triple(value: Any, kind: type, name: str) -> tuple:
    """Three values ``(x, y, z)`` of ``kind`` from one number or a sequence of three."""
    if isinstance(value, numbers.Real):
        value = (value,) * 3
    if isinstance(value, (str, bytes)):
        raise _value_error(name, value, "a number or 3 numbers (x, y, z)")
    try:
        v = tuple(kind(x) for x in value)
    except (TypeError, ValueError) as exc:
        raise _value_error(name, value, "a number or 3 numbers (x, y, z)") from exc
    if len(v) != 3:
        raise InputError(f"{name} must have 3 values (x, y, z), got {value}")
    return v


def _physics_dict(physics: Any) -> dict[str, Any]:
    """The complete, checked :class:`CBCTPhysics` field dict of a partial dict (or a :class:`CBCTPhysics`)."""
    if isinstance(physics, CBCTPhysics):
        physics = physics.to_dict()
    if not isinstance(physics, Mapping):
        raise _value_error("physics", physics, "a dict of CBCTPhysics fields")
    merged = {**CBCTPhysics().to_dict(), **dict(physics)}
    types = _field_types(CBCTPhysics)
    unknown = sorted(set(merged) - set(types))
    if unknown:
        raise InputError(f"unknown CBCT physics option(s) {unknown}; valid: {sorted(types)}")
    for name, hint in types.items():
        _check_value(name, merged[name], hint)
    try:
        return CBCTPhysics(**merged).to_dict()
    except ValueError as exc:  # out of range
        raise InputError(str(exc)) from exc


# ---------------------------------------------------------------------------------------------------------------
# Presets
# ---------------------------------------------------------------------------------------------------------------
PRESETS: dict[str, dict[str, Any]] = {
    "paper": {
        "simct_size": (256, 256, 256),
        "simct_spacing": (1.0, 1.0, 1.0),
        "cbct_size": (128, 128, 128),
        "cbct_spacing": (1.0, 1.0, 1.0),
        "simct_views": 360,
        "cbct_views": 360,
        "projection_spacing": 2.0,
        "supersample": 2,
    },
    "fast": {
        "simct_size": (64, 64, 64),
        "simct_spacing": (4.0, 4.0, 4.0),
        "cbct_size": (48, 48, 48),
        "cbct_spacing": (5.0, 5.0, 5.0),
        "simct_views": 180,
        "cbct_views": 120,
        "projection_spacing": 4.0,
        "supersample": 2,
    },
}
"""Grid and view presets. ``paper``: the reference study's grids (Sim-CT 256^3 at 1 mm, CBCT 128^3 at 1 mm =
an interior 128 mm field of view; ``cbct_spacing=2`` covers the whole object). ``fast``: small grids."""


def make_config(preset: str = "fast", **overrides: Any) -> SimulationConfig:
    """A :class:`SimulationConfig` from a preset and overrides.

    Overrides may name any config field or any :class:`CBCTPhysics` field (e.g. ``photons=1e4``); a scalar
    ``cbct_spacing``/``simct_spacing``/``*_size`` is used for all three axes.

    Raises:
        InputError: unknown preset or keyword, or a value of the wrong type or out of range.
    """
    if preset not in PRESETS:
        raise InputError(f"unknown preset {preset!r}; choose one of {tuple(PRESETS)}")
    names = {f.name for f in fields(SimulationConfig)}
    phys_names = {f.name for f in fields(CBCTPhysics)}
    kwargs: dict[str, Any] = {**PRESETS[preset], "preset": preset}
    physics = dict(CBCTPhysics().to_dict())
    for key, value in overrides.items():
        if value is None and key in ("num_cases", "num_objects", "projection_spacing", "phantom_radius_mm"):
            kwargs[key] = None
        elif key == "physics":
            if not isinstance(value, (CBCTPhysics, Mapping)):
                raise _value_error(key, value, "a CBCTPhysics or a dict of its fields")
            physics.update(value.to_dict() if isinstance(value, CBCTPhysics) else dict(value))
        elif key in phys_names:
            physics[key] = value
        elif key in names:
            kwargs[key] = value
        else:
            raise InputError(f"unknown simulation option {key!r}; valid: {sorted(names | phys_names)}")
    if "cbct_spacing" in overrides and "projection_spacing" not in overrides and preset == "fast":
        kwargs["projection_spacing"] = None
    kwargs["physics"] = physics
    return SimulationConfig(**kwargs)
