"""The package's cone-beam projector and FDK against RTK's (``itk-rtk``, an independent implementation): the same
moved phantom reconstructed by both must agree voxel for voxel, so a flipped axis, a wrong sign of the motion or a
half-voxel shift in either the projector or the reconstruction fails here."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("itk", reason="itk (itk-elastix / itk-rtk, the test extra) is not installed")

from benchmarks.simulation.rtk_cbct import rtk_available, rtk_cbct  # noqa: E402
from monai_rigidreg.core.geometry import Grid  # noqa: E402
from monai_rigidreg.simulation.phantoms import make_phantom  # noqa: E402
from monai_rigidreg.simulation.physics import CBCTPhysics  # noqa: E402
from monai_rigidreg.simulation.volumes import simulate_cbct  # noqa: E402

pytestmark = pytest.mark.skipif(not rtk_available(), reason="itk-rtk (the test extra) is not installed")

MOTION = (6.0, -4.0, 3.0, 5.0, -3.0, 8.0)  # mm, degrees


@pytest.fixture(scope="module")
def pair():
    torch.set_num_threads(2)
    obj_grid = Grid.centered((64, 64, 64), (4.0, 4.0, 4.0))
    cbct_grid = Grid.centered((32, 32, 32), (4.0, 4.0, 4.0))
    mu, _ = make_phantom("shepp-logan-asym", obj_grid, seed=0, supersample=1, radius_mm=100.0)
    ideal = CBCTPhysics.ideal()
    ours, fov, geom = simulate_cbct(mu, obj_grid, cbct_grid, MOTION, (0.0, 0.0, 0.0), 90, 800.0, 1200.0, ideal,
                                    detector_radius_mm=140.0, device="cpu")
    return mu, obj_grid, cbct_grid, geom, ideal, ours.numpy(), fov.numpy()


def _shift_mm(a: np.ndarray, b: np.ndarray, mask: np.ndarray, spacing: float) -> np.ndarray:
    """The shift s (mm, x y z) with b(p) ~ a(p - s): the least-squares fit of b - a to -grad(a) s + c."""
    grads = np.gradient(a, spacing)
    design = np.c_[np.stack([g[mask] for g in grads], 1), np.ones(int(mask.sum()))]
    return -np.linalg.lstsq(design, (b - a)[mask], rcond=None)[0][:3]


def test_rtk_reconstructs_the_same_moved_phantom(pair):
    mu, obj_grid, cbct_grid, geom, ideal, ours, fov = pair
    theirs, fov_rtk = rtk_cbct(mu, obj_grid, cbct_grid, MOTION, geom, ideal, degrade=False)
    assert np.array_equal(fov, fov_rtk)
    inner = fov & (np.abs(ours) + np.abs(theirs) > 0)
    assert np.corrcoef(ours[inner], theirs[inner])[0, 1] > 0.99
    # the same mean attenuation (a scale or a filter gain error shows here) ...
    assert theirs[inner].mean() == pytest.approx(ours[inner].mean(), rel=0.02)
    # ... at the same place: well under a tenth of a 4 mm voxel
    assert np.abs(_shift_mm(ours, theirs, inner, 4.0)).max() < 0.1


def test_a_wrong_motion_or_a_flipped_axis_is_seen(pair):
    mu, obj_grid, cbct_grid, geom, ideal, ours, fov = pair
    assert np.corrcoef(ours[fov], ours[:, ::-1, :][fov])[0, 1] < 0.9  # an axis flipped (y)
    moved_back = tuple(-v for v in MOTION[:3]) + MOTION[3:]  # translation sign flipped
    theirs, _ = rtk_cbct(mu, obj_grid, cbct_grid, moved_back, geom, ideal, degrade=False)
    assert np.corrcoef(ours[fov], theirs[fov])[0, 1] < 0.9
    half_voxel = (MOTION[0] + 2.0,) + MOTION[1:]  # half a voxel along x
    theirs, _ = rtk_cbct(mu, obj_grid, cbct_grid, half_voxel, geom, ideal, degrade=False)
    assert _shift_mm(ours, theirs, fov & (np.abs(ours) + np.abs(theirs) > 0), 4.0)[0] == pytest.approx(2.0, abs=0.3)
