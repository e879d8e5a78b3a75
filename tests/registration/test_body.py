"""Body mask, couch mask and couch exclusion (monai_rigidreg.registration.body) and the couch of the simulation
(monai_rigidreg.simulation.couch), on small synthetic torsos built here and on the real abdomen CT."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
import SimpleITK as sitk

from monai_rigidreg.io.shared_data import find_data_file
from monai_rigidreg.registration.body import body_mask, couch_mask, exclude_outside_body
from monai_rigidreg.simulation.couch import (
    COUCH_LABELS,
    Couch,
    add_couch,
    couch_fractions,
    couch_labels,
    place_couch,
)

TISSUE_HU, LUNG_HU, BONE_HU, AIR_HU = 40.0, -850.0, 700.0, -1000.0
SEMI_X, SEMI_Y = 120.0, 80.0  # torso half-width (LPS x, left-right) and half-depth (y, anterior-posterior), mm
REAL_CT = "abdomen_pelvis_totalsegmentator_example_ct.nii.gz"


def physical_xyz(image: sitk.Image) -> np.ndarray:
    """LPS coordinates (mm) of every voxel centre, ``[z, y, x, 3]``: origin + direction @ (spacing * index)."""
    size = image.GetSize()
    idx = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in size[::-1]], indexing="ij")[::-1], axis=-1)
    direction = np.array(image.GetDirection()).reshape(3, 3)
    return (idx * np.array(image.GetSpacing())) @ direction.T + np.array(image.GetOrigin())


def torso(
    size=(96, 96, 48), spacing=(3.0, 3.0, 3.0), direction=np.eye(3), center=(0.0, 0.0, 0.0), semi_z=None,
    seed=0, pixel=sitk.sitkFloat32,
) -> tuple[sitk.Image, np.ndarray, np.ndarray]:
    """``(image, body, lungs)``: an elliptic torso (soft tissue, two lungs, a spine) in air, noise 20 HU.

    The torso is an elliptic cylinder along LPS z (a line of contact with a couch), or an ellipsoid of z half-length
    ``semi_z`` (a point of contact), its lungs scaled with it. The lungs run through the whole image along z, so in
    3D they are open to the image border (as through a trachea) and only slice-wise hole filling keeps them.
    ``body`` and ``lungs`` are the truth, boolean ``[z, y, x]`` arrays.
    """
    img = sitk.Image([int(n) for n in size], sitk.sitkFloat32)
    img.SetSpacing(spacing)
    d = np.asarray(direction, dtype=float)
    img.SetDirection(tuple(d.ravel()))
    img.SetOrigin(tuple(np.asarray(center) - d @ ((np.array(size) - 1) / 2 * np.array(spacing))))
    p = physical_xyz(img) - np.asarray(center)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    f = 1.0 if semi_z is None else np.sqrt(np.clip(1.0 - (z / semi_z) ** 2, 0.0, None))  # cross-section scale
    body = (x / SEMI_X) ** 2 + (y / SEMI_Y) ** 2 <= f**2
    lungs = np.zeros_like(body)
    for side in (-1, 1):  # 36 mm of chest wall laterally (times f)
        dx, dy = x - side * 0.42 * SEMI_X * f, y + 0.1 * SEMI_Y * f
        lungs |= (dx / (0.3 * SEMI_X)) ** 2 + (dy / (0.5 * SEMI_Y)) ** 2 <= f**2
    lungs &= body
    hu = np.where(body, TISSUE_HU, AIR_HU)
    hu[lungs] = LUNG_HU
    hu[body & (x**2 + (y - 0.55 * SEMI_Y) ** 2 <= 15.0**2)] = BONE_HU  # spine, posterior (LPS +y)
    hu += np.random.default_rng(seed).normal(0.0, 20.0, hu.shape)
    out = sitk.Cast(sitk.GetImageFromArray(hu.astype(np.float32)), pixel)
    out.CopyInformation(img)
    return out, body, lungs


def dice(a: np.ndarray, b: np.ndarray) -> float:
    return 2.0 * float((a & b).sum()) / float(a.sum() + b.sum())


def arr(image: sitk.Image) -> np.ndarray:
    return sitk.GetArrayFromImage(image)


def high_hu_couch(image: sitk.Image, couch: Couch) -> np.ndarray:
    """Truth: voxels mostly covered by the couch whose value is above the body threshold (the shells, the rails and
    the voxels a shell shares with the foam core)."""
    return (arr(couch_labels(image, couch)) > 0) & (arr(image) > -400.0)


def test_physical_xyz_matches_simpleitk():
    img, _, _ = torso(size=(9, 8, 7), spacing=(1.5, 2.0, 2.5), direction=np.array([[0, 0, 1], [-1, 0, 0], [0, 1, 0]]),
                      center=(5.0, -7.0, 20.0))
    pts = physical_xyz(img)
    for ijk in [(0, 0, 0), (8, 0, 3), (2, 7, 6)]:
        np.testing.assert_allclose(pts[ijk[2], ijk[1], ijk[0]], img.TransformIndexToPhysicalPoint(ijk), atol=1e-9)


@pytest.mark.parametrize("radius", [[1, 1, 1], [2, 2, 2], [1, 2, 3], [3, 1, 2]])
@pytest.mark.parametrize("kind", ["noise", "blobs"])
def test_ball_morphology_equals_itk(radius, kind):
    """body_mask's numpy ball filters give ITK's binary opening (outside counts as foreground for the erosion),
    closing with a safe border and dilation voxel for voxel, on masks that touch the image border, with anisotropic
    radii (a transposed kernel or a wrong border rule changes voxels)."""
    import torch
    import torch.nn.functional as F

    from monai_rigidreg.registration.body import _ball_filter, _closing, _opening

    rng = np.random.default_rng(sum(radius) + len(kind))
    shape = (17, 21, 26)
    noise = rng.random(shape)
    if kind == "blobs":  # noise smoothed by a 5-voxel box: blobs a few voxels wide
        smooth = F.avg_pool3d(torch.from_numpy(noise)[None, None], 5, 1, 2, count_include_pad=False)[0, 0].numpy()
        arr = smooth > 0.5
    else:
        arr = noise > 0.4
    arr[:2] = True
    arr[:, :, -1] = True
    img = sitk.GetImageFromArray(arr.astype(np.uint8))
    ball = sitk.sitkBall
    opened = sitk.BinaryMorphologicalOpening(img, kernelRadius=radius, kernelType=ball, foregroundValue=1)
    closed = sitk.BinaryMorphologicalClosing(img, kernelRadius=radius, kernelType=ball, foregroundValue=1,
                                             safeBorder=True)
    sparse = rng.random(shape) > 0.995  # dilated, the dense masks fill the whole image
    sparse[:, -1] = True
    dilated = sitk.BinaryDilate(sitk.GetImageFromArray(sparse.astype(np.uint8)), kernelRadius=radius,
                                kernelType=ball, backgroundValue=0, foregroundValue=1)
    for ours, itk in ((_opening(arr, radius), opened), (_closing(arr, radius), closed),
                      (_ball_filter(sparse, radius, True, False), dilated)):
        ref = sitk.GetArrayFromImage(itk) != 0
        assert 0 < ref.sum() < ref.size
        np.testing.assert_array_equal(ours, ref)


def test_body_mask_keeps_lungs_and_drops_a_separate_couch():
    img, body, lungs = torso()
    couch = place_couch(img, gap_mm=10.0)
    ct = add_couch(img, couch)
    hi = high_hu_couch(ct, couch)
    mask = arr(body_mask(ct)).astype(bool)
    assert body_mask(ct).GetPixelID() == sitk.sitkUInt8
    assert hi.sum() > 5000  # the couch is there: two shells and two rails across the image
    assert dice(mask, body) > 0.99
    assert mask[lungs].all()  # the lungs (open to the image's z border) are filled slice by slice
    assert not mask[hi].any()
    assert not mask[arr(couch_labels(ct, couch)) > 0].any()


@pytest.mark.parametrize("gap_mm", [0.0, 1.0, 2.0])
def test_body_mask_excludes_a_couch_touching_the_body_at_a_point(gap_mm):
    img, body, lungs = torso(semi_z=150.0)  # an ellipsoid: the most posterior point touches the couch
    couch = place_couch(img, gap_mm=gap_mm)
    ct = add_couch(img, couch)
    hi = high_hu_couch(ct, couch)
    mask = arr(body_mask(ct)).astype(bool)
    assert dice(mask, body) > 0.98
    assert mask[lungs].mean() > 0.999
    assert mask[hi].mean() < (0.1 if gap_mm == 0 else 0.02), "couch shell in the body mask"  # measured 0.07, 0.004


@pytest.mark.parametrize("gap_mm", [0.0, 2.0])
def test_body_mask_with_a_couch_touching_along_a_line_keeps_only_the_contact_strip(gap_mm):
    """The worst case: a cylinder lying on the couch along its whole length. The opening cannot cut the couch shell
    right at the contact; what stays is a strip of the shell near the line of contact, nothing farther."""
    img, body, _ = torso()
    couch = place_couch(img, gap_mm=gap_mm)
    ct = add_couch(img, couch)
    hi = high_hu_couch(ct, couch)
    mask = arr(body_mask(ct)).astype(bool)
    assert dice(mask, body) > 0.98
    assert mask[hi].mean() < 0.2  # measured 0.16 (gap 0), 0.03 (gap 2)
    x = physical_xyz(ct)[..., 0]
    assert np.abs(x[mask & hi] - couch.center_x_mm).max() < 40.0  # only near the line of contact (x = centre)


def test_body_mask_on_a_fine_grid_is_computed_coarse_and_lands_on_the_input_grid():
    """A 2 mm grid whose size is no multiple of the 2x2x2 blocks of the 4 mm working grid: the mask comes back on the
    input grid (same geometry, no shift: its centroid is the truth's), and a given mask is dilated on the coarse grid
    by the margin to the margin plus two working voxels."""
    img, body, lungs = torso(size=(131, 97, 25), spacing=(2.0, 2.0, 2.0), semi_z=150.0, center=(3.0, -5.0, 7.0))
    couch = place_couch(img, gap_mm=2.0)
    ct = add_couch(img, couch)
    hi = high_hu_couch(ct, couch)
    mask_img = body_mask(ct)
    assert mask_img.GetSize() == ct.GetSize() and mask_img.GetOrigin() == ct.GetOrigin()
    assert mask_img.GetSpacing() == ct.GetSpacing() and mask_img.GetDirection() == ct.GetDirection()
    mask = arr(mask_img).astype(bool)
    assert dice(mask, body) > 0.98 and mask[lungs].mean() > 0.999 and mask[hi].mean() < 0.02
    pts = physical_xyz(ct)
    np.testing.assert_allclose(pts[mask].mean(axis=0), pts[body].mean(axis=0), atol=0.5)
    out = arr(exclude_outside_body(ct, mask_img, margin_mm=4.0))
    np.testing.assert_array_equal(out[body], arr(ct)[body])
    kept = out != -1000
    dist = sitk.GetArrayFromImage(sitk.SignedMaurerDistanceMap(mask_img, insideIsPositive=False, useImageSpacing=True,
                                                               squaredDistance=False))
    assert dist[~kept].min() > 4.0 - 1e-6  # everything within the margin is kept...
    assert dist[kept & ~mask].max() <= 4.0 + 2 * 4.0  # ...and nothing beyond the margin plus two working voxels


def test_body_mask_with_a_field_of_view_whose_outside_is_not_air():
    """Some CBCTs write 0 (water) outside the field of view: without ``fov`` the outside looks like one huge body;
    with it, the body is right and nothing outside the field of view is body."""
    img, body, _ = torso(semi_z=150.0)
    pts = physical_xyz(img)
    fov = np.hypot(pts[..., 0], pts[..., 1]) <= 110.0
    a = arr(img)
    a[~fov] = 0.0
    cbct = sitk.GetImageFromArray(a)
    cbct.CopyInformation(img)
    fov_img = sitk.GetImageFromArray(fov.astype(np.uint8))
    fov_img.CopyInformation(img)
    assert arr(body_mask(cbct)).astype(bool)[~fov].mean() > 0.9  # the trap
    mask = arr(body_mask(cbct, fov=fov_img)).astype(bool)
    assert not mask[~fov].any() and dice(mask, body & fov) > 0.98


def test_couch_mask_finds_the_couch_and_none_of_the_body():
    img, body, _ = torso(semi_z=150.0)
    couch = place_couch(img, gap_mm=2.0)
    ct = add_couch(img, couch)
    hi = high_hu_couch(ct, couch)
    found = arr(couch_mask(ct)).astype(bool)
    assert found[hi].mean() > 0.9
    assert not found[body].any()
    assert couch_mask(ct).GetPixelID() == sitk.sitkUInt8
    # far from the body (more than 10 mm), every high-HU couch voxel is found
    y = physical_xyz(ct)[..., 1]
    far = hi & (y > y[body].max() + 10.0)
    assert far.sum() > 1000 and found[far].all()


@pytest.mark.parametrize("pixel", [sitk.sitkFloat32, sitk.sitkInt16])
def test_exclude_outside_body_keeps_the_body_and_blanks_the_couch(pixel):
    img, body, _ = torso(semi_z=150.0)
    couch = place_couch(img, gap_mm=2.0)
    ct = sitk.Cast(add_couch(img, couch), pixel)
    hi = high_hu_couch(ct, couch)
    out = exclude_outside_body(ct)
    assert out.GetPixelID() == pixel
    assert out.GetSpacing() == ct.GetSpacing() and out.GetDirection() == ct.GetDirection()
    before, after = arr(ct), arr(out)
    np.testing.assert_array_equal(after[body], before[body])
    assert (after[hi] == -1000).mean() > 0.95
    # what stays of the couch is next to the body (the margin), and the rest of the outside is air
    y = physical_xyz(ct)[..., 1]
    assert y[hi & (after != -1000)].min() >= y[body].max() - 1e-6
    assert (after[hi & (y > y[body].max() + 10.0)] == -1000).all()
    # a given body mask is used as such (dilated by the margin)
    given = exclude_outside_body(ct, body_mask(ct), margin_mm=4.0)
    assert (arr(given)[hi] == -1000).mean() > 0.9
    np.testing.assert_array_equal(arr(given)[body], before[body])


@pytest.mark.parametrize(
    "direction",
    [np.diag([-1.0, -1.0, 1.0]), np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
     np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])],
    ids=["flipped-xy", "x-y-swapped", "sagittal-stack"],
)
def test_couch_lands_posterior_to_the_body_in_physical_space(direction):
    """On a grid whose index axes are flipped or permuted against LPS, the couch is still a plate under the patient's
    back: at larger LPS y than every body voxel, wide along LPS x, thin along y, along the whole z extent, its curved
    edges rising anteriorly (-y). Placing it along an index axis, or at -y, fails these checks."""
    size = np.array([90, 70, 40])[np.argmax(np.abs(direction), axis=0)]  # LPS extents 270 x 210 x 120 mm at 3 mm
    img, body, lungs = torso(size=tuple(int(n) for n in size), direction=direction, center=(30.0, -50.0, 400.0))
    pts = physical_xyz(img)
    x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
    flat = place_couch(img, gap_mm=3.0, rail_width_mm=0.0, core_mm=4.0, curvature_radius_mm=None)
    ct = add_couch(img, flat)
    plate = arr(couch_labels(ct, flat)) > 0
    assert plate.sum() > 1000
    assert flat.top_y_mm == pytest.approx(y[body].max() + 3.0)  # posterior (+y) of the back, gap 3 mm
    assert flat.top_y_mm - 1.5 <= y[plate].min() <= flat.top_y_mm + 3.0 + 1.5  # top shell 3 mm, voxels 3 mm
    changed = np.abs(arr(ct) - arr(img)) > 1e-3
    assert y[changed].min() > y[body].max()  # nothing painted into the patient
    assert abs(np.median(x[plate]) - 30.0) < 3.0  # centred under the body
    assert np.ptp(x[plate]) > 250.0 and np.ptp(y[plate]) < 15.0  # a plate across x (the whole image), thin along y
    assert np.isclose(np.ptp(z[plate]), np.ptp(z), atol=1e-6)  # along the whole scan length
    curved = place_couch(img, gap_mm=3.0, rail_width_mm=0.0, curvature_radius_mm=500.0)
    shell = arr(couch_labels(img, curved)) == COUCH_LABELS["shell"]
    centre, edge = shell & (np.abs(x - 30.0) < 10.0), shell & (np.abs(x - 30.0) > 120.0)
    assert y[edge].min() < y[centre].min() - 10.0  # the edges rise toward anterior (-y)
    mask = arr(body_mask(ct)).astype(bool)  # slice-wise hole filling across the index axis closest to LPS z
    assert dice(mask, body) > 0.98 and mask[lungs].mean() > 0.999
    assert mask[plate].mean() < 0.05  # only the strip along the line of contact (a cylinder on a flat plate)


def test_body_mask_of_a_truncated_cbct_field_of_view():
    """A CBCT-like image: a cylindrical field of view of radius 110 mm cuts the 240 mm wide torso; outside it the
    reconstruction is -1000 HU, and its edge carries a bright truncation ring. The couch is reconstructed only inside
    the field of view. (The lungs stay 24 mm inside the edge: a lung cut by the edge is not a hole in that slice.)"""
    img, body, lungs = torso(semi_z=150.0)
    pts = physical_xyz(img)
    rho = np.hypot(pts[..., 0], pts[..., 1])
    fov = rho <= 110.0
    fov_img = sitk.GetImageFromArray(fov.astype(np.uint8))
    fov_img.CopyInformation(img)
    couch = place_couch(img, gap_mm=2.0)
    cbct = add_couch(img, couch, fov=fov_img)
    a = arr(cbct)
    a[(rho > 107.0) & fov] += 300.0  # truncation ring (3 mm)
    a[~fov] = -1000.0
    cbct = sitk.GetImageFromArray(a)
    cbct.CopyInformation(img)
    mask_img = body_mask(cbct)
    mask = arr(mask_img).astype(bool)
    cc = sitk.ConnectedComponentImageFilter()
    cc.Execute(mask_img)
    assert cc.GetObjectCount() == 1
    assert not mask[~fov].any()
    assert dice(mask, body & fov) > 0.97
    assert mask[lungs].mean() > 0.999
    hi = high_hu_couch(cbct, couch) & fov
    assert hi.sum() > 300 and mask[hi].mean() < 0.02
    ring_outside_body = (rho > 107.0) & fov & ~body
    assert mask[ring_outside_body].mean() < 0.05


def test_static_couch_pair_patient_moved():
    """The pair of issue 15: the patient moves by d between CT and CBCT, the couch stays. After exclusion the two
    images differ by the patient's motion only: the body masks' centroids shift by d, and the couch is gone."""
    ct_patient, body, _ = torso(semi_z=150.0)
    d = np.array([6.0, -9.0, 0.0])  # mm; anterior (-y): the patient stays above the couch; z: see the centroid
    moved = sitk.Resample(ct_patient, ct_patient, sitk.TranslationTransform(3, tuple(-d)), sitk.sitkLinear, AIR_HU)
    couch = place_couch(ct_patient, gap_mm=1.0)
    ct, cbct = add_couch(ct_patient, couch), add_couch(moved, couch)
    hi = high_hu_couch(ct, couch)
    y = physical_xyz(ct)[..., 1]
    full = np.broadcast_to(sum(couch_fractions(ct, couch).values()) > 0.999, hi.shape)  # wholly couch: no noise
    np.testing.assert_array_equal(arr(ct)[full], arr(cbct)[full])  # the couch did not move
    pts = physical_xyz(ct)
    m_ct, m_cb = arr(body_mask(ct)).astype(bool), arr(body_mask(cbct)).astype(bool)
    shift = pts[m_cb].mean(axis=0) - pts[m_ct].mean(axis=0)
    np.testing.assert_allclose(shift, d, atol=0.6)
    for image in (ct, cbct):
        assert (arr(exclude_outside_body(image))[hi & (y > y[body].max() + 6.0)] == -1000).all()


def test_place_couch_respects_the_gap_under_a_curved_top():
    img, body, _ = torso(semi_z=150.0)
    for gap in (0.0, 5.0):
        couch = place_couch(img, gap_mm=gap, curvature_radius_mm=400.0)
        pts = physical_xyz(img)[body & (arr(img) > -400)]
        clearance = (couch.top_y_mm - couch.rise(pts[:, 0])) - pts[:, 1]
        assert clearance.min() == pytest.approx(gap, abs=1e-6)
    assert place_couch(img, top_y_mm=123.0, center_x_mm=-4.0).top_y_mm == 123.0
    with pytest.raises(ValueError, match="gap"):
        place_couch(img, gap_mm=-1.0)
    with pytest.raises(ValueError, match="nothing"):
        place_couch(sitk.Image([8, 8, 8], sitk.sitkFloat32) - 1000.0)


def test_add_couch_hu_and_partial_volume():
    """A flat couch, exactly on voxel boundaries: shells at their HU, foam core at its HU, nothing else changed; half
    a voxel of shell blends half and half."""
    img = sitk.Image([40, 40, 4], sitk.sitkFloat32) - 1000.0
    img.SetSpacing((2.0, 2.0, 2.0))
    img.SetOrigin((-39.0, -39.0, 0.0))  # voxel centres at odd mm: voxel boundaries at even mm
    couch = Couch(top_y_mm=0.0, center_x_mm=0.0, width_mm=40.0, curvature_radius_mm=None, shell_mm=4.0,
                  shell_hu=500.0, core_mm=8.0, core_hu=-800.0, rail_width_mm=0.0)
    a = arr(add_couch(img, couch))
    col = a[0, :, 20]  # x = 1 mm; y of voxel j is -39 + 2 j
    y = -39.0 + 2.0 * np.arange(40)
    np.testing.assert_allclose(col[(y > 0) & (y < 4)], 500.0)
    np.testing.assert_allclose(col[(y > 4) & (y < 12)], -800.0)
    np.testing.assert_allclose(col[(y > 12) & (y < 16)], 500.0)
    np.testing.assert_allclose(col[(y < 0) | (y > 16)], -1000.0)
    shifted = add_couch(img, Couch(**{**couch.__dict__, "top_y_mm": 1.0}))  # shell now covers half of a voxel
    np.testing.assert_allclose(arr(shifted)[0, 20, 20], 0.5 * 500.0 + 0.5 * -1000.0)  # voxel y in [0, 2]


def test_empty_and_multi_component_images(caplog):
    air = sitk.Image([32, 32, 16], sitk.sitkInt16) - 1000
    with caplog.at_level(logging.WARNING):
        assert not arr(body_mask(air)).any()
        out = exclude_outside_body(air)
    assert "empty body mask" in caplog.text
    np.testing.assert_array_equal(arr(out), arr(air))
    # two separate legs: the largest only by default, both with min_component_fraction
    img, _, _ = torso(size=(64, 40, 16))
    pts = physical_xyz(img)
    legs = [(pts[..., 0] - s) ** 2 + pts[..., 1] ** 2 <= r**2 for s, r in ((-45.0, 30.0), (45.0, 27.0))]
    a = np.where(legs[0] | legs[1], TISSUE_HU, AIR_HU).astype(np.float32)
    two = sitk.GetImageFromArray(a)
    two.CopyInformation(img)
    one = arr(body_mask(two)).astype(bool)
    both = arr(body_mask(two, min_component_fraction=0.5)).astype(bool)
    assert dice(one, legs[0]) > 0.97 and not one[legs[1]].any()
    assert dice(both, legs[0] | legs[1]) > 0.97


def test_real_abdomen_ct_body_and_couch():
    """The TotalSegmentator abdomen CT (122x101x112 at 3 mm, direction diag(-1, -1, 1)) lies on a curved couch shell
    at the posterior border of the image. Its body is one component of 20-30 L, and the couch outside the patient's
    width (the posterior 24 mm of the image, more than 120 mm lateral of the centre: only couch there) is found and
    excluded."""
    path = find_data_file(REAL_CT)
    if path is None:
        pytest.skip(f"{REAL_CT} not found: set MONAI_RIGIDREG_DATA or place it in ../shared/data")
    ct = sitk.ReadImage(str(path))
    t0 = time.perf_counter()
    body_img = body_mask(ct)
    seconds = time.perf_counter() - t0
    body = arr(body_img).astype(bool)
    volume_l = body.sum() * np.prod(ct.GetSpacing()) / 1e6
    assert 20.0 < volume_l < 30.0, volume_l
    cc = sitk.ConnectedComponentImageFilter()
    cc.Execute(body_img)
    assert cc.GetObjectCount() == 1
    pts = physical_xyz(ct)
    x, y = pts[..., 0], pts[..., 1]
    hu = arr(ct)
    couch_region = (hu > -400) & (y > y.max() - 24.0) & (np.abs(x - x.mean()) > 120.0)
    assert couch_region.sum() > 3000
    assert not body[couch_region].any()
    assert arr(couch_mask(ct, body_img))[couch_region].mean() > 0.95
    assert (arr(exclude_outside_body(ct, body_img))[couch_region] == -1000).all()
    # the patient (anterior to the couch, within its width) is kept whole
    assert body[(hu > -400) & (y < y.max() - 60.0) & (np.abs(x - x.mean()) < 100.0)].mean() > 0.99
    assert seconds < 10.0


def test_body_mask_cache_keys_on_content_and_geometry_and_evicts_the_oldest():
    from monai_rigidreg.registration.body import BodyMaskCache, coarse_body_mask, image_key

    img, _, _ = torso()
    cache = BodyMaskCache(maxsize=1)
    first = cache(img)
    assert cache.hits == 0 and cache(img) is first and cache.hits == 1
    assert np.array_equal(arr(first), arr(coarse_body_mask(img)))
    moved = sitk.Image(img)
    moved.SetOrigin([o + 1.0 for o in img.GetOrigin()])  # same voxels elsewhere: another image
    assert image_key(moved) != image_key(img)
    assert cache(moved) is not first and cache.hits == 1
    assert cache(img) is not first and cache.hits == 1  # evicted by the second image (maxsize 1)
