"""Shared fixtures: small deterministic volumes, seeds and the optional real-data directory."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from monai_rigidreg.data import shared_data_dir
from monai_rigidreg.geometry import rotation_matrix

torch.set_num_threads(max(1, min(2, torch.get_num_threads())))


def oblique_direction(rx: float, ry: float, rz: float) -> tuple[float, ...]:
    """Row-major direction cosines of a rotation given in degrees."""
    return tuple(rotation_matrix(*np.deg2rad([rx, ry, rz])).ravel())


def smooth_random_image(size_xyz, spacing, origin, direction, seed=0, sigma_mm=3.0) -> sitk.Image:
    """A smooth random float32 volume (structure at every scale of a few mm) with the given geometry."""
    rng = np.random.default_rng(seed)
    img = sitk.GetImageFromArray(rng.normal(size=tuple(size_xyz)[::-1]).astype(np.float32))
    img.SetSpacing(spacing)
    img = sitk.SmoothingRecursiveGaussian(img, sigma_mm)
    img.SetOrigin(origin)
    img.SetDirection(direction)
    return img


@pytest.fixture
def real_data_dir():
    d = shared_data_dir()
    if d is None:
        pytest.skip("real CT volumes not found: set MONAI_RIGIDREG_DATA or place them in ../shared/data")
    return d


TINY_SIM = dict(
    preset="fast",
    simct_size=(32, 32, 32),
    simct_spacing=(8.0, 8.0, 8.0),
    cbct_size=(24, 24, 24),
    cbct_spacing=(10.0, 10.0, 10.0),
    simct_views=60,
    cbct_views=60,
)
"""Simulation settings small enough for the default test suite (a few seconds per case on a 2-core CPU)."""


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """Three simulated CBCT/Sim-CT pairs (asymmetric Shepp-Logan, random motion) and their datalist."""
    from monai_rigidreg.simulation import simulate_dataset

    out = tmp_path_factory.mktemp("tiny_sim")
    return simulate_dataset(out, phantom="shepp-logan-asym", protocol="random", num_cases=3, seed=1, progress=False,
                            **TINY_SIM)
