"""One simulated Sim-CT / CBCT pair under a given motion (the demo's data, and a building block for scripts)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from monai_rigidreg.geometry import params_to_matrix
from monai_rigidreg.simulation.generator import (
    _detector_radius,
    _seed,
    make_config,
    save_fov_mask,
    save_volume_hu,
    simulate_cbct,
    simulate_simct,
)
from monai_rigidreg.simulation.phantoms import PHANTOMS, make_phantom
from monai_rigidreg.simulation.projector import resolve_device

__all__ = ["simulate_pair"]


def simulate_pair(
    output_dir: str | Path,
    phantom: str | Path = "shepp-logan-asym",
    params: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    preset: str = "fast",
    seed: int = 0,
    device: str = "auto",
    **overrides: Any,
) -> dict[str, Any]:
    """Simulate ``output_dir/simct.nii.gz`` (fixed, unmoved object) and ``output_dir/cbct.nii.gz`` (moving: the
    object moved by ``params`` before projection), plus ``cbct_fov.nii.gz``.

    Args:
        output_dir: created if needed; existing files are replaced.
        phantom: ``"shepp-logan"``, ``"shepp-logan-asym"``, ``"random"`` or a CT path.
        params: motion ``(tx, ty, tz, rx, ry, rz)`` (mm, degrees) about the isocentre = the Sim-CT centre.
        preset: ``"fast"`` or ``"paper"`` (see :func:`~monai_rigidreg.simulation.make_config`).
        seed: phantom (random family) and noise seed.
        device: ``"auto"``, ``"cpu"``, ``"cuda"``.
        **overrides: :class:`~monai_rigidreg.simulation.SimulationConfig` / physics fields.

    Returns:
        ``{"fixed", "moving", "moving_fov"}`` paths, ``"params"``, ``"matrix"`` and ``"center"`` of the ground
        truth (the registration transform fixed -> moving is the motion itself).
    """
    cfg = make_config(preset, phantom=str(phantom), seed=seed, device=device, **overrides)
    dev = resolve_device(device)
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    obj_seed = _seed(cfg.seed, 0, 0)
    simct_mu, _ = make_phantom(cfg.phantom, cfg.simct_grid, obj_seed, cfg.supersample, cfg.radius_mm, dev)
    simct = simulate_simct(
        simct_mu,
        cfg.simct_grid,
        cfg.simct_views,
        cfg.sod,
        cfg.sdd,
        cfg.simct_filter,
        cfg.simct_photons,
        _seed(cfg.seed, 2, 0),
        dev,
    )
    fixed = save_volume_hu(simct, cfg.simct_grid, out / "simct.nii.gz", cfg.volume_dtype)
    obj_grid = cfg.object_grid()
    obj_mu, _ = make_phantom(cfg.phantom, obj_grid, obj_seed, cfg.supersample, cfg.radius_mm, dev)
    rec, fov, _ = simulate_cbct(
        obj_mu,
        obj_grid,
        cfg.cbct_grid,
        list(params),
        (0.0, 0.0, 0.0),
        cfg.cbct_views,
        cfg.sod,
        cfg.sdd,
        cfg.cbct_physics,
        cfg.cbct_filter,
        seed=_seed(cfg.seed, 1, 0),
        detector_radius_mm=_detector_radius(cfg, obj_grid, obj_mu),
        mask_outside_fov=cfg.mask_outside_fov,
        padding_mode="zeros" if cfg.phantom in PHANTOMS else "border",
        device=dev,
    )
    moving = save_volume_hu(rec, cfg.cbct_grid, out / "cbct.nii.gz", cfg.volume_dtype)
    save_fov_mask(fov, cfg.cbct_grid, out / "cbct_fov.nii.gz")
    center = cfg.simct_grid.center()
    return {
        "fixed": str(fixed),
        "moving": str(moving),
        "moving_fov": str(out / "cbct_fov.nii.gz"),
        "params": [float(v) for v in params],
        "matrix": params_to_matrix(params, center).tolist(),
        "center": [float(v) for v in center],
    }
