"""Simulation of paired planning-CT (fan-beam FBP) / CBCT (cone-beam FDK) volumes with known rigid motion.

Modules: :mod:`.phantoms` (Shepp-Logan, asymmetric and random phantoms, real CTs), :mod:`.scanner`
(geometries), :mod:`.projector` (forward/back projection), :mod:`.reconstruction` (FDK, FBP), :mod:`.physics`
(noise, scatter, beam hardening, truncation), :mod:`.protocols` (motions), :mod:`.generator` (datasets),
:mod:`.cli` (``monai-rigidreg simulate``).
"""

from __future__ import annotations

from monai_rigidreg.simulation.generator import (
    PRESETS,
    SimulationConfig,
    make_config,
    save_volume_hu,
    simulate_cbct,
    simulate_dataset,
    simulate_simct,
)
from monai_rigidreg.simulation.pair import simulate_pair  # noqa: E402  (after generator: it builds on it)
from monai_rigidreg.simulation.phantoms import (
    MU_WATER,
    PHANTOMS,
    Shape,
    ct_to_mu,
    hu_to_mu,
    load_ct,
    make_phantom,
    mu_to_hu,
    random_phantom_shapes,
    shepp_logan_shapes,
    voxelize,
)
from monai_rigidreg.simulation.physics import CBCTPhysics, apply_cbct_physics, fov_mask
from monai_rigidreg.simulation.projector import (
    cone_backproject,
    cone_forward,
    fan_backproject,
    fan_forward,
    resolve_device,
)
from monai_rigidreg.simulation.protocols import PROTOCOLS, MotionCase, paper_cases, protocol_cases, random_cases
from monai_rigidreg.simulation.reconstruction import FILTERS, fbp_fan, fdk, ramp_filter
from monai_rigidreg.simulation.scanner import ConeBeamGeometry, FanBeamGeometry

__all__ = [
    "simulate_pair",
    "PRESETS",
    "SimulationConfig",
    "make_config",
    "save_volume_hu",
    "simulate_cbct",
    "simulate_dataset",
    "simulate_simct",
    "MU_WATER",
    "PHANTOMS",
    "Shape",
    "ct_to_mu",
    "hu_to_mu",
    "load_ct",
    "make_phantom",
    "mu_to_hu",
    "random_phantom_shapes",
    "shepp_logan_shapes",
    "voxelize",
    "CBCTPhysics",
    "apply_cbct_physics",
    "fov_mask",
    "cone_backproject",
    "cone_forward",
    "fan_backproject",
    "fan_forward",
    "resolve_device",
    "PROTOCOLS",
    "MotionCase",
    "paper_cases",
    "protocol_cases",
    "random_cases",
    "FILTERS",
    "fbp_fan",
    "fdk",
    "ramp_filter",
    "ConeBeamGeometry",
    "FanBeamGeometry",
]
