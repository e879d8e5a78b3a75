"""Simulation of paired planning-CT (fan-beam FBP) / CBCT (cone-beam FDK) volumes with known rigid motion.

Modules: :mod:`.phantoms` (Shepp-Logan, asymmetric and random phantoms, real CTs), :mod:`.synth` (synthetic
anatomy for domain randomization: random label maps and contrasts, the ``"synth"`` phantom), :mod:`.scanner`
(geometries), :mod:`.projector` (forward/back projection), :mod:`.reconstruction` (FDK, FBP), :mod:`.physics`
(noise, scatter, beam hardening, truncation), :mod:`.protocols` (motions), :mod:`.config` (configuration and
presets), :mod:`.volumes` (one Sim-CT, one CBCT, one case), :mod:`.dataset` (datasets), :mod:`.pair` (one pair),
:mod:`.cli` (``monai-rigidreg simulate``) and :mod:`.toy` (tiny analytic pairs for tests and benchmarks, not a
simulator).
"""

from __future__ import annotations

from monai_rigidreg.simulation.config import PRESETS, SimulationConfig, make_config
from monai_rigidreg.simulation.dataset import simulate_dataset
from monai_rigidreg.simulation.pair import simulate_pair
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
from monai_rigidreg.simulation.projector import cone_backproject, cone_forward, fan_backproject, fan_forward
from monai_rigidreg.simulation.protocols import PROTOCOLS, MotionCase, paper_cases, protocol_cases, random_cases
from monai_rigidreg.simulation.reconstruction import FILTERS, fbp_fan, fdk, ramp_filter
from monai_rigidreg.simulation.scanner import ConeBeamGeometry, FanBeamGeometry
from monai_rigidreg.simulation.synth import synth_hu_volume, synth_label_map, synth_phantom
from monai_rigidreg.simulation.volumes import save_volume_hu, simulate_case, simulate_cbct, simulate_simct

__all__ = [
    "simulate_pair",
    "PRESETS",
    "SimulationConfig",
    "make_config",
    "save_volume_hu",
    "simulate_case",
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
    "synth_hu_volume",
    "synth_label_map",
    "synth_phantom",
    "CBCTPhysics",
    "apply_cbct_physics",
    "fov_mask",
    "cone_backproject",
    "cone_forward",
    "fan_backproject",
    "fan_forward",
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
