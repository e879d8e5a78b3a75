"""Tests of monai_rigidreg.simulation.synth: synthetic anatomy (random label maps, random contrasts) as a phantom.

Small grids (<= 77^3) and the tiny simulation settings of ``conftest.TINY_SIM``: the file runs in about 10 s on two
CPU cores.
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch
from conftest import TINY_SIM, resampled_with_truth

from monai_rigidreg.core.geometry import Grid, params_to_sitk
from monai_rigidreg.core.image_ops import erode, gradient_magnitude
from monai_rigidreg.simulation import (
    MU_WATER,
    PHANTOMS,
    hu_to_mu,
    make_phantom,
    simulate_pair,
    synth_hu_volume,
    synth_label_map,
    synth_phantom,
)
from monai_rigidreg.simulation.projector import grid_axes
from monai_rigidreg.simulation.synth import AIR, CORTEX, FIRST_TISSUE, HU_RANGES, WALL

GRID = Grid.centered((40, 40, 40), (6.0, 6.0, 6.0))
"""240 mm cube at 6 mm: the default radius is 120 mm."""
RADIUS = 120.0


def _radius(grid: Grid) -> torch.Tensor:
    xs, ys, zs = grid_axes(grid)
    return torch.sqrt(xs[:, None, None] ** 2 + ys[None, :, None] ** 2 + zs[None, None, :] ** 2).float()


def _tissue_boundaries_per_mm(labels: torch.Tensor, spacing: float) -> float:
    """Fraction of neighbouring tissue-voxel pairs with different labels, per mm (mean over the three axes)."""
    total = 0.0
    for d in range(3):
        a, b = labels.narrow(d, 0, labels.shape[d] - 1), labels.narrow(d, 1, labels.shape[d] - 1)
        both = (a >= FIRST_TISSUE) & (b >= FIRST_TISSUE)
        total += float(((a != b) & both).sum() / both.sum())
    return total / 3 / spacing


def test_deterministic_per_seed():
    a, b, c = synth_label_map(GRID, 3), synth_label_map(GRID, 3), synth_label_map(GRID, 4)
    assert a.dtype == torch.int64 and tuple(a.shape) == GRID.size
    assert torch.equal(a, b) and not torch.equal(a, c)
    ha, hb = synth_hu_volume(a, 3, GRID), synth_hu_volume(b, 3, GRID)
    assert ha.dtype == torch.float32 and torch.equal(ha, hb)
    assert not torch.equal(ha, synth_hu_volume(a, 5, GRID))  # another contrast of the same shapes
    pa, pb = synth_phantom(GRID, 3), synth_phantom(GRID, 3)
    assert torch.equal(pa, pb) and not torch.equal(pa, synth_phantom(GRID, 4))


def test_label_count_within_range():
    for seed in range(4):
        lab = synth_label_map(GRID, seed, num_labels=(8, 12))
        assert int(lab.min()) >= 0 and int(lab.max()) <= 11
        assert 6 <= lab.unique().numel() <= 12  # air, (wall), cortex and several tissue compartments
    fixed = synth_label_map(GRID, 0, num_labels=6, body=False)
    assert int(fixed.max()) <= 5 and int(fixed.min()) >= WALL + 1  # no air, no wall without a body
    with pytest.raises(ValueError, match="num_labels"):
        synth_label_map(GRID, 0, num_labels=(4, 8))
    with pytest.raises(ValueError, match="smoothness_mm"):
        synth_label_map(GRID, 0, smoothness_mm=(30.0, 8.0))


def test_air_outside_and_body_inside():
    r = _radius(GRID)
    for seed in range(4):
        lab = synth_label_map(GRID, seed)
        hu = synth_hu_volume(lab, seed, GRID)
        assert bool((lab[r > 0.95 * RADIUS] == AIR).all())  # inside a sphere of 0.95 radius
        assert bool((lab[r < 0.3 * RADIUS] != AIR).all())  # the smallest semi-axis is > 0.3 radius
        # air is exactly -1000 HU beyond the partial-volume blur, the body is not air
        assert float(hu[r > 0.95 * RADIUS + 3 * 6.0].max()) == pytest.approx(-1000.0, abs=1e-3)
        assert float(hu[r < 0.3 * RADIUS].min()) > -990.0
        assert float((lab != AIR).float().mean()) > 0.1


def test_hu_in_physical_ranges_and_mu():
    for seed in range(3):
        lab = synth_label_map(GRID, seed)
        hu = synth_hu_volume(lab, seed, GRID)
        assert float(hu.min()) >= -1000.0 and float(hu.max()) <= HU_RANGES["bone"][1]
        body = lab != AIR
        assert -150.0 < float(hu[body].median()) < 400.0  # mostly fat / soft tissue / organs
        # the cortex is bone; a custom range is respected
        assert float(hu[lab == CORTEX].median()) > 300.0
    soft = synth_hu_volume(lab, 0, GRID, hu_ranges={"bone": (200.0, 250.0)}, tissue_classes={"soft": 1.0},
                           texture=0.0, bias=0.0, blur_mm=0.0)
    assert float(soft.max()) <= 250.0
    inner = erode((lab >= FIRST_TISSUE).float()[None, None], (2, 2, 2))[0, 0] > 0
    assert 0.0 <= float(soft[inner].min()) and float(soft[inner].max()) <= 80.0
    mu = synth_phantom(GRID, 0)
    assert torch.allclose(mu, hu_to_mu(synth_hu_volume(synth_label_map(GRID, 0), 0, GRID)))
    assert float(mu.min()) >= 0.0 and float(mu.max()) <= MU_WATER * 2.5


def test_edges_exist_inside_the_body():
    for seed in range(3):
        lab = synth_label_map(GRID, seed)
        hu = synth_hu_volume(lab, seed, GRID)
        inner = erode(((lab != AIR) & (lab != WALL)).float()[None, None], (2, 2, 2))[0, 0] > 0
        grad = gradient_magnitude(hu)[inner]  # HU per voxel, central differences
        assert float(torch.quantile(grad, 0.99)) > 150.0, seed


def test_structure_size_is_physical():
    """The same object on a 2 mm and a 4 mm grid, and a smoothness in mm that sets the compartment size."""
    fine, coarse = Grid.centered((77,) * 3, (2.0,) * 3), Grid.centered((39,) * 3, (4.0,) * 3)
    for seed in (0, 1):
        lf = synth_label_map(fine, seed, num_labels=12, smoothness_mm=8.0, radius_mm=78.0)
        lc = synth_label_map(coarse, seed, num_labels=12, smoothness_mm=8.0, radius_mm=78.0)
        assert float((lf[::2, ::2, ::2] == lc).float().mean()) > 0.99  # the 4 mm voxel centres are 2 mm ones
        bf, bc = _tissue_boundaries_per_mm(lf, 2.0), _tissue_boundaries_per_mm(lc, 4.0)
        assert bc == pytest.approx(bf, rel=0.15)
        smooth = synth_label_map(fine, seed, num_labels=12, smoothness_mm=30.0, radius_mm=78.0)
        assert bf > 2.0 * _tissue_boundaries_per_mm(smooth, 2.0)


def test_registered_phantom_name():
    assert "synth" in PHANTOMS
    vol, desc = make_phantom("synth", GRID, seed=7, radius_mm=100.0)
    assert desc == {"phantom": "synth", "seed": 7, "radius_mm": 100.0}
    assert torch.equal(vol, synth_phantom(GRID, 7, radius_mm=100.0))
    assert float(vol[_radius(GRID) > 0.95 * 100.0 + 3 * 6.0].abs().max()) == 0.0  # rotations keep it in the grid


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a.ravel(), b.ravel())[0, 1])


def test_simulated_pair_matches_the_known_motion(tmp_path):
    params = [8.0, -6.0, 5.0, 4.0, -3.0, 10.0]
    pair = simulate_pair(tmp_path, phantom="synth", params=params, seed=2, device="cpu", **TINY_SIM)
    fixed, moving = sitk.ReadImage(pair["fixed"]), sitk.ReadImage(pair["moving"])
    fov = sitk.ReadImage(pair["moving_fov"])
    f, reg, raw, mask = resampled_with_truth(fixed, moving, fov, params_to_sitk(pair["params"], pair["center"]))
    assert f.max() > 200 and (f < -900).mean() > 0.1  # bone and air in the Sim-CT
    assert _ncc(f[mask], reg[mask]) > 0.9
    body = mask & (f > -500.0)  # inside the body, where air/body contrast does not dominate the correlation
    after, before = _ncc(f[body], reg[body]), _ncc(f[body], raw[body])
    assert after > 0.5 and after > before + 0.1, (before, after)


def test_synth_datasets_hold_one_object_per_seed(tmp_path):
    """``simulate --phantom synth --set num_objects=2``: two different synthetic objects, like ``random``."""
    import json

    from conftest import TINY_SIM

    from monai_rigidreg.simulation import simulate_dataset

    path = simulate_dataset(tmp_path / "ds", phantom="synth", protocol="random", num_cases=3, seed=4, progress=False,
                            num_objects=2, **{k: v for k, v in TINY_SIM.items()})
    items = json.loads(open(path, encoding="utf-8").read())["training"]
    assert len({it["fixed"] for it in items}) == 2
    assert all(it.get("object", "").startswith("synth-seed") for it in items)
