"""MONAI transforms of monai-rigidreg: random rigid motion, image-domain CBCT degradation, network-grid
preprocessing. All geometry goes through :mod:`monai_rigidreg.core.geometry` (LPS mm, fixed -> moving)."""

from __future__ import annotations

from monai_rigidreg.transforms.cbct import CBCT_KEY, CBCT_RECORD_KEYS, RandCBCTDegradation, RandCBCTDegradationd
from monai_rigidreg.transforms.grid import (
    NormalizeHU,
    NormalizeHUd,
    ResampleToNetworkGrid,
    ResampleToNetworkGridd,
    network_grid,
)
from monai_rigidreg.transforms.isocenter import RandIsocenterCropd
from monai_rigidreg.transforms.rigid import (
    RIGID_KEY,
    RandRigid6DoF,
    RandRigid6DoFd,
    Rigid6DoF,
    apply_rigid_motion,
    sample_rigid_params,
)

__all__ = [
    "CBCT_KEY",
    "CBCT_RECORD_KEYS",
    "RIGID_KEY",
    "NormalizeHU",
    "NormalizeHUd",
    "RandCBCTDegradation",
    "RandCBCTDegradationd",
    "RandIsocenterCropd",
    "RandRigid6DoF",
    "RandRigid6DoFd",
    "ResampleToNetworkGrid",
    "ResampleToNetworkGridd",
    "Rigid6DoF",
    "apply_rigid_motion",
    "network_grid",
    "sample_rigid_params",
]
