"""Tests of monai_rigidreg.simulation.clinical: clinical-geometry pairs (isocentre off the CT centre, large setup
errors, local deformations, target-region landmarks) on a small synthetic planning CT (not the real CTs).

The ground truth is checked end to end: the CBCT warped back by the true transform reproduces the CT inside the
field of view (a flipped translation or swapped axes do not), and a dense bead near the isocentre appears in the
CBCT where the landmark ground truth ``T(phi(x))`` says. All volumes are tiny (CBCT <= 32^3 at 4 mm, 60 views).
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from monai_rigidreg.core.geometry import Grid, params_to_matrix, params_to_sitk, recenter_params, transform_points
from monai_rigidreg.simulation import CBCTPhysics
from monai_rigidreg.simulation.clinical import (
    ClinicalCBCTSpec,
    ClinicalGroup,
    SmoothDeformation,
    best_rigid_fit,
    case_seed,
    inside_mask,
    load_clinical_case,
    load_planning_ct,
    make_clinical_case,
    roi_landmarks,
    sample_deformation,
    sample_isocenter,
    sample_motion,
    save_clinical_case,
    simulate_clinical_cbct,
    tre_points,
)

CENTER = np.array([12.0, -20.0, 30.0])  # the CT centre is not the origin
BEAD = np.array([20.0, -5.0, 4.0])  # offset of a dense bead from the CT centre, mm
SPEC = ClinicalCBCTSpec(size=(32, 32, 24), spacing=4.0, views=60, physics=CBCTPhysics.ideal(), extension_mm=40.0)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _synthetic_ct() -> sitk.Image:
    """64 x 64 x 50 voxels at 4 mm (HU): an elliptic body cylinder along z with lung-like, soft and bone blobs and
    a dense bead; asymmetric in every axis. Centre ``CENTER``."""
    grid = Grid.centered((64, 64, 50), (4.0, 4.0, 4.0), CENTER)
    xs, ys, zs = (o + s * np.arange(n) for o, s, n in zip(grid.origin, grid.spacing, grid.size))
    z, y, x = np.meshgrid(zs - CENTER[2], ys - CENTER[1], xs - CENTER[0], indexing="ij")
    hu = np.full(x.shape, -1000.0)
    body = (x / 100.0) ** 2 + (y / 80.0) ** 2 <= 1.0
    hu[body] = (20.0 + 10.0 * np.sin(x / 23.0) * np.cos(y / 17.0 + z / 29.0))[body]
    rng = np.random.default_rng(3)
    for _ in range(40):
        c = np.array([rng.uniform(-80, 80), rng.uniform(-60, 60), rng.uniform(-90, 90)])
        r = rng.uniform(8, 22)
        blob = ((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 <= r * r) & body
        hu[blob] = float(rng.choice([-750.0, -100.0, 120.0, 600.0]))
    spine = ((x - 10.0) ** 2 + (y - 55.0) ** 2 <= 12.0**2) & (np.sin(z / 9.0) > -0.3)
    hu[spine] = 900.0
    bead = (x - BEAD[0]) ** 2 + (y - BEAD[1]) ** 2 + (z - BEAD[2]) ** 2 <= 9.0**2
    hu[bead] = 2500.0
    img = sitk.GetImageFromArray(hu.astype(np.float32))
    return grid.apply_to(img)


@pytest.fixture(scope="module")
def planning_ct():
    return load_planning_ct(_synthetic_ct(), name="synthetic")


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def _ncc_back(ct, cbct, fov, params, center) -> float:
    """NCC of the CT and the CBCT resampled onto it by ``params`` about ``center``, over the CT voxels the transform
    puts in the field of view."""
    tfm = params_to_sitk(params, center)
    back = sitk.GetArrayFromImage(sitk.Resample(cbct, ct.image, tfm, sitk.sitkLinear, -1000.0))
    mask = sitk.GetArrayFromImage(sitk.Resample(fov, ct.image, tfm, sitk.sitkNearestNeighbor, 0)) > 0
    assert mask.sum() > 2000
    return _ncc(sitk.GetArrayFromImage(ct.image)[mask], back[mask])


def test_ground_truth_warps_the_cbct_back_onto_the_ct(planning_ct):
    ct = planning_ct
    p = ct.center + np.array([-30.0, 25.0, 8.0])  # the isocentre, off the CT centre
    motion = np.array([18.0, -11.0, 9.0, 6.0, -9.0, 14.0])  # about the isocentre
    cbct, fov, info = simulate_clinical_cbct(ct, p, motion, spec=SPEC, seed=0)
    # the CBCT is centred on the isocentre, on the spec's grid
    assert np.allclose(Grid.from_sitk(cbct).center(), p)
    assert cbct.GetSize() == SPEC.size and Grid.from_sitk(fov) == Grid.from_sitk(cbct)
    # the same transform about the CT centre (the project's convention for the ground truth) maps alike
    truth_c = recenter_params(motion, p, ct.center)
    assert np.allclose(params_to_matrix(truth_c, ct.center), params_to_matrix(motion, p))
    good = _ncc_back(ct, cbct, fov, truth_c, ct.center)
    assert good > 0.9, good
    flipped = np.concatenate([-motion[:3], motion[3:]])
    swapped = motion[[1, 0, 2, 4, 3, 5]]
    for wrong in (flipped, swapped, np.zeros(6)):
        bad = _ncc_back(ct, cbct, fov, wrong, p)
        assert bad < good - 0.2, (wrong, bad, good)


def test_image_quality_ncc_reads_the_truth_and_the_record_gives_the_exposure(planning_ct):
    """``bench_clinical_image_quality``'s NCC: the CT under the true motion matches the (ideal) CBCT, under the
    inverse motion or the identity it does not; the record gives the ray through the isocentre and the photons."""
    from benchmarks.simulation.bench_clinical_image_quality import truth_ncc

    ct = planning_ct
    p = ct.center + np.array([-20.0, 10.0, 5.0])
    motion = np.array([15.0, -10.0, 6.0, 8.0, -6.0, 12.0])
    cbct, fov, info = simulate_clinical_cbct(ct, p, motion, spec=SPEC, seed=0)
    m = params_to_matrix(motion, p)
    image = sitk.Cast(ct.image, sitk.sitkFloat32)
    right = truth_ncc(image, cbct, fov, m)
    assert right > 0.9
    assert truth_ncc(image, cbct, fov, np.linalg.inv(m)) < right - 0.3
    assert truth_ncc(image, cbct, fov, np.eye(4)) < right - 0.3
    # the body is an ellipse of 200 x 160 mm: between about 160 and 200 mm of soft tissue through the isocentre
    assert 0.02 * 140 < info["centre_line_integral"] < 0.02 * 260
    assert info["photons"] is None  # ideal physics: no quantum noise


def test_isocenter_and_motion_sampling(planning_ct):
    ct = planning_ct
    rng = np.random.default_rng(0)
    z0, z1 = ct.z_range()
    for _ in range(10):
        p, d = sample_isocenter(ct, rng, (40.0, 60.0), min_depth_mm=8.0, cbct_length_mm=SPEC.length_mm)
        assert 40.0 <= d <= 60.0 and np.isclose(np.linalg.norm(p - ct.center), d)
        assert inside_mask(ct.body, p[None])[0]
        assert z0 <= p[2] - SPEC.length_mm / 2 and p[2] + SPEC.length_mm / 2 <= z1
    for _ in range(20):
        m = sample_motion(rng, (40.0, 60.0), 45.0, 30.0)
        assert 40.0 <= np.linalg.norm(m[:3]) <= 60.0
        assert np.all(np.abs(m[3:]) <= 45.0) and np.abs(m[3:]).max() >= 30.0
    # deterministic
    a = sample_isocenter(ct, np.random.default_rng(5), (0.0, 50.0))
    b = sample_isocenter(ct, np.random.default_rng(5), (0.0, 50.0))
    assert np.array_equal(a[0], b[0])
    assert case_seed(1, "ct", "small", 0) == case_seed(1, "ct", "small", 0) != case_seed(1, "ct", "small", 1)


def test_deformation_magnitude_support_and_inverse():
    rng = np.random.default_rng(1)
    near = np.array([5.0, -3.0, 20.0])
    for peak in (5.0, 15.0):
        d = sample_deformation(rng, near, peak)
        assert d.peak() == pytest.approx(peak, rel=1e-3)
        assert d.lipschitz_bound() <= 0.7
        # zero beyond the bumps' supports
        reach = max(np.linalg.norm(np.asarray(c) - near) + r for c, r in zip(d.centers, d.radii))
        far = near + (reach + 1.0) * np.array([[1, 0, 0], [0, -1, 0], [0, 0, 1], [0.6, 0.8, 0]])
        assert np.all(d.displacement(far) == 0.0)
        # phi inverts y -> y - v(y); its displacement has the same peak
        axes = [np.arange(-90.0, 91.0, 6.0) + near[k] for k in range(3)]
        x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        y = d.forward(x)
        assert np.allclose(y - d.displacement(y), x, atol=1e-5)
        assert np.linalg.norm(y - x, axis=1).max() <= peak + 1e-6
        assert np.linalg.norm(y - x, axis=1).max() > 0.8 * peak
    # the torch twin
    pts = torch.tensor([[5.0, 0.0, 20.0], [40.0, -30.0, 10.0]], dtype=torch.float64)
    assert np.allclose(d.displacement_torch(pts).numpy(), d.displacement(pts.numpy()))
    assert SmoothDeformation.from_dict(d.to_dict()) == d


def test_landmark_ground_truth_follows_the_anatomy(planning_ct):
    """A dense bead inside a deformed region shows up in the CBCT at ``T(phi(bead))``, not at ``T(bead)``."""
    ct = planning_ct
    bead = ct.center + BEAD
    p = ct.center + np.array([10.0, 0.0, 0.0])
    deformation = SmoothDeformation(((bead + [5.0, 5.0, 0.0]).tolist(),), (70.0,), ((7.0, -6.0, 5.0),))
    motion = np.array([12.0, 8.0, -6.0, 8.0, -5.0, 10.0])
    cbct, fov, _ = simulate_clinical_cbct(ct, p, motion, deformation, spec=SPEC, seed=0)
    arr = sitk.GetArrayFromImage(cbct)
    zyx = np.argwhere(arr > 1500.0)
    w = arr[arr > 1500.0] - 1500.0
    found = (transform_points(Grid.from_sitk(cbct).index_to_physical(), zyx[:, ::-1].astype(float)) * w[:, None]).sum(0)
    found /= w.sum()
    m = params_to_matrix(motion, p)
    expected = transform_points(m, deformation.forward(bead[None]))[0]
    rigid_only = transform_points(m, bead[None])[0]
    assert np.linalg.norm(expected - rigid_only) > 8.0
    assert np.linalg.norm(found - expected) < 1.5, (found, expected)


def test_make_clinical_case_records_a_consistent_truth(planning_ct, tmp_path):
    ct = planning_ct
    group = ClinicalGroup("t", (10.0, 20.0), 10.0, isocenter_distance_mm=(20.0, 40.0), deformation_mm=(6.0, 8.0))
    case = make_clinical_case(ct, group, seed=7, spec=SPEC, roi_box_mm=60.0, num_landmarks=50, min_depth_mm=8.0)
    r = case.record
    p, c = np.asarray(r["isocenter"]), np.asarray(r["center"])
    assert np.allclose(c, ct.center) and 20.0 <= r["isocenter_distance_mm"] <= 40.0
    assert np.isclose(np.linalg.norm(p - c), r["isocenter_distance_mm"])
    assert 10.0 <= np.linalg.norm(r["params_isocenter"][:3]) <= 20.0
    assert np.allclose(params_to_matrix(r["params"], c), r["matrix"])
    assert np.allclose(params_to_matrix(r["params_isocenter"], p), r["matrix"])
    assert 6.0 <= r["deformation_peak_mm"] <= 8.0
    lm, lm_true = np.asarray(r["landmarks"]), np.asarray(r["landmarks_moving"])
    assert 10 <= len(lm) <= 50
    assert np.all(np.abs(lm - p) <= 30.0 + 1e-6) and inside_mask(ct.body, lm).all()
    assert inside_mask(case.fov, lm_true).all()
    d = SmoothDeformation.from_dict(r["deformation"])
    assert np.allclose(lm_true, transform_points(np.asarray(r["matrix"]), d.forward(lm)))
    # the floor: the best rigid fit of the landmarks, below the setup error's own residual
    rigid_residual = np.linalg.norm(transform_points(np.asarray(r["matrix"]), lm) - lm_true, axis=1).mean()
    assert 0.0 < r["rigid_floor_mm"] <= rigid_residual
    # where TRE is measured: body points whose true position is in the field of view
    pts = tre_points(ct, case.matrix, case.fov)
    assert len(pts) > 100 and inside_mask(case.fov, transform_points(case.matrix, pts)).all()
    # written and read back (int16 HU); an unfinished folder reads as None
    record = save_clinical_case(case, tmp_path / "case", fixed="ct.nii.gz")
    back = load_clinical_case(tmp_path / "case")
    assert back.record == record and record["moving"] == "cbct.nii.gz" and record["fixed"].endswith("ct.nii.gz")
    g_back, g = Grid.from_sitk(back.cbct), Grid.from_sitk(case.cbct)
    assert g_back.size == g.size and np.allclose(g_back.origin, g.origin, atol=1e-4)  # NIfTI: float32 origin
    diff = sitk.GetArrayFromImage(back.cbct) - sitk.GetArrayFromImage(case.cbct)
    assert np.abs(diff).max() <= 0.5 + 1e-3
    assert np.array_equal(sitk.GetArrayFromImage(back.fov), sitk.GetArrayFromImage(case.fov))
    assert load_clinical_case(tmp_path / "nothing") is None


def test_best_rigid_fit_and_roi_landmarks(planning_ct):
    rng = np.random.default_rng(2)
    src = rng.normal(size=(30, 3)) * 20.0
    m = params_to_matrix([4.0, -2.0, 7.0, 10.0, -20.0, 35.0], [1.0, 2.0, 3.0])
    fit, residual = best_rigid_fit(src, transform_points(m, src))
    assert np.allclose(fit, m, atol=1e-9) and residual < 1e-9
    pts = roi_landmarks(planning_ct, planning_ct.center, 50.0, 40, seed=0)
    assert len(pts) == 40 and np.all(np.abs(pts - planning_ct.center) <= 25.0 + 1e-6)
    assert np.array_equal(pts, roi_landmarks(planning_ct, planning_ct.center, 50.0, 40, seed=0))
