"""monai-rigidreg: rigid 6-DoF CBCT-to-CT registration for adaptive radiotherapy, as a MONAI plugin."""

from __future__ import annotations

__version__ = "0.1.0"

from monai_rigidreg.geometry import (  # noqa: E402
    PARAM_NAMES,
    Grid,
    matrix_to_params,
    params_to_matrix,
    params_to_sitk,
    sitk_to_params,
    target_registration_error,
)

__all__ = [
    "__version__",
    "PARAM_NAMES",
    "Grid",
    "matrix_to_params",
    "params_to_matrix",
    "params_to_sitk",
    "sitk_to_params",
    "target_registration_error",
]
