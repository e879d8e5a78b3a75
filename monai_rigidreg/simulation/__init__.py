"""Simulation of paired planning-CT (fan-beam FBP) / CBCT (cone-beam FDK) volumes with known rigid motion.

Modules: :mod:`.phantoms` (Shepp-Logan, asymmetric and random phantoms, real CTs), :mod:`.synth` (synthetic
anatomy for domain randomization: random label maps and contrasts, the ``"synth"`` phantom), :mod:`.scanner`
(geometries), :mod:`.projector` (forward/back projection), :mod:`.reconstruction` (FDK, FBP), :mod:`.physics`
(noise, scatter, beam hardening, truncation), :mod:`.protocols` (motions), :mod:`.config` (configuration and
presets), :mod:`.volumes` (one Sim-CT, one CBCT, one case), :mod:`.dataset` (datasets), :mod:`.pair` (one pair),
:mod:`.simulate_command` (``monai-rigidreg simulate``) and :mod:`.toy` (tiny analytic pairs for tests and
benchmarks, not a simulator).

The names below are exported here on first use (PEP 562), so that ``monai-rigidreg --help`` builds the ``simulate``
command's parser without importing torch.
"""

from monai_rigidreg.core.lazy_exports import lazy_exports

_MODULES = {
    "config": ("PRESETS", "SimulationConfig", "make_config"),
    "dataset": ("simulate_dataset",),
    "pair": ("simulate_pair",),
    "phantoms": ("MU_WATER", "PHANTOMS", "Shape", "ct_to_mu", "hu_to_mu", "load_ct", "make_phantom", "mu_to_hu",
                 "random_phantom_shapes", "shepp_logan_shapes", "voxelize"),
    "physics": ("CBCTPhysics", "apply_cbct_physics", "centre_line_integral", "effective_photons", "fov_mask"),
    "projector": ("cone_backproject", "cone_forward", "fan_backproject", "fan_forward"),
    "protocols": ("PROTOCOLS", "MotionCase", "paper_cases", "protocol_cases", "random_cases"),
    "reconstruction": ("FILTERS", "fbp_fan", "fdk", "ramp_filter"),
    "scanner": ("ConeBeamGeometry", "FanBeamGeometry"),
    "synth": ("synth_hu_volume", "synth_label_map", "synth_phantom"),
    "volumes": ("save_volume_hu", "simulate_case", "simulate_cbct", "simulate_simct"),
}
_NAMES = {name: f"monai_rigidreg.simulation.{module}" for module, names in _MODULES.items() for name in names}
__all__ = list(_NAMES)
__getattr__, __dir__ = lazy_exports(__name__, _NAMES)
