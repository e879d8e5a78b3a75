"""Round trips and convention pins for monai_rigidreg.core.geometry."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch
from conftest import oblique_direction

from monai_rigidreg.core.geometry import (
    Grid,
    compose_matrices,
    lps_to_ras_affine,
    mask_points,
    matrix_to_params,
    matrix_to_params_torch,
    normalized_theta,
    parameter_errors,
    params_to_matrix,
    params_to_matrix_torch,
    params_to_sitk,
    ras_to_lps_affine,
    recenter_params,
    rotation_matrix,
    sitk_to_matrix,
    sitk_to_params,
    target_registration_error,
    transform_points,
)

RNG = np.random.default_rng(1234)
CASES = [
    (np.r_[RNG.uniform(-50, 50, 3), RNG.uniform(-45, 45, 3)], RNG.uniform(-150, 150, 3)) for _ in range(200)
]


def test_worked_example_from_conventions():
    tfm = params_to_sitk([5, 0, 0, 10, 0, 0], (0, 0, 0))
    np.testing.assert_allclose(tfm.TransformPoint((0, 0, 0)), (5, 0, 0), atol=1e-12)
    np.testing.assert_allclose(tfm.TransformPoint((0, 10, 0)), (5, 9.848, 1.736), atol=1e-3)
    np.testing.assert_allclose(params_to_matrix([5, 0, 0, 10, 0, 0]) @ [0, 10, 0, 1], (5, 9.848, 1.736, 1), atol=1e-3)
    g = Grid((4, 4, 4), (2, 2, 2), (-3, -3, -3))
    np.testing.assert_allclose(g.center(), (0, 0, 0), atol=1e-12)


def test_rotation_order_is_itk_zxy():
    # R = Rz @ Rx @ Ry: compare against SimpleITK's own matrix for each single axis and a mix
    for angles in [(0.3, 0, 0), (0, 0.4, 0), (0, 0, -0.5), (0.2, -0.7, 1.1)]:
        tfm = sitk.Euler3DTransform((0, 0, 0), *angles, (0, 0, 0))
        np.testing.assert_allclose(rotation_matrix(*angles), np.reshape(tfm.GetMatrix(), (3, 3)), atol=1e-12)


@pytest.mark.parametrize("params,center", CASES[:100])
def test_params_matrix_roundtrip(params, center):
    np.testing.assert_allclose(matrix_to_params(params_to_matrix(params, center), center), params, atol=1e-9)


@pytest.mark.parametrize("params,center", CASES[100:])
def test_params_sitk_roundtrip_and_points(params, center):
    tfm = params_to_sitk(params, center)
    np.testing.assert_allclose(sitk_to_params(tfm), params, atol=1e-9)
    np.testing.assert_allclose(tfm.GetCenter(), center, atol=1e-12)
    pts = RNG.uniform(-200, 200, (10, 3))
    expected = np.array([tfm.TransformPoint(tuple(p)) for p in pts])
    np.testing.assert_allclose(transform_points(params_to_matrix(params, center), pts), expected, atol=1e-9)
    np.testing.assert_allclose(sitk_to_matrix(tfm), params_to_matrix(params, center), atol=1e-12)


def test_sitk_to_params_other_rigid_types_and_recentering():
    p, c = CASES[0]
    versor = sitk.VersorRigid3DTransform()
    versor.SetCenter(tuple(c))
    versor.SetMatrix(tuple(params_to_matrix(p, c)[:3, :3].ravel()))
    versor.SetTranslation(tuple(p[:3]))
    np.testing.assert_allclose(sitk_to_params(versor), p, atol=1e-9)
    # expressing about another centre changes translation only, and the map stays the same
    q = sitk_to_params(params_to_sitk(p, c), center=(0, 0, 0))
    np.testing.assert_allclose(q[3:], p[3:], atol=1e-9)
    np.testing.assert_allclose(params_to_matrix(q, (0, 0, 0)), params_to_matrix(p, c), atol=1e-9)
    np.testing.assert_allclose(recenter_params(p, c, (0, 0, 0)), q, atol=1e-9)


def test_composite_transform_matrix_order():
    a, ca = CASES[1]
    b, cb = CASES[2]
    comp = sitk.CompositeTransform([params_to_sitk(a, ca), params_to_sitk(b, cb)])
    pts = RNG.uniform(-100, 100, (5, 3))
    expected = np.array([comp.TransformPoint(tuple(p)) for p in pts])
    np.testing.assert_allclose(transform_points(sitk_to_matrix(comp), pts), expected, atol=1e-9)
    np.testing.assert_allclose(
        sitk_to_matrix(comp), compose_matrices(params_to_matrix(a, ca), params_to_matrix(b, cb)), atol=1e-9
    )


def test_matrix_to_params_rejects_non_rigid():
    m = np.eye(4)
    m[0, 0] = 1.1
    with pytest.raises(ValueError, match="not rigid"):
        matrix_to_params(m)
    with pytest.raises(ValueError, match="6 parameters"):
        params_to_matrix([1, 2, 3])
    with pytest.raises(ValueError, match="finite"):
        params_to_matrix([np.nan, 0, 0, 0, 0, 0])


def test_torch_matches_numpy_and_is_differentiable():
    params = torch.tensor(np.stack([c[0] for c in CASES[:8]]), dtype=torch.float64, requires_grad=True)
    centers = torch.tensor(np.stack([c[1] for c in CASES[:8]]), dtype=torch.float64)
    mats = params_to_matrix_torch(params, centers)
    for i in range(8):
        np.testing.assert_allclose(mats[i].detach().numpy(), params_to_matrix(CASES[i][0], CASES[i][1]), atol=1e-12)
    back = matrix_to_params_torch(mats, centers)
    np.testing.assert_allclose(back.detach().numpy(), params.detach().numpy(), atol=1e-9)
    assert torch.autograd.gradcheck(lambda p: params_to_matrix_torch(p, centers[:2]), (params[:2].detach().clone()
                                    .requires_grad_(True),))


def test_grid_from_sitk_and_affine_roundtrip():
    img = sitk.Image(24, 28, 20, sitk.sitkFloat32)
    img.SetSpacing((1.0, 1.5, 2.0))
    img.SetOrigin((-10.0, 5.0, 3.0))
    img.SetDirection(oblique_direction(10, -5, 20))
    g = Grid.from_sitk(img)
    for idx in [(0, 0, 0), (3, 7, 11), (23, 27, 19)]:
        np.testing.assert_allclose((g.index_to_physical() @ [*idx, 1])[:3], img.TransformIndexToPhysicalPoint(idx))
    ras = g.affine("RAS")
    np.testing.assert_allclose(ras, lps_to_ras_affine(g.index_to_physical()))
    np.testing.assert_allclose(ras_to_lps_affine(ras), g.index_to_physical())
    g2 = Grid.from_affine(ras, g.size, space="RAS")
    np.testing.assert_allclose(g2.index_to_physical(), g.index_to_physical(), atol=1e-12)
    np.testing.assert_allclose(g.center(), img.TransformContinuousIndexToPhysicalPoint((11.5, 13.5, 9.5)))


@pytest.mark.parametrize("array_order", ["xyz", "zyx"])
def test_normalized_theta_maps_corners(array_order):
    fixed = Grid((5, 6, 7), (1.0, 2.0, 3.0), (1, 2, 3), oblique_direction(0, 0, 30))
    moving = Grid((9, 8, 4), (0.5, 1.5, 2.5), (-4, 0, 2), oblique_direction(10, 0, 0))
    m = params_to_matrix([3, -2, 1, 5, -3, 10], fixed.center())
    theta = normalized_theta(torch.tensor(m)[None], fixed, moving, array_order)[0].numpy()
    # a fixed corner in normalized coordinates -> index -> physical -> T -> moving index -> normalized
    for idx in [(0, 0, 0), (4, 5, 6), (2, 0, 6)]:
        idx = np.array(idx, float)
        norm_f = 2 * idx / (np.array(fixed.size) - 1) - 1
        norm_f = norm_f[::-1] if array_order == "xyz" else norm_f  # torch grid order is last-axis-first
        moving_idx = (moving.physical_to_index() @ m @ fixed.index_to_physical() @ [*idx, 1])[:3]
        norm_m = 2 * moving_idx / (np.array(moving.size) - 1) - 1
        norm_m = norm_m[::-1] if array_order == "xyz" else norm_m
        np.testing.assert_allclose(theta @ [*norm_f, 1], norm_m, atol=1e-9)


def test_tre_and_parameter_errors():
    c = np.array([10.0, -5.0, 3.0])
    t_true = params_to_matrix([1, 2, 3, 4, 5, 6], c)
    assert target_registration_error(t_true, t_true, RNG.uniform(-50, 50, (100, 3))) == pytest.approx(0.0, abs=1e-12)
    # a pure 3-4-0 mm translation error gives TRE 5 mm everywhere
    t_pred = params_to_matrix([4, 6, 3, 4, 5, 6], c)
    pts = RNG.uniform(-50, 50, (100, 3))
    assert target_registration_error(t_pred, t_true, pts) == pytest.approx(5.0)
    assert target_registration_error([4, 6, 3, 4, 5, 6], [1, 2, 3, 4, 5, 6], pts, center=c) == pytest.approx(5.0)
    # a 1 degree rotation error about z through c: point at distance r from the axis moves 2 r sin(0.5 deg)
    d = target_registration_error(params_to_sitk([0, 0, 0, 0, 0, 1], c), np.eye(4), [c + [100, 0, 0]])
    assert d == pytest.approx(2 * 100 * np.sin(np.deg2rad(0.5)))
    # TRE from a mask image
    mask = sitk.Image(8, 8, 8, sitk.sitkUInt8)
    mask[2:4, 2:4, 2:4] = 1
    assert target_registration_error(t_pred, t_true, mask) == pytest.approx(5.0)
    err = parameter_errors([[1, 2, 3, 179, 0, -1]], [[0, 2, 5, -179, 0, 1]])
    np.testing.assert_allclose(err, [[1, 0, 2, 2, 0, 2]], atol=1e-12)


def test_mask_points_are_the_physical_points_of_the_mask_voxels():
    """mask_points reads SimpleITK's [z, y, x] array: each non-zero voxel (i, j, k) gives its own LPS point (a
    non-cubic, anisotropic, oblique mask, so an x/z swap or a missing direction shows), and a rotation's TRE over
    the mask is the TRE over those points."""
    mask = sitk.Image(5, 6, 7, sitk.sitkUInt8)
    mask.SetSpacing((1.0, 2.0, 3.0))
    mask.SetOrigin((10.0, -20.0, 30.0))
    mask.SetDirection(oblique_direction(10.0, -20.0, 30.0))
    voxels = [(0, 1, 2), (4, 0, 6), (1, 5, 3), (3, 2, 0)]  # ITK index order (i, j, k) = (x, y, z)
    for v in voxels:
        mask[v] = 1
    expected = np.array([mask.TransformIndexToPhysicalPoint(v) for v in voxels])
    found = mask_points(mask)
    assert found.shape == (4, 3)
    np.testing.assert_allclose(found[np.lexsort(found.T)], expected[np.lexsort(expected.T)], atol=1e-9)
    c = Grid.from_sitk(mask).center()
    t_pred, t_true = params_to_matrix([0, 0, 0, 20, -10, 30], c), np.eye(4)
    assert target_registration_error(t_pred, t_true, mask) == pytest.approx(
        target_registration_error(t_pred, t_true, expected), rel=1e-12)


def test_worked_examples_3_5_6_7_of_the_conventions_page_exactly():
    """The numbers of docs/conventions.md examples 3 (re-centring), 5 (LPS/RAS), 6 (torch theta) and 7 (wrap)."""
    np.testing.assert_allclose(recenter_params([5, 0, 0, 10, 0, 0], (0, 0, 0), (0, 10, 0)),
                               [5, -0.1519, 1.7365, 10, 0, 0], atol=1e-4)
    lps = np.array([10.0, 20.0, 30.0, 1.0])
    flip = lps_to_ras_affine(np.eye(4))
    np.testing.assert_allclose(flip @ lps, [-10, -20, 30, 1])
    np.testing.assert_allclose(ras_to_lps_affine(flip), np.eye(4))
    grid = Grid((4, 4, 4), (2.0, 2.0, 2.0), (-3.0, -3.0, -3.0))
    m = torch.tensor(params_to_matrix([2, 0, 0, 0, 0, 0], grid.center()))[None]
    np.testing.assert_allclose(normalized_theta(m, grid, grid)[0].numpy(),
                               [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2 / 3]], atol=1e-12)
    np.testing.assert_allclose(normalized_theta(m, grid, grid, array_order="zyx")[0].numpy(),
                               [[1, 0, 0, 2 / 3], [0, 1, 0, 0], [0, 0, 1, 0]], atol=1e-12)
    np.testing.assert_allclose(parameter_errors([1, 2, 3, 179, 0, -1], [0, 2, 5, -179, 0, 1]), [1, 0, 2, 2, 0, 2])


def test_grid_corners_are_the_corner_voxel_centres():
    # oblique, anisotropic, off the origin: the first corner is the origin, the last index (size - 1) mapped by the
    # direction and spacing, and the bounding box of physical_extent is theirs
    direction = rotation_matrix(*np.deg2rad([10.0, -20.0, 35.0]))
    grid = Grid((5, 7, 3), (1.5, 2.0, 3.0), (10.0, -4.0, 2.5), tuple(direction.ravel()))
    corners = grid.corners()
    assert corners.shape == (8, 3)
    np.testing.assert_allclose(corners[0], grid.origin)
    np.testing.assert_allclose(corners[-1], np.asarray(grid.origin) + direction @ (np.array([4.0, 6.0, 2.0])
                                                                                 * [1.5, 2.0, 3.0]))
    np.testing.assert_allclose(corners[1], np.asarray(grid.origin) + direction @ [0.0, 0.0, 6.0])  # last axis first
    lo, hi = grid.physical_extent()
    np.testing.assert_allclose(lo, corners.min(0))
    np.testing.assert_allclose(hi, corners.max(0))


def test_index_to_normalized_inverts_the_map_of_normalized_theta():
    # the grid's first voxel is -1 and its last +1 along every axis, the tensor's last axis first (xyz layout: the
    # first component addresses index axis k); a one-voxel axis's voxel is -1, as normalized_theta maps it
    from monai_rigidreg.core.geometry import index_to_normalized

    m = index_to_normalized((5, 9, 3), "xyz")
    np.testing.assert_allclose(m @ [0, 0, 0, 1], [-1, -1, -1, 1])
    np.testing.assert_allclose(m @ [4, 8, 2, 1], [1, 1, 1, 1])
    np.testing.assert_allclose(m @ [2, 0, 1, 1], [0, -1, 0, 1])  # (k, j, i) order: k = 1 of 0..2 is the middle
    np.testing.assert_allclose(index_to_normalized((5, 9, 1), "xyz") @ [0, 0, 0, 1], [-1, -1, -1, 1])
    np.testing.assert_allclose(index_to_normalized((5, 9, 3), "zyx") @ [4, 0, 0, 1], [1, -1, -1, 1])
