"""One simulated Sim-CT / CBCT pair under a given motion (the demo's data, and a building block for scripts)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from monai_rigidreg.core.geometry import params_to_matrix
from monai_rigidreg.simulation.config import make_config
from monai_rigidreg.simulation.volumes import frame_offset, simulate_case

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

    The pair is case 0 of object 0 of the configuration (see :func:`~monai_rigidreg.simulation.simulate_case`):
    the same volumes as the first case of a dataset of the same configuration under that motion.

    Args:
        output_dir: created if needed; existing files are replaced.
        phantom: ``"shepp-logan"``, ``"shepp-logan-asym"``, ``"random"`` or a CT path.
        params: motion ``(tx, ty, tz, rx, ry, rz)`` (mm, degrees) about the isocentre = the Sim-CT centre (with a CT
            as the phantom, the CT's centre: the pair keeps the CT's frame unless ``ct_frame=False``).
        preset: ``"fast"`` or ``"paper"`` (see :func:`~monai_rigidreg.simulation.make_config`).
        seed: phantom (random family) and noise seed.
        device: ``"auto"``, ``"cpu"``, ``"cuda"``.
        **overrides: :class:`~monai_rigidreg.simulation.SimulationConfig` / physics fields.

    Returns:
        ``{"fixed", "moving", "moving_fov"}`` paths, ``"params"``, ``"matrix"`` and ``"center"`` of the ground
        truth (the registration transform fixed -> moving is the motion itself), and ``"frame_offset_mm"``: where
        the volumes lie relative to the simulation's frame centred on the origin (the CT's centre for a CT, else 0;
        :func:`~monai_rigidreg.simulation.volumes.frame_offset`).
    """
    cfg = make_config(preset, phantom=str(phantom), seed=seed, device=device, **overrides)
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    case = {
        "index": 0,
        "object_index": 0,
        "params": [float(v) for v in params],
        "fixed": "simct.nii.gz",
        "moving": "cbct.nii.gz",
        "moving_fov": "cbct_fov.nii.gz",
    }
    paths = simulate_case(cfg, case, out)
    offset = frame_offset(cfg)
    center = cfg.simct_grid.center() + offset
    return {
        "fixed": str(paths["fixed"]),
        "moving": str(paths["moving"]),
        "moving_fov": str(paths["moving_fov"]),
        "params": case["params"],
        "matrix": params_to_matrix(params, center).tolist(),
        "center": [float(v) for v in center],
        "frame_offset_mm": [float(v) for v in offset],
    }
