"""The last level's expected TRE (registration.precision): it grows with the residual and with less structure in
view, it is infinite where the images leave a direction of the pose free, and its mm / degree bookkeeping is exact."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from monai_rigidreg.core.geometry import Grid, grid_points
from monai_rigidreg.registration.precision import expected_tre_mm, pose_covariance

EYE = torch.eye(4, dtype=torch.float64)[None]


def _texture(n: int, seed: int = 0) -> torch.Tensor:
    """``[1, 2, n, n, n]`` smooth random features (two channels, as the last level's)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand((1, 1, n, n, n), generator=g)
    for _ in range(2):
        x = F.avg_pool3d(x, 5, 1, 2)
    return torch.cat([x, 0.5 * x], 1)


def _noisy(fixed: torch.Tensor, sigma: float, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return fixed + sigma * torch.randn(fixed.shape, generator=g)


def test_expected_tre_follows_the_residual_and_the_structure_in_view():
    """Twice the residual noise: twice the expected TRE (the covariance is s^2 H^-1). Half the volume weighted:
    more than sqrt(2) times (half the samples, and a shorter lever arm for the rotations). A bias polynomial
    estimated with the pose can only raise it (it takes variation the pose could have used)."""
    grid = Grid(size=(48, 48, 48), spacing=(2.0, 2.0, 2.0))
    fixed = _texture(48)
    one = expected_tre_mm(pose_covariance(_noisy(fixed, 0.01), fixed, grid, EYE)[0], grid)
    two = expected_tre_mm(pose_covariance(_noisy(fixed, 0.02), fixed, grid, EYE)[0], grid)
    assert two / one == pytest.approx(2.0, rel=0.05)
    half = torch.zeros((1, 1, 48, 48, 48))
    half[..., :24] = 1.0
    halved = expected_tre_mm(pose_covariance(_noisy(fixed, 0.01), fixed, grid, EYE, weight=half)[0], grid)
    assert halved > math.sqrt(2.0) * one
    biased = expected_tre_mm(pose_covariance(_noisy(fixed, 0.01), fixed, grid, EYE, bias_degree=2)[0], grid)
    assert biased >= one * 0.999


def test_a_pose_the_images_leave_free_has_no_finite_precision():
    """Features that vary along x only (slabs) fix tx but neither ty nor tz: the covariance is infinite, and so is
    the expected TRE; so it is with too few voxels in view."""
    grid = Grid(size=(32, 32, 32), spacing=(2.0, 2.0, 2.0))
    x = torch.linspace(0, 6 * math.pi, 32)
    slabs = torch.sin(x)[:, None, None].expand(32, 32, 32)[None, None].contiguous()
    fixed = torch.cat([slabs, slabs], 1)
    cov, _, _ = pose_covariance(_noisy(fixed, 0.01), fixed, grid, EYE)
    assert not np.all(np.isfinite(cov)) and expected_tre_mm(cov, grid) == math.inf
    tiny = torch.zeros((1, 1, 32, 32, 32))
    tiny[..., :2, :2, :2] = 1.0
    cov, _, count = pose_covariance(_noisy(_texture(32), 0.01), _texture(32), grid, EYE, weight=tiny)
    assert count < 100 and expected_tre_mm(cov, grid) == math.inf


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_expected_tre_of_one_parameter_is_its_displacement_over_the_grid(axis):
    """A variance of 1 on one translation: 1 mm everywhere. A variance of 1 degree^2 on the rotation about one axis:
    the RMS over the grid points of their distance from that axis (through the grid centre) in radians. On a grid
    that is long along z, a transposed axis or radians mistaken for degrees gives another number."""
    grid = Grid(size=(12, 16, 40), spacing=(2.0, 1.5, 1.0), origin=(-5.0, 3.0, 7.0))
    cov = np.zeros((6, 6))
    cov[axis, axis] = 1.0
    assert expected_tre_mm(cov, grid, step=1) == pytest.approx(1.0, rel=1e-6)
    cov = np.zeros((6, 6))
    cov[3 + axis, 3 + axis] = 1.0
    rel = grid_points(grid, 1) - grid.center()
    others = [a for a in range(3) if a != axis]
    want = math.sqrt(float(np.mean((rel[:, others] ** 2).sum(1)))) * math.pi / 180.0
    assert expected_tre_mm(cov, grid, step=1) == pytest.approx(want, rel=1e-4)
