"""Paired Sim-CT / CBCT dataset generator with known rigid ground truth.

For every object (a phantom or a real CT) the planning CT ("Sim-CT") is simulated once, unmoved: fan-beam
projection slice by slice and FBP. For every case of the protocol the object is moved by a rigid motion ``M``
(a body point at ``p`` goes to ``M(p)``; ``M`` about the isocentre = the Sim-CT centre = the origin), then the
CBCT is projected (cone beam), degraded (:class:`~monai_rigidreg.simulation.physics.CBCTPhysics`) and
reconstructed with FDK. With fixed = Sim-CT and moving = CBCT, the registration transform (fixed -> moving
points, ``sitk.Resample(cbct, simct, T)`` aligns them) is ``T = M``; it is stored as parameters about the
Sim-CT centre, as a 4x4 matrix and with its centre.

Output layout under ``output_dir``::

    dataset.json              MONAI datalist {"training": [...]} (load_decathlon_datalist)
    simulation.json           full configuration, package versions
    objects/objNNN_simct.nii.gz      Sim-CT per object (int16, HU)
    cases/caseNNNN_cbct.nii.gz       CBCT per case (int16, HU)
    cases/caseNNNN_cbct_fov.nii.gz   CBCT field of view (uint8 mask on the CBCT grid)

All volumes are centred on the isocentre (0, 0, 0) with identity direction (LPS).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.errors import InputError, OutputExistsError
from monai_rigidreg.geometry import Grid, params_to_matrix
from monai_rigidreg.simulation.phantoms import PHANTOMS, make_phantom, mu_to_hu
from monai_rigidreg.simulation.physics import CBCTPhysics, apply_cbct_physics, fov_mask
from monai_rigidreg.simulation.projector import cone_forward, fan_forward, grid_axes, resolve_device
from monai_rigidreg.simulation.protocols import PROTOCOLS, MotionCase, protocol_cases
from monai_rigidreg.simulation.reconstruction import FILTERS, fbp_fan, fdk
from monai_rigidreg.simulation.scanner import ConeBeamGeometry, FanBeamGeometry
from monai_rigidreg.warp import warp_volume

__all__ = [
    "PRESETS",
    "SimulationConfig",
    "make_config",
    "simulate_simct",
    "simulate_cbct",
    "simulate_dataset",
    "save_volume_hu",
]

_RUNTIME_KEYS = ("device", "workers", "volume_dtype")


@dataclass
class SimulationConfig:
    """Everything that determines a simulated dataset (units in the field names' docs).

    Args:
        phantom: ``"shepp-logan"``, ``"shepp-logan-asym"``, ``"random"`` or a path to a CT (NIfTI/DICOM).
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
        device: ``"cpu"``, ``"cuda"`` or ``"auto"`` (does not change the configuration identity).
        workers: worker processes for the cases (0: in this process).
        volume_dtype: how the volumes are stored: ``"int16"`` whole HU (default, as scanners store CT) or
            ``"float32"`` (see :func:`save_volume_hu`; a storage choice, not part of the configuration identity).
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
    device: str = "auto"
    workers: int = 0
    volume_dtype: str = "int16"

    def __post_init__(self) -> None:
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
        if isinstance(self.physics, CBCTPhysics):
            self.physics = self.physics.to_dict()
        self.physics = CBCTPhysics(**{**CBCTPhysics().to_dict(), **dict(self.physics)}).to_dict()
        if self.phantom not in PHANTOMS:
            p = Path(self.phantom).expanduser()
            if not p.exists():
                raise InputError(f"CT file or DICOM directory not found (built-in phantoms: {PHANTOMS})", p)
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
        """The fields that define the dataset (everything but the runtime ones), JSON-able."""
        d = asdict(self)
        for k in _RUNTIME_KEYS:
            d.pop(k)
        return json.loads(json.dumps(d))


def _triple(value: Any, kind: type, name: str) -> tuple:
    if isinstance(value, (int, float)):
        value = (value,) * 3
    v = tuple(kind(x) for x in value)
    if len(v) != 3:
        raise InputError(f"{name} must have 3 values (x, y, z), got {value}")
    return v


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
        InputError: unknown preset or keyword.
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


# ---------------------------------------------------------------------------------------------------------------
# Single volumes
# ---------------------------------------------------------------------------------------------------------------
def simulate_simct(
    mu: torch.Tensor,
    grid: Grid,
    views: int = 360,
    sod: float = 800.0,
    sdd: float = 1200.0,
    window: str = "shepp-logan",
    photons: float | None = None,
    seed: int = 0,
    device: str | torch.device | None = "auto",
) -> torch.Tensor:
    """Fan-beam CT of an attenuation volume: slice-by-slice projection (one detector row per slice) and FBP.

    Args:
        mu: ``[nx, ny, nz]`` attenuation (1/mm) on ``grid``.
        grid: axis-aligned grid; the reconstruction is on the same grid.
        views: projections over 360 degrees.
        sod, sdd: distances, mm.
        window: FBP filter window.
        photons: photons per detector pixel for Poisson noise (``None``: noise-free).
        seed: noise seed.
        device: torch device.

    Returns:
        ``[nx, ny, nz]`` float32 reconstructed attenuation (1/mm) on ``device``.
    """
    dev = resolve_device(device)
    radius = _support_radius(mu, grid, xy_only=True) + 2 * max(grid.spacing)
    geom = FanBeamGeometry(sod=sod, sdd=sdd, num_views=views).fitted(radius, min(grid.spacing[:2]))
    sino = fan_forward(mu, grid, geom, dev)
    if photons:
        gen = torch.Generator(device=dev).manual_seed(int(seed))
        counts = torch.poisson(photons * torch.exp(-sino), generator=gen)
        sino = -torch.log(counts.clamp_min(1.0) / photons)
    return fbp_fan(sino, geom, grid, window, dev)


def _support_radius(mu: torch.Tensor, grid: Grid, xy_only: bool = False, threshold: float = 1e-5) -> float:
    """Largest distance (mm) from the isocentre (or the z axis) of a voxel with ``mu > threshold``."""
    xs, ys, zs = grid_axes(grid, mu.device)
    occ = mu > threshold
    if not bool(occ.any()):
        return float(max(grid.spacing))
    r2 = xs[:, None] ** 2 + ys[None, :] ** 2
    r_xy = float(r2[occ.any(2)].max().sqrt())
    if xy_only:
        return r_xy
    return float(math.sqrt(r_xy**2 + float((zs[occ.any(0).any(0)] ** 2).max())))


def simulate_cbct(
    mu_object: torch.Tensor,
    object_grid: Grid,
    cbct_grid: Grid,
    params: Any = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    center: Any = (0.0, 0.0, 0.0),
    views: int = 360,
    sod: float = 800.0,
    sdd: float = 1200.0,
    physics: CBCTPhysics | None = None,
    window: str = "shepp-logan",
    seed: int = 0,
    detector_radius_mm: float | None = None,
    mask_outside_fov: bool = True,
    padding_mode: str = "zeros",
    device: str | torch.device | None = "auto",
) -> tuple[torch.Tensor, torch.Tensor, ConeBeamGeometry]:
    """CBCT of an object moved by the rigid motion ``M = params`` (a body point at ``p`` goes to ``M(p)``).

    The moved object is ``obj(M^-1(y))`` (trilinear resampling on ``object_grid``), projected with the cone
    beam, degraded by ``physics`` and reconstructed with FDK on ``cbct_grid``.

    Args:
        mu_object: ``[nx, ny, nz]`` attenuation (1/mm) on ``object_grid`` (axis-aligned).
        object_grid: grid of ``mu_object``; it should leave room for the motion.
        cbct_grid: reconstruction grid.
        params: motion ``(tx, ty, tz, rx, ry, rz)``, mm / degrees, about ``center`` (LPS mm).
        center: rotation centre, mm (the Sim-CT centre, the isocentre).
        views: projections over 360 degrees.
        sod, sdd: distances, mm.
        physics: degradations (default :class:`CBCTPhysics` defaults; ``CBCTPhysics.ideal()`` for none).
        window: FDK filter window.
        seed: noise seed.
        detector_radius_mm: radius about the axis the detector must cover (``None``: the moved object's).
            The detector pitch at the isocentre is ``object_grid`` spacing.
        mask_outside_fov: set voxels outside the field of view to 0 (air).
        padding_mode: what the moved object has where it comes from outside ``object_grid``
            (``"zeros"`` or ``"border"``).
        device: torch device.

    Returns:
        ``(mu [nx, ny, nz] float32 1/mm, fov [nx, ny, nz] bool, geometry)`` on ``device``.
    """
    dev = resolve_device(device)
    physics = CBCTPhysics() if physics is None else physics
    m = params_to_matrix(params, center)
    inv = torch.as_tensor(np.linalg.inv(m), dtype=torch.float64, device=dev)[None]
    obj = mu_object.to(device=dev, dtype=torch.float32)[None, None]
    if np.allclose(m, np.eye(4)):
        moved = obj[0, 0]
    else:
        moved = warp_volume(obj, inv, object_grid, object_grid, "bilinear", padding_mode)[0, 0]
    radius = detector_radius_mm
    if radius is None:
        radius = _support_radius(moved, object_grid, xy_only=True) + max(object_grid.spacing)
    half_h = 0.5 * cbct_grid.size[2] * cbct_grid.spacing[2] + cbct_grid.spacing[2]
    geom = ConeBeamGeometry(sod=sod, sdd=sdd, num_views=views).fitted(radius, half_h, min(object_grid.spacing))
    proj = cone_forward(moved, object_grid, geom, dev)
    del moved, obj
    gen = torch.Generator(device=dev).manual_seed(int(seed))
    proj = apply_cbct_physics(proj, geom, physics, gen)
    rec = fdk(proj, geom, cbct_grid, window, dev)
    fov = fov_mask(cbct_grid, geom, physics, dev)
    if mask_outside_fov:
        rec = torch.where(fov, rec, torch.zeros_like(rec))
    return rec, fov, geom


def save_volume_hu(mu: torch.Tensor, grid: Grid, path: str | Path, dtype: str = "int16") -> Path:
    """Write an attenuation volume ``[nx, ny, nz]`` (1/mm) as a NIfTI in HU (atomically).

    ``dtype="int16"`` (default) stores whole HU, clipped to the int16 range, as CT scanners and DICOM do: a
    rounding error of at most 0.5 HU, far below the noise, for smaller files read in about half the time of
    compressed float32 (``benchmarks/bench_inference_speed.py``). ``"float32"`` keeps the reconstruction's values
    exactly.
    """
    if dtype not in ("int16", "float32"):
        raise ValueError(f"dtype must be 'int16' or 'float32', got {dtype!r}")
    arr = mu_to_hu(mu.detach().to("cpu", torch.float32)).numpy().transpose(2, 1, 0)
    if dtype == "int16":
        info = np.iinfo(np.int16)
        arr = np.clip(np.rint(arr), info.min, info.max).astype(np.int16)
    img = grid.apply_to(sitk.GetImageFromArray(np.ascontiguousarray(arr)))
    return _write_atomic(img, Path(path))


def save_fov_mask(fov: torch.Tensor, grid: Grid, path: str | Path) -> Path:
    """Write a boolean field-of-view mask ``[nx, ny, nz]`` as a uint8 NIfTI on ``grid`` (atomically)."""
    arr = fov.detach().cpu().numpy().transpose(2, 1, 0).astype(np.uint8)
    return _write_atomic(grid.apply_to(sitk.GetImageFromArray(np.ascontiguousarray(arr))), Path(path))


def _write_atomic(img: sitk.Image, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    sitk.WriteImage(img, str(tmp), True)
    os.replace(tmp, path)
    return path


# ---------------------------------------------------------------------------------------------------------------
# Dataset
# ---------------------------------------------------------------------------------------------------------------
def _seed(*keys: int) -> int:
    return int(np.random.SeedSequence([int(k) for k in keys]).generate_state(1)[0])


def _num_objects(cfg: SimulationConfig, num_cases: int) -> int:
    if cfg.phantom != "random":
        return 1
    if cfg.num_objects is not None:
        return max(1, min(int(cfg.num_objects), num_cases))
    return max(1, math.ceil(num_cases / 8))


def _object_name(cfg: SimulationConfig, k: int) -> str:
    if cfg.phantom == "random":
        return f"random-seed{_seed(cfg.seed, 0, k)}"
    if cfg.phantom in PHANTOMS:
        return cfg.phantom
    return Path(cfg.phantom).name


def _object_volume(cfg: SimulationConfig, k: int, grid: Grid, device: torch.device) -> torch.Tensor:
    mu, _ = make_phantom(cfg.phantom, grid, _seed(cfg.seed, 0, k), cfg.supersample, cfg.radius_mm, device)
    return mu


def _detector_radius(cfg: SimulationConfig, obj_grid: Grid, mu: torch.Tensor) -> float:
    """One detector per object: covers the object (3D radius about the isocentre) plus the largest translation."""
    t_max = cfg.max_translation * math.sqrt(3)
    radius = _support_radius(mu, obj_grid) + t_max + max(obj_grid.spacing)
    return min(radius, 0.9 * cfg.sod)


_CACHE: dict[tuple, Any] = {}


def _run_case(cfg_dict: dict[str, Any], case: dict[str, Any], out_dir: str) -> str:
    """Simulate and write one CBCT (top-level so that worker processes can run it)."""
    cfg = SimulationConfig(**cfg_dict)
    dev = resolve_device(cfg.device)
    key = (json.dumps(cfg.identity(), sort_keys=True), case["object_index"], str(dev))
    if key not in _CACHE:
        _CACHE.clear()
        grid = cfg.object_grid()
        mu = _object_volume(cfg, case["object_index"], grid, dev)
        _CACHE[key] = (grid, mu, _detector_radius(cfg, grid, mu))
    grid, mu, radius = _CACHE[key]
    rec, fov, _ = simulate_cbct(
        mu,
        grid,
        cfg.cbct_grid,
        case["params"],
        (0.0, 0.0, 0.0),
        cfg.cbct_views,
        cfg.sod,
        cfg.sdd,
        cfg.cbct_physics,
        cfg.cbct_filter,
        seed=_seed(cfg.seed, 1, case["index"]),
        detector_radius_mm=radius,
        mask_outside_fov=cfg.mask_outside_fov,
        padding_mode="zeros" if cfg.phantom in PHANTOMS else "border",
        device=dev,
    )
    out = Path(out_dir)
    save_fov_mask(fov, cfg.cbct_grid, out / case["moving_fov"])
    # written last: its presence marks a finished case
    save_volume_hu(rec, cfg.cbct_grid, out / case["moving"], cfg.volume_dtype)
    return case["case_id"]


def _worker_init() -> None:
    torch.set_num_threads(1)


def _versions() -> dict[str, str]:
    import monai

    import monai_rigidreg

    return {
        "monai_rigidreg": getattr(monai_rigidreg, "__version__", "?"),
        "torch": torch.__version__,
        "monai": monai.__version__,
        "SimpleITK": sitk.Version.VersionString(),
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


def _prepare_output(out: Path, cfg: SimulationConfig, overwrite: bool) -> None:
    meta = out / "simulation.json"
    if out.exists() and not out.is_dir():
        raise OutputExistsError(out, "it is a file, not a directory")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        if not meta.is_file():
            raise OutputExistsError(
                out, "it is a non-empty directory that is not a simulated dataset; pass overwrite=True"
            )
        try:
            old = json.loads(meta.read_text())["config"]
        except (ValueError, KeyError) as exc:
            raise OutputExistsError(out, f"its simulation.json is unreadable ({exc}); pass overwrite=True") from exc
        if old != cfg.identity():
            diff = sorted(k for k in set(old) | set(cfg.identity()) if old.get(k) != cfg.identity().get(k))
            raise OutputExistsError(
                out,
                f"it holds a dataset of another configuration (differs in {diff}); "
                "pass overwrite=True or choose another directory",
            )


def simulate_dataset(
    output_dir: str | Path,
    phantom: str | Path = "shepp-logan",
    protocol: str = "paper",
    num_cases: int | None = None,
    preset: str = "fast",
    seed: int = 0,
    device: str = "auto",
    overwrite: bool = False,
    workers: int = 0,
    progress: bool = True,
    **overrides: Any,
) -> Path:
    """Simulate a paired Sim-CT (fixed) / CBCT (moving) dataset with ground-truth rigid transforms.

    Deterministic for a seed (on one device); resumable: finished cases found in ``output_dir`` (same
    configuration) are kept and skipped.

    Args:
        output_dir: output directory (created).
        phantom: ``"shepp-logan"``, ``"shepp-logan-asym"``, ``"random"`` or a path to a CT (NIfTI file or
            DICOM directory, HU).
        protocol: ``"paper"`` or ``"random"``.
        num_cases: number of cases (``None``: all 63 ``paper`` cases, 64 ``random`` ones).
        preset: ``"paper"`` (Sim-CT 256^3 at 1 mm, CBCT 128^3 at 1 mm) or ``"fast"`` (Sim-CT 64^3 at 4 mm,
            CBCT 48^3 at 5 mm).
        seed: master seed.
        device: ``"cpu"``, ``"cuda"`` or ``"auto"``.
        overwrite: recompute everything even where files exist, and accept a directory holding something else.
        workers: worker processes for the CBCTs (0: this process).
        progress: show a tqdm progress bar.
        **overrides: any :class:`SimulationConfig` or :class:`CBCTPhysics` field (e.g. ``cbct_spacing=2.0``,
            ``cbct_views=180``, ``photons=1e4``, ``scatter_to_primary=0``).

    Returns:
        Path of ``dataset.json`` (a MONAI datalist: ``load_decathlon_datalist(path, data_list_key="training")``).

    Raises:
        InputError: bad options, a missing or unsuitable CT.
        OutputExistsError: ``output_dir`` holds other data and ``overwrite`` is False.
    """
    cfg = make_config(
        preset,
        phantom=str(phantom),
        protocol=protocol,
        num_cases=num_cases,
        seed=seed,
        device=device,
        workers=workers,
        **overrides,
    )
    out = Path(output_dir).expanduser()
    _prepare_output(out, cfg, overwrite)
    out.mkdir(parents=True, exist_ok=True)
    dev = resolve_device(cfg.device)
    meta = {"config": cfg.identity(), "runtime": {"device": str(dev), "workers": cfg.workers}, "versions": _versions()}
    (out / "simulation.json").write_text(json.dumps(meta, indent=2))

    cases: list[MotionCase] = protocol_cases(
        cfg.protocol, cfg.num_cases, cfg.seed, cfg.max_translation, cfg.max_rotation
    )
    n_obj = _num_objects(cfg, len(cases))
    center = cfg.simct_grid.center()
    items, todo = [], []
    for i, case in enumerate(cases):
        k = i % n_obj
        cid = f"case{i:04d}"
        item = {
            "fixed": f"objects/obj{k:03d}_simct.nii.gz",
            "moving": f"cases/{cid}_cbct.nii.gz",
            "moving_fov": f"cases/{cid}_cbct_fov.nii.gz",
            "params": [float(v) for v in case.params],
            "matrix": params_to_matrix(case.params, center).tolist(),
            "center": [float(v) for v in center],
            "case_id": cid,
            "object": _object_name(cfg, k),
            "group": case.group,
            "label": case.label,
            "condition": case.condition,
        }
        items.append(item)
        if overwrite or not ((out / item["moving"]).is_file() and (out / item["moving_fov"]).is_file()):
            todo.append({**item, "index": i, "object_index": k})

    from tqdm.auto import tqdm

    # the Sim-CTs: one per object, unmoved
    for k in range(n_obj):
        path = out / f"objects/obj{k:03d}_simct.nii.gz"
        if path.is_file() and not overwrite:
            continue
        grid = cfg.simct_grid
        mu = _object_volume(cfg, k, grid, dev)
        rec = simulate_simct(
            mu, grid, cfg.simct_views, cfg.sod, cfg.sdd, cfg.simct_filter, cfg.simct_photons, _seed(cfg.seed, 2, k), dev
        )
        save_volume_hu(rec, grid, path, cfg.volume_dtype)
    cfg_dict = dataclasses.asdict(cfg)
    bar = tqdm(total=len(todo), desc="CBCT cases", unit="case", disable=not progress)
    if cfg.workers > 0 and len(todo) > 1:
        ctx = torch.multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(cfg.workers, mp_context=ctx, initializer=_worker_init) as pool:
            for _ in pool.map(_run_case, [cfg_dict] * len(todo), todo, [str(out)] * len(todo)):
                bar.update()
    else:
        for case in todo:
            _run_case(cfg_dict, case, str(out))
            bar.update()
    bar.close()
    _CACHE.clear()
    path = out / "dataset.json"
    tmp = out / ".dataset.json.tmp"
    tmp.write_text(json.dumps({"name": "monai-rigidreg simulated CBCT/Sim-CT pairs", "training": items}, indent=1))
    os.replace(tmp, path)
    return path
