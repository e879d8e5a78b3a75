"""Tests of monai_rigidreg.simulation: projector/FDK/FBP scaling, ground truth, physics, dataset generator, CLI.

All volumes are tiny (<= 48^3, <= 180 views) so the file runs in well under two minutes on one core.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import torch
from conftest import resampled_with_truth

from monai_rigidreg.core.errors import InputError, OutputExistsError
from monai_rigidreg.core.geometry import Grid, params_to_matrix, params_to_sitk, transform_points
from monai_rigidreg.simulation import (
    MU_WATER,
    CBCTPhysics,
    ConeBeamGeometry,
    FanBeamGeometry,
    cone_forward,
    fan_forward,
    fbp_fan,
    fdk,
    hu_to_mu,
    make_phantom,
    mu_to_hu,
    paper_cases,
    protocol_cases,
    random_phantom_shapes,
    save_volume_hu,
    shepp_logan_shapes,
    simulate_cbct,
    simulate_dataset,
)
from monai_rigidreg.simulation.projector import grid_axes

MU = 0.02  # 1/mm, about water
TINY = {  # dataset overrides: Sim-CT 32^3 at 8 mm, CBCT 24^3 at 10 mm, few views
    "simct_size": 32,
    "simct_spacing": 8.0,
    "cbct_size": 24,
    "cbct_spacing": 10.0,
    "simct_views": 90,
    "cbct_views": 60,
    "projection_spacing": 8.0,
    "supersample": 1,
}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _ball(grid: Grid, radius: float, mu: float = MU, center=(0.0, 0.0, 0.0)) -> torch.Tensor:
    xs, ys, zs = grid_axes(grid)
    x, y, z = torch.meshgrid(xs - center[0], ys - center[1], zs - center[2], indexing="ij")
    return ((x**2 + y**2 + z**2) <= radius**2).float() * mu


def _centre(vol: torch.Tensor, half: int = 2) -> torch.Tensor:
    c = [s // 2 for s in vol.shape]
    return vol[c[0] - half : c[0] + half, c[1] - half : c[1] + half, c[2] - half : c[2] + half]


def _data_dir() -> Path | None:
    env = os.environ.get("MONAI_RIGIDREG_DATA")
    for d in ([Path(env)] if env else []) + [Path(__file__).resolve().parents[3] / "shared" / "data"]:
        if (d / "abdomen_pelvis_totalsegmentator_example_ct.nii.gz").is_file():
            return d
    return None


# ----------------------------------------------------------------------------------------------------------------
# projector and reconstruction
# ----------------------------------------------------------------------------------------------------------------
def test_projection_geometry_convention():
    """Source on +x at view 0, on +y at view 1 (90 deg); detector u = (-sin b, cos b, 0), v = +z.

    A blob at p = (1, 21, 11) mm projects at view 0 to u = 21 sdd / (sod - 1), v = 11 sdd / (sod - 1) and at
    view 1 to u = -1 sdd / (sod - 21).
    """
    grid = Grid.centered((32, 32, 32), (2.0, 2.0, 2.0))
    vol = _ball(grid, 3.0, 1.0, center=(1.0, 21.0, 11.0))  # voxel centres are at odd mm
    geom = ConeBeamGeometry(num_views=4, detector_shape=(81, 41), pixel_pitch=(1.5, 1.5))
    proj = cone_forward(vol, grid, geom, "cpu").double()
    u, v = geom.u_coords(), geom.v_coords()

    def centroid(img):
        return float((img.sum(0) * u).sum() / img.sum()), float((img.sum(1) * v).sum() / img.sum())

    u0, v0 = centroid(proj[0])
    assert u0 == pytest.approx(21.0 * geom.sdd / (geom.sod - 1.0), abs=0.3)
    assert v0 == pytest.approx(11.0 * geom.sdd / (geom.sod - 1.0), abs=0.3)
    u1, v1 = centroid(proj[1])
    assert u1 == pytest.approx(-1.0 * geom.sdd / (geom.sod - 21.0), abs=0.3)
    assert v1 == pytest.approx(11.0 * geom.sdd / (geom.sod - 21.0), abs=0.3)


def _detector_uv(grid: Grid, geom, beta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scanner convention of test_projection_geometry_convention, written out: for every voxel centre
    ``(X, Y, Z)`` of ``grid``, its detector coordinates at gantry angle ``beta`` (u along (-sin b, cos b, 0), v along
    +z, mm on the detector) and its distance ``U`` from the source along the central ray; ``[nx, ny, nz]`` each."""
    x, y, z = np.meshgrid(*(a.numpy() for a in grid_axes(grid)), indexing="ij")
    big_u = geom.sod - (x * math.cos(beta) + y * math.sin(beta))
    mag = geom.sdd / big_u
    return (-x * math.sin(beta) + y * math.cos(beta)) * mag, z * mag, big_u


def test_fan_projection_geometry_convention():
    """Fan beam, slice by slice: a voxel at (X, Y) projects at view b to u = (-X sin b + Y cos b) sdd / U, the
    cone beam's convention. Voxel centres and detector columns are set to meet exactly (2 mm voxels at even mm, 3 mm
    columns at multiples of 3 mm, magnification 1.5), so a mirrored detector or a half-pixel offset moves the peak."""
    grid = Grid.centered((33, 33, 3), (2.0, 2.0, 2.0))  # voxel centres at even mm, index 16 is 0 mm
    geom = FanBeamGeometry(num_views=4, num_detectors=41, pixel_pitch=3.0)  # sod 800, sdd 1200: column 20 is u = 0
    assert geom.magnification == 1.5
    vol = torch.zeros(33, 33, 3)
    vol[16, 17, 0] = MU  # (X, Y) = (0, 2) mm in slice 0
    vol[15, 16, 2] = MU  # (X, Y) = (-2, 0) mm in slice 2 (slice 1 stays empty)
    sino = fan_forward(vol, grid, geom, "cpu").double()
    assert sino.shape == (4, 3, 41)
    assert float(sino[:, 1].abs().max()) == 0.0
    u_cols = geom.u_coords().numpy()
    for k, (x, y) in ((0, (0.0, 2.0)), (2, (-2.0, 0.0))):
        for view, beta in enumerate(geom.angles().tolist()):
            big_u = geom.sod - x * math.cos(beta) - y * math.sin(beta)
            u = (-x * math.sin(beta) + y * math.cos(beta)) * geom.sdd / big_u
            col = int(np.argmin(np.abs(u_cols - u)))
            assert abs(u_cols[col] - u) < 0.02  # the voxel projects onto a column centre
            row = sino[view, k].numpy()
            assert int(np.argmax(row)) == col, (k, view, u)
            assert row[col] == pytest.approx(2.0 * MU, rel=1e-3)  # one 2 mm voxel on the ray
            assert np.delete(row, col).max() < 0.01 * row[col]
    # the same for the expected columns, written out: view 0 sees +Y at +u, view 1 sees -X at +u
    assert int(sino[0, 0].argmax()) == 21 and int(sino[1, 0].argmax()) == 20
    assert int(sino[0, 2].argmax()) == 20 and int(sino[1, 2].argmax()) == 21


def test_fan_fbp_puts_an_off_centre_ball_where_it_is():
    """The Sim-CT's reconstruction (fan forward projection + FBP) of a ball off the axis: at the ball, not mirrored
    through the axis (a detector read the wrong way round in one of the two would put it near (-X, -Y))."""
    grid = Grid.centered((32, 32, 2), (4.0, 4.0, 4.0))
    x, y, _ = torch.meshgrid(*grid_axes(grid), indexing="ij")
    centre = (22.0, -14.0)
    vol = (((x - centre[0]) ** 2 + (y - centre[1]) ** 2) <= 12.0**2).float() * MU
    geom = FanBeamGeometry(num_views=90).fitted(64.0, 4.0)
    rec = fbp_fan(fan_forward(vol, grid, geom, "cpu"), geom, grid, "ram-lak", "cpu").double()
    w = torch.where(rec > 0.5 * MU, rec, torch.zeros_like(rec)).sum(2)
    found = (float((w * x[:, :, 0]).sum() / w.sum()), float((w * y[:, :, 0]).sum() / w.sum()))
    np.testing.assert_allclose(found, centre, atol=1.0)  # a quarter voxel
    inside = ((x - centre[0]) ** 2 + (y - centre[1]) ** 2) < 6.0**2
    assert abs(float(rec[inside].mean()) / MU - 1.0) < 0.05


@pytest.mark.parametrize(("kind", "use_symmetry"), [("fan", False), ("cone", True), ("cone", False)])
def test_backprojection_of_one_detector_pixel(kind, use_symmetry):
    """Back projection of a single detector pixel (value 1, views 0 and 1 of a 4-view full scan): every voxel gets
    ``(sod / U)^2`` times the bilinear weight of that pixel at the voxel's own (u, v) of the convention, so the
    voxel whose ray meets the pixel centre gets exactly 1 and its neighbours one pixel away 0. A mirrored detector
    axis or a half-pixel offset of the sampling fails this."""
    from monai_rigidreg.simulation import cone_backproject, fan_backproject

    grid = Grid.centered((17, 17, 9), (2.0, 2.0, 2.0))  # voxel centres at even mm, index 8 is 0 mm
    for view, (col, row) in ((0, (12, 6)), (1, (13, 5))):  # u = +6 / +9 mm, v = +3 / 0 mm
        if kind == "fan":
            geom = FanBeamGeometry(num_views=4, num_detectors=21, pixel_pitch=3.0)
            data = torch.zeros(4, 9, 21, dtype=torch.float64)
            data[view, :, col] = 1.0
            out = fan_backproject(data, grid, geom, "cpu").double().numpy()
        else:
            geom = ConeBeamGeometry(num_views=4, detector_shape=(21, 11), pixel_pitch=(3.0, 3.0))
            data = torch.zeros(4, 11, 21, dtype=torch.float64)
            data[view, row, col] = 1.0
            out = cone_backproject(data, grid, geom, "cpu", use_symmetry=use_symmetry).double().numpy()
        beta = float(geom.angles()[view])
        u, v, big_u = _detector_uv(grid, geom, beta)
        weight = np.clip(1.0 - np.abs(u - float(geom.u_coords()[col])) / 3.0, 0.0, None)
        if kind == "cone":
            weight = weight * np.clip(1.0 - np.abs(v - float(geom.v_coords()[row])) / 3.0, 0.0, None)
        expected = (geom.sod / big_u) ** 2 * weight
        np.testing.assert_allclose(out, expected, atol=2e-5)
        # the voxel on the pixel's ray through the centre plane (view 0: (0, 4) mm, view 1: (-6, 0) mm)
        ix, iy = (8, 10) if view == 0 else (5, 8)
        iz = 5 if kind == "cone" and view == 0 else 4  # v = +3 mm is z = +2 mm at magnification 1.5
        assert out[ix, iy, iz] == pytest.approx(1.0, abs=1e-5)


def test_rot90_view_sharing_is_exact():
    """The 4-views-at-once path (90 degree symmetry) equals the plain per-view projector and back projector."""
    from monai_rigidreg.simulation import cone_backproject

    grid = Grid.centered((20, 20, 18), (6.0, 6.0, 6.0))
    obj, _ = make_phantom("random", grid, seed=2)
    geom = ConeBeamGeometry(num_views=12, start_angle=7.0).fitted(90.0, 60.0, 6.0)
    a = cone_forward(obj, grid, geom, "cpu", use_symmetry=True)
    b = cone_forward(obj, grid, geom, "cpu", use_symmetry=False)
    assert torch.allclose(a, b, atol=1e-5)
    qa = cone_backproject(a, grid, geom, "cpu", use_symmetry=True)
    qb = cone_backproject(a, grid, geom, "cpu", use_symmetry=False)
    assert torch.allclose(qa, qb, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("use_symmetry", [True, False])
def test_backprojection_of_chosen_columns(use_symmetry):
    """``columns``: the chosen voxel columns get exactly the full back projection's values, the others 0; an
    off-centre, non-symmetric set (the symmetric path must gather its rotations) and a wrong mask shape."""
    from monai_rigidreg.simulation import cone_backproject

    grid = Grid.centered((20, 20, 18), (6.0, 6.0, 6.0))
    obj, _ = make_phantom("random", grid, seed=3)
    geom = ConeBeamGeometry(num_views=12, start_angle=7.0).fitted(90.0, 60.0, 6.0)
    proj = cone_forward(obj, grid, geom, "cpu")
    full = cone_backproject(proj, grid, geom, "cpu", use_symmetry=use_symmetry)
    cols = torch.zeros(20, 20, dtype=torch.bool)
    cols[2:9, 11:19] = True
    cols[15, 3] = True
    part = cone_backproject(proj, grid, geom, "cpu", use_symmetry=use_symmetry, columns=cols)
    assert torch.allclose(part[cols], full[cols], rtol=1e-6, atol=1e-6)
    assert float(full[cols].abs().amax(-1).min()) > 0  # every chosen column holds values
    assert torch.count_nonzero(part[~cols]) == 0
    with pytest.raises(ValueError, match="columns"):
        cone_backproject(proj, grid, geom, "cpu", columns=cols[:, :10])


def test_fdk_masked_to_the_fov_equals_full_reconstruction():
    """``simulate_cbct`` reconstructs only the field of view's columns: the same volume as a full FDK masked
    afterwards."""
    from monai_rigidreg.simulation import simulate_cbct
    from monai_rigidreg.simulation.physics import CBCTPhysics
    from monai_rigidreg.simulation.reconstruction import fdk

    grid = Grid.centered((24, 24, 16), (8.0, 8.0, 8.0))
    obj, _ = make_phantom("shepp-logan", grid, radius_mm=80.0)
    rec, fov, geom = simulate_cbct(obj, grid, grid, views=16, physics=CBCTPhysics.ideal(), device="cpu",
                                   detector_radius_mm=70.0)
    assert 0 < int(fov.any(2).sum()) < 24 * 24  # the field of view leaves out some columns
    ref = fdk(cone_forward(obj, grid, geom, "cpu"), geom, grid, "shepp-logan", "cpu")
    assert torch.allclose(rec, torch.where(fov, ref, torch.zeros_like(ref)), rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("kind", ["cone", "cone-symmetric", "fan"])
def test_empty_margins_change_no_line_integral(kind, monkeypatch):
    """The projectors sweep only the occupied planes: an object off-centre in a grid with wide empty margins gives
    the line integrals of the full sweep over every plane (the reference: the span forced to the whole grid)."""
    from monai_rigidreg.simulation import projector

    tight = Grid((14, 10, 12), (3.0, 3.0, 3.0), (-9.0, 15.0, -16.5))
    obj, _ = make_phantom("random", tight, seed=4)
    obj[0], obj[-1], obj[:, 0], obj[:, -1] = 0.02, 0.03, 0.04, 0.05  # the edge planes hold something
    wide = Grid((30, 34, 12), (3.0, 3.0, 3.0), (-45.0, -51.0, -16.5))
    big = torch.zeros(wide.size)
    big[12:26, 22:32] = obj
    if kind == "cone-symmetric":  # square and centred: the four rotated copies are swept together (their joint span)
        wide = Grid.centered((34, 34, 12), (3.0, 3.0, 3.0))
        big = torch.zeros(wide.size)
        big[14:28, 22:32] = obj
        assert projector._quarter_symmetric(ConeBeamGeometry(num_views=16).fitted(110.0, 30.0, 3.0), wide)
    if kind.startswith("cone"):
        geom = ConeBeamGeometry(num_views=16, start_angle=3.0).fitted(110.0, 30.0, 3.0)
        project = projector.cone_forward
    else:
        geom = FanBeamGeometry(num_views=16, start_angle=3.0).fitted(110.0, 3.0)
        project = projector.fan_forward
    lo_x = 14 if kind == "cone-symmetric" else 12
    assert projector._occupied_span(big) == (lo_x, lo_x + 14)
    assert projector._occupied_span(big.transpose(0, 1)) == (22, 32)
    got = project(big, wide, geom, "cpu")
    monkeypatch.setattr(projector, "_occupied_span", lambda planes: (0, planes.shape[0]))
    want = project(big, wide, geom, "cpu")
    assert float(want.max()) > 0.5
    torch.testing.assert_close(got, want, atol=2e-5, rtol=1e-5)


def test_fan_backprojection_field_of_view_only():
    """``fov_only``: the same values inside the circle every view sees, 0 outside (where they were incomplete)."""
    from monai_rigidreg.simulation import fan_backproject

    grid = Grid.centered((40, 40, 3), (2.0, 2.0, 2.0))
    geom = FanBeamGeometry(num_views=24).fitted(30.0, 2.0)
    sino = torch.rand(24, 3, int(geom.num_detectors), generator=torch.Generator().manual_seed(0))
    full = fan_backproject(sino, grid, geom, "cpu")
    fov = fan_backproject(sino, grid, geom, "cpu", fov_only=True)
    half = float(geom.u_coords()[-1]) + float(geom.pixel_pitch) / 2
    radius = geom.sod * math.sin(math.atan(half / geom.sdd))
    xs = grid_axes(grid)[0]
    inside = (xs[:, None] ** 2 + xs[None, :] ** 2 <= radius**2)[:, :, None].expand(40, 40, 3)
    assert 0.3 < float(inside.float().mean()) < 0.9
    torch.testing.assert_close(fov[inside], full[inside])
    assert bool((fov[~inside] == 0).all()) and float(full[~inside].abs().max()) > 0


@pytest.mark.parametrize("kind", ["cone", "fan"])
def test_central_ray_line_integral(kind):
    grid = Grid.centered((40, 40, 40), (2.0, 2.0, 2.0))
    vol = _ball(grid, 30.0)
    if kind == "cone":
        geom = ConeBeamGeometry(num_views=3, detector_shape=(40, 40), pixel_pitch=(3.0, 3.0))
        proj = cone_forward(vol, grid, geom, "cpu")
        centre = proj[:, 19:21, 19:21].mean((1, 2))
    else:
        geom = FanBeamGeometry(num_views=3, num_detectors=40, pixel_pitch=3.0)
        proj = fan_forward(vol, grid, geom, "cpu")
        centre = proj[:, 19:21, 19:21].mean((1, 2))
    # chord of the ball through the centre (rays through pixel centres +-1.5 mm off-axis: negligible)
    assert torch.allclose(centre, torch.full_like(centre, 2 * 30.0 * MU), rtol=0.02)


def test_detector_is_fitted_to_the_object():
    grid = Grid.centered((32, 32, 32), (4.0, 4.0, 4.0))
    vol = _ball(grid, 50.0)
    geom = ConeBeamGeometry(num_views=8).fitted(52.0, 52.0, 4.0)
    assert geom.detector_shape[0] * geom.pixel_pitch[0] > 2 * 52 * geom.magnification
    proj = cone_forward(vol, grid, geom, "cpu")
    assert float(proj[:, :, :2].abs().max()) == 0.0 and float(proj[:, :, -2:].abs().max()) == 0.0
    assert float(proj[:, :2].abs().max()) == 0.0


def test_fdk_uniform_ball_within_one_percent():
    grid = Grid.centered((32, 32, 32), (4.0, 4.0, 4.0))
    vol = _ball(grid, 40.0)
    geom = ConeBeamGeometry(num_views=180).fitted(90.0, 64.0, 4.0)  # sees the whole grid
    rec = fdk(cone_forward(vol, grid, geom, "cpu"), geom, grid, "ram-lak", "cpu")
    assert abs(float(_centre(rec).mean()) / MU - 1.0) < 0.01
    outside = rec[_ball(grid, 52.0) == 0]
    assert float(outside.abs().mean()) < 0.02 * MU


def test_fan_fbp_uniform_ball_and_windows():
    grid = Grid.centered((32, 32, 8), (4.0, 4.0, 4.0))
    xs, ys, _ = grid_axes(grid)
    cyl = ((xs[:, None] ** 2 + ys[None, :] ** 2) <= 40.0**2).float()[:, :, None].expand(32, 32, 8) * MU
    geom = FanBeamGeometry(num_views=180).fitted(44.0, 4.0)
    sino = fan_forward(cyl.contiguous(), grid, geom, "cpu")
    noise = torch.randn(sino.shape, generator=torch.Generator().manual_seed(0)) * 0.01
    stds = {}
    for window in ("ram-lak", "shepp-logan", "cosine", "hann", "hamming"):
        rec = fbp_fan(sino, geom, grid, window, "cpu")
        assert abs(float(_centre(rec).mean()) / MU - 1.0) < 0.01, window
        stds[window] = float(_centre(fbp_fan(sino + noise, geom, grid, window, "cpu") - rec, 4).std())
    assert stds["hann"] < stds["shepp-logan"] < stds["ram-lak"]
    with pytest.raises(ValueError, match="unknown filter"):
        fbp_fan(sino, geom, grid, "butterworth", "cpu")


# ----------------------------------------------------------------------------------------------------------------
# ground truth
# ----------------------------------------------------------------------------------------------------------------
def test_marker_appears_at_motion_of_its_position():
    """A dense marker at p in the object shows up in the CBCT at M(p) (T = M), not at M^-1(p)."""
    obj_grid = Grid.centered((48, 48, 48), (4.0, 4.0, 4.0))
    p = np.array([30.0, -22.0, 14.0])
    obj = _ball(obj_grid, 70.0) + _ball(obj_grid, 4.5, 0.4, center=tuple(p))
    params = (10.0, -6.0, 8.0, 15.0, -10.0, 20.0)
    cbct_grid = Grid.centered((40, 40, 40), (4.0, 4.0, 4.0))
    rec, fov, _ = simulate_cbct(obj, obj_grid, cbct_grid, params, views=90, physics=CBCTPhysics.ideal(), device="cpu")
    idx = np.unravel_index(int(rec.argmax()), rec.shape)
    # sub-voxel centroid of the marker in a 5^3 neighbourhood of the brightest voxel
    sl = tuple(slice(i - 2, i + 3) for i in idx)
    w = (rec[sl] - rec[sl].median()).clamp_min(0.0).double()
    xs, ys, zs = (a[s_] for a, s_ in zip(grid_axes(cbct_grid), sl))
    found = np.array([float((w.sum((1, 2)) * xs).sum()), float((w.sum((0, 2)) * ys).sum()), 0.0]) / float(w.sum())
    found[2] = float((w.sum((0, 1)) * zs).sum() / w.sum())
    m = params_to_matrix(params, (0.0, 0.0, 0.0))
    expected = transform_points(m, p)[0]
    wrong = transform_points(np.linalg.inv(m), p)[0]
    assert np.abs(found - expected).max() < 4.0 * 0.5  # within half a voxel (4 mm) on every axis
    assert np.linalg.norm(found - wrong) > 20.0
    assert bool(fov[idx])


def _read(path: Path) -> sitk.Image:
    return sitk.ReadImage(str(path))


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a.ravel(), b.ravel())[0, 1])


def test_dataset_ground_truth_aligns_with_sitk(tmp_path):
    path = simulate_dataset(
        tmp_path / "ds", "shepp-logan-asym", "paper", num_cases=3, seed=1, device="cpu", progress=False, **TINY
    )
    items = json.loads(path.read_text())["training"]
    assert [it["condition"] for it in items[:2]] == ["Translation (1.5 cm)", "Rotation (theta_x = 30 deg)"]
    for i, it in enumerate(items):
        fixed, moving = _read(path.parent / it["fixed"]), _read(path.parent / it["moving"])
        fov = _read(path.parent / it["moving_fov"])
        f, reg, raw, mask = resampled_with_truth(fixed, moving, fov, params_to_sitk(it["params"], it["center"]))
        after, before = _ncc(f[mask], reg[mask]), _ncc(f[mask], raw[mask])
        gain = 0.05 if i < 2 else 0.005  # 15 mm / 30 deg cases: clearly; the 5 mm case on 8 mm voxels: still higher
        assert after > 0.9 and after > before + gain, (it["label"], before, after)
        assert np.allclose(np.array(it["matrix"]), params_to_matrix(it["params"], it["center"]))


# ----------------------------------------------------------------------------------------------------------------
# physics
# ----------------------------------------------------------------------------------------------------------------
def _ball_cbct(physics: CBCTPhysics, seed: int = 0, insert: bool = False) -> torch.Tensor:
    grid = Grid.centered((28, 28, 28), (5.0, 5.0, 5.0))
    obj = _ball(grid, 60.0)
    if insert:
        obj = obj + _ball(grid, 20.0, 0.2 * MU)
    rec, _, _ = simulate_cbct(obj, grid, grid, views=90, physics=physics, seed=seed, window="ram-lak", device="cpu")
    return rec


def test_noise_std_scales_as_inverse_sqrt_photons():
    clean = _ball_cbct(CBCTPhysics.ideal())
    std = {}
    for i0 in (1e4, 4e4):
        phys = CBCTPhysics(photons=i0, electronic_noise=0.0, scatter_to_primary=0.0, beam_hardening=0.0)
        std[i0] = float(_centre(_ball_cbct(phys, seed=3) - clean, 5).std())
    assert std[1e4] / std[4e4] == pytest.approx(2.0, rel=0.15)


def test_automatic_exposure_raises_the_dose_for_a_thick_patient_only():
    """``exposure_reference``: projections whose ray through the isocentre (the median over the views of the
    detector's centre pixel) is thicker than the reference are taken at ``photons * exp(p_centre - reference)``:
    the measured line integrals of a 9-thick patient keep the noise of a 6.5-thick one (where 3e4 photons alone leave
    about 4 primary photons: 3 times the noise and a bias of the log), and a thin patient's projections are the
    very same as without the control. Not the thickest ray (12), not the first view's or the mean over the views."""
    from monai_rigidreg.simulation import apply_cbct_physics, effective_photons
    from monai_rigidreg.simulation.scanner import ConeBeamGeometry

    geom = ConeBeamGeometry(num_views=16, detector_shape=(21, 11), pixel_pitch=(3.0, 3.0))
    base = {"photons": 3e4, "electronic_noise": 0.0, "scatter_to_primary": 0.0, "beam_hardening": 0.0}
    on, off = CBCTPhysics(**base, exposure_reference=6.5), CBCTPhysics(**base)

    def measured(p, phys):
        return apply_cbct_physics(p, geom, phys, torch.Generator().manual_seed(4))

    thick = torch.full((16, 11, 21), 9.0)
    thick[:, :, :3] = 2.0  # the body's edge
    thick[:, :, -3:] = 12.0  # thicker off the isocentre
    thick[::4, 5, 10] = 4.0  # the centre ray thinner in 4 of 16 views (view 0 among them): the median stays 9
    assert effective_photons(thick, on) == pytest.approx(3e4 * math.exp(2.5))
    assert effective_photons(thick, off) == 3e4
    region = torch.zeros(16, 11, 21, dtype=torch.bool)
    region[:, :, 3:-3] = True
    region[:, 5, 10] = False  # the 9-thick pixels
    with_aec, without = measured(thick, on)[region], measured(thick, off)[region]
    assert float(with_aec.std()) == pytest.approx(1 / math.sqrt(3e4 * math.exp(-6.5)), rel=0.15)
    assert abs(float(with_aec.mean()) - 9.0) < 0.05
    assert float(without.std()) > 3 * float(with_aec.std()) and abs(float(without.mean()) - 9.0) > 0.1
    thin = torch.full((16, 11, 21), 5.0)
    assert effective_photons(thin, on) == 3e4 and torch.equal(measured(thin, on), measured(thin, off))


def test_noise_is_seeded():
    phys = CBCTPhysics(photons=1e4, scatter_to_primary=0.0, beam_hardening=0.0)
    a, b, c = _ball_cbct(phys, 1), _ball_cbct(phys, 1), _ball_cbct(phys, 2)
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_scatter_lowers_contrast_and_adds_cupping():
    ideal = _ball_cbct(CBCTPhysics.ideal(), insert=True)
    scat = _ball_cbct(CBCTPhysics(photons=None, electronic_noise=0, scatter_to_primary=0.5, beam_hardening=0), 0, True)
    c = 14  # centre index; insert radius 20 mm = 4 voxels; ball radius 60 mm = 12 voxels

    def contrast(v):
        return float(v[c - 1 : c + 1, c - 1 : c + 1, c - 1 : c + 1].mean() - v[c + 6 : c + 8, c - 1 : c + 1, c].mean())

    def cupping(v):  # near the edge minus half-way out (relative): a cupped profile rises towards the edge
        return float(v[c + 9 : c + 11, c - 1 : c + 1, c].mean() - v[c + 5 : c + 7, c - 1 : c + 1, c].mean()) / MU

    assert contrast(scat) < 0.85 * contrast(ideal)
    assert cupping(scat) > cupping(ideal) + 0.01
    assert float(_centre(scat).mean()) < 0.95 * float(_centre(ideal).mean())  # uncorrected scatter lowers mu
    # beam hardening also cups
    bh = _ball_cbct(CBCTPhysics(photons=None, electronic_noise=0, scatter_to_primary=0, beam_hardening=0.05), 0, True)
    assert cupping(bh) > cupping(ideal) + 0.02


def test_truncation_and_small_fov():
    grid = Grid.centered((28, 28, 28), (5.0, 5.0, 5.0))
    obj = _ball(grid, 60.0)
    phys = CBCTPhysics.ideal()
    phys = CBCTPhysics(**{**phys.to_dict(), "detector_fraction": 0.6, "fov_diameter_mm": 60.0})
    rec, fov, _ = simulate_cbct(obj, grid, grid, views=60, physics=phys, device="cpu")
    xs, ys, _ = grid_axes(grid)
    rho = torch.sqrt(xs[:, None] ** 2 + ys[None, :] ** 2)
    assert bool((rho[fov.any(2)] <= 30.0 + 1e-6).all()) and int(fov.sum()) > 100
    assert float(rec[~fov].abs().max()) == 0.0


# ----------------------------------------------------------------------------------------------------------------
# phantoms and units
# ----------------------------------------------------------------------------------------------------------------
def test_hu_round_trip_and_file_units(tmp_path):
    hu = np.array([-1000.0, -500.0, 0.0, 40.0, 1000.0, 3000.0])
    assert np.allclose(mu_to_hu(hu_to_mu(hu)), hu)
    assert hu_to_mu(0.0) == pytest.approx(MU_WATER) and float(hu_to_mu(np.array(-1500.0))) == 0.0
    grid = Grid.centered((6, 5, 4), (2.0, 2.5, 3.0))
    mu = torch.rand(6, 5, 4) * 0.04
    img = _read(save_volume_hu(mu, grid, tmp_path / "v.nii.gz"))
    assert np.allclose(Grid.from_sitk(img).center(), 0.0, atol=1e-5)
    assert np.allclose(img.GetDirection(), np.eye(3).ravel())
    stored = sitk.GetArrayFromImage(img).transpose(2, 1, 0)
    # int16 whole HU by default (as scanners store CT): within half a HU of the exact values
    assert img.GetPixelID() == sitk.sitkInt16
    assert np.abs(stored - mu_to_hu(mu.numpy())).max() <= 0.5 + 1e-3
    exact = _read(save_volume_hu(mu, grid, tmp_path / "f.nii.gz", dtype="float32"))
    back = hu_to_mu(sitk.GetArrayFromImage(exact).transpose(2, 1, 0))
    assert exact.GetPixelID() == sitk.sitkFloat32 and np.allclose(back, mu.numpy(), atol=1e-6)
    # out-of-range values clip instead of wrapping around
    one = Grid.centered((2, 2, 2), (1.0, 1.0, 1.0))
    clipped = _read(save_volume_hu(torch.full((2, 2, 2), 10.0), one, tmp_path / "c.nii.gz"))
    assert int(sitk.GetArrayViewFromImage(clipped).min()) == 32767
    with pytest.raises(ValueError, match="dtype"):
        save_volume_hu(mu, grid, tmp_path / "x.nii.gz", dtype="uint8")


def test_shepp_logan_variants_and_random_family():
    stock, asym = shepp_logan_shapes(100.0), shepp_logan_shapes(100.0, asymmetric=True)
    assert asym[0].semi_axes[2] == pytest.approx(0.87 * stock[0].semi_axes[2])
    assert asym[0].semi_axes[0] == pytest.approx(0.87 * stock[0].semi_axes[0])
    assert asym[0].semi_axes[1] == stock[0].semi_axes[1]
    # no two skull semi-axes within 15 %: no rotation axis about which the skull is (nearly) symmetric
    a = sorted(asym[0].semi_axes)
    assert a[1] / a[0] > 1.15 and a[2] / a[1] > 1.15
    grid = Grid.centered((32, 32, 32), (8.0, 8.0, 8.0))
    vol, _ = make_phantom("shepp-logan", grid)
    assert float(vol.max()) == pytest.approx(1.8 * MU_WATER, rel=0.01)
    assert float(vol[16, 16, 16]) == pytest.approx(MU_WATER, rel=0.2)  # brain = water
    a, b = random_phantom_shapes(5), random_phantom_shapes(5)
    assert a == b and a != random_phantom_shapes(6)
    va, desc = make_phantom("random", grid, seed=5)
    assert desc["seed"] == 5 and float(va.max()) > 1.3 * MU_WATER  # bone
    assert float((va > 0).float().mean()) > 0.05
    # everything stays inside a sphere of 0.95 radius: rotations keep it in the grid
    xs, ys, zs = grid_axes(grid)
    r = torch.sqrt(xs[:, None, None] ** 2 + ys[None, :, None] ** 2 + zs[None, None, :] ** 2)
    for seed in range(6):
        v, _ = make_phantom("random", grid, seed=seed)
        assert float(v[r > 0.95 * 128 + 8 * 1.8].abs().max()) == 0.0


def test_protocols():
    cases = paper_cases()
    groups = {c.group for c in cases}
    assert groups == {"translation", "translation_multi", "rotation_x", "rotation_y", "rotation_z", "rotation", "multi"}
    for c in cases:
        assert max(abs(v) for v in c.params[:3]) <= 15 and max(abs(v) for v in c.params[3:]) <= 30
    assert {abs(c.params[0]) for c in cases if c.group == "translation"} == {0.0, 5.0, 10.0, 15.0}
    assert len(protocol_cases("paper", 5)) == 5 and len(protocol_cases("paper")) == len(cases)
    r1, r2 = protocol_cases("random", 10, seed=3), protocol_cases("random", 10, seed=3)
    assert r1 == r2 and all(abs(v) <= 30 for c in r1 for v in c.params)


# ----------------------------------------------------------------------------------------------------------------
# dataset generator
# ----------------------------------------------------------------------------------------------------------------
def test_dataset_deterministic_resumable_and_monai_loadable(tmp_path):
    from monai.data import load_decathlon_datalist

    kw = dict(phantom="random", protocol="random", num_cases=3, seed=7, device="cpu", progress=False, **TINY)
    p1 = simulate_dataset(tmp_path / "a", num_objects=2, **kw)
    p2 = simulate_dataset(tmp_path / "b", num_objects=2, workers=2, **kw)  # worker processes: same result
    items = json.loads(p1.read_text())["training"]
    assert p1.read_text() == p2.read_text()
    assert len({it["fixed"] for it in items}) == 2 and len({it["object"] for it in items}) == 2
    for it in items:
        for key in ("fixed", "moving", "moving_fov"):
            a = sitk.GetArrayFromImage(_read(p1.parent / it[key]))
            assert np.array_equal(a, sitk.GetArrayFromImage(_read(p2.parent / it[key])))
    fov = _read(p1.parent / items[0]["moving_fov"])
    assert fov.GetPixelID() == sitk.sitkUInt8 and fov.GetSize() == (24, 24, 24)
    meta = json.loads((p1.parent / "simulation.json").read_text())
    assert meta["config"]["seed"] == 7 and "torch" in meta["versions"]

    # MONAI datalist
    dl = load_decathlon_datalist(str(p1), is_segmentation=False, data_list_key="training")
    assert len(dl) == 3 and all(Path(d["moving"]).is_file() and Path(d["fixed"]).is_absolute() for d in dl)
    assert all(len(d["params"]) == 6 and np.array(d["matrix"]).shape == (4, 4) for d in dl)

    # resumable: only the missing case is recomputed
    done = p1.parent / items[1]["moving"]
    mtimes = {it["moving"]: (p1.parent / it["moving"]).stat().st_mtime_ns for it in items}
    (p1.parent / items[2]["moving"]).unlink()
    simulate_dataset(tmp_path / "a", num_objects=2, **kw)
    assert done.stat().st_mtime_ns == mtimes[items[1]["moving"]]
    again = sitk.GetArrayFromImage(_read(p1.parent / items[2]["moving"]))
    assert np.array_equal(again, sitk.GetArrayFromImage(_read(p2.parent / items[2]["moving"])))

    # a dataset written before the physics had the exposure control (the field absent) resumes; one with it on
    # is another configuration
    meta_path = p1.parent / "simulation.json"
    assert "exposure_reference" not in json.loads(meta_path.read_text())["config"]["physics"]
    simulate_dataset(tmp_path / "a", num_objects=2, **kw)
    with pytest.raises(OutputExistsError, match="physics"):
        simulate_dataset(tmp_path / "a", num_objects=2, **{**kw, "physics": {"exposure_reference": 6.5}})

    # another configuration in the same directory is refused, unless overwrite
    with pytest.raises(OutputExistsError, match="seed"):
        simulate_dataset(tmp_path / "a", num_objects=2, **{**kw, "seed": 8})
    simulate_dataset(tmp_path / "a", num_objects=2, overwrite=True, **{**kw, "seed": 8})
    assert not np.array_equal(
        sitk.GetArrayFromImage(_read(done)), sitk.GetArrayFromImage(_read(p2.parent / items[1]["moving"]))
    )


def test_an_interrupted_overwrite_leaves_no_volume_of_the_old_dataset_to_resume_from(tmp_path, monkeypatch):
    """--overwrite with another seed, interrupted after its first case, then resumed without --overwrite: every
    case is the new seed's (was: the old seed's cases kept as if finished, under the new ground truth, exit 0)."""
    from monai_rigidreg.simulation import dataset

    kw = dict(phantom="shepp-logan-asym", protocol="random", num_cases=3, device="cpu", progress=False, **TINY)
    out = tmp_path / "sim"
    simulate_dataset(out, seed=7, **kw)
    (out / "notes.txt").write_text("mine")  # not the writer's: overwrite leaves it
    real = dataset._run_case
    calls = []

    def interrupted(cfg, case, out_dir):
        if calls:
            raise KeyboardInterrupt
        calls.append(case["case_id"])
        return real(cfg, case, out_dir)

    monkeypatch.setattr(dataset, "_run_case", interrupted)
    with pytest.raises(KeyboardInterrupt):
        simulate_dataset(out, seed=8, overwrite=True, **kw)
    monkeypatch.setattr(dataset, "_run_case", real)
    assert not (out / "dataset.json").exists()  # no datalist while the dataset is incomplete
    assert sorted(p.name for p in (out / "cases").iterdir()) == ["case0000_cbct.nii.gz", "case0000_cbct_fov.nii.gz"]
    resumed = simulate_dataset(out, seed=8, **kw)
    fresh = simulate_dataset(tmp_path / "fresh", seed=8, **kw)
    assert json.loads(resumed.read_text()) == json.loads(fresh.read_text())
    for item in json.loads(fresh.read_text())["training"]:
        for key in ("fixed", "moving"):
            a = sitk.GetArrayFromImage(_read(out / item[key]))
            assert np.array_equal(a, sitk.GetArrayFromImage(_read(tmp_path / "fresh" / item[key]))), item[key]
    assert (out / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize(("option", "expected"), [
    ({"seed": -1}, "'seed' must be a whole number >= 0"),
    ({"max_translation": -5.0}, "'max_translation' must be a number >= 0"),
    ({"max_rotation": float("nan")}, "'max_rotation' must be a number >= 0"),
    ({"sdd": 100.0}, "need 0 < sod < sdd"),
    ({"phantom_radius_mm": -5.0}, "'phantom_radius_mm' must be a number > 0"),
    ({"num_objects": 0}, "'num_objects' must be a number > 0"),
    ({"supersample": 0}, "'supersample' must be a whole number >= 1"),
    ({"workers": -1}, "'workers' must be a whole number >= 0"),
    ({"seed": 10**400}, "'seed' must be"),  # too big for the seeding; math.isfinite overflowed on it
])
def test_simulation_numbers_out_of_range_are_input_errors(tmp_path, option, expected):
    """These ended in an internal error (exit 1) or were silently clamped and recorded as given."""
    with pytest.raises(InputError, match=expected):
        simulate_dataset(tmp_path / "x", num_cases=1, device="cpu", progress=False, **{**TINY, **option})
    assert not (tmp_path / "x").exists()


def test_a_ct_inside_the_folders_the_simulation_writes_is_refused(tmp_path):
    """simulate --overwrite from a CT lying among the previous dataset's volumes would have deleted (or rewritten)
    its own input."""
    kw = dict(protocol="random", num_cases=1, device="cpu", progress=False, **TINY)
    simulate_dataset(tmp_path / "d", phantom="shepp-logan-asym", **kw)
    ct = tmp_path / "d" / "objects" / "obj000_simct.nii.gz"
    before = ct.read_bytes()
    with pytest.raises(InputError, match="lies in a folder this simulation writes"):
        simulate_dataset(tmp_path / "d", phantom=str(ct), overwrite=True, **kw)
    assert ct.read_bytes() == before


def test_bad_inputs(tmp_path):
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("keep me")
    with pytest.raises(OutputExistsError):
        simulate_dataset(tmp_path / "other", num_cases=1, device="cpu", progress=False, **TINY)
    with pytest.raises(InputError, match="not found"):
        simulate_dataset(tmp_path / "x", phantom=str(tmp_path / "missing.nii.gz"), device="cpu", **TINY)
    with pytest.raises(InputError, match="unknown simulation option"):
        simulate_dataset(tmp_path / "x", num_cases=1, cbct_voxels=3, device="cpu", **TINY)
    with pytest.raises(InputError, match="preset"):
        simulate_dataset(tmp_path / "x", num_cases=1, preset="huge", device="cpu")
    img2d = sitk.Image(8, 8, sitk.sitkFloat32)
    sitk.WriteImage(img2d, str(tmp_path / "flat.nii.gz"))
    nan = sitk.GetImageFromArray(np.full((6, 6, 6), np.nan, np.float32))
    sitk.WriteImage(nan, str(tmp_path / "nan.nii.gz"))
    grid = Grid.centered((8, 8, 8), (8.0, 8.0, 8.0))
    for name in ("flat.nii.gz", "nan.nii.gz"):
        with pytest.raises(InputError):
            make_phantom(str(tmp_path / name), grid)
    assert (tmp_path / "other" / "notes.txt").read_text() == "keep me"


def test_real_ct_phantom(tmp_path):
    data = _data_dir()
    if data is None:
        pytest.skip("real CTs not found: set MONAI_RIGIDREG_DATA or provide ../shared/data next to the repository")
    ct = data / "abdomen_pelvis_totalsegmentator_example_ct.nii.gz"
    grid = Grid.centered((40, 40, 40), (8.0, 8.0, 8.0))
    mu, desc = make_phantom(str(ct), grid)
    assert desc["phantom"] == "ct" and float(mu.min()) >= 0.0
    centre = _centre(mu, 3)
    assert 0.7 * MU_WATER < float(centre.median()) < 1.3 * MU_WATER  # soft tissue at the isocentre
    assert float(mu[0, 0, 20]) < 0.1 * MU_WATER  # air in the corner
    path = simulate_dataset(tmp_path / "ct", phantom=str(ct), num_cases=1, device="cpu", progress=False, **TINY)
    item = json.loads(path.read_text())["training"][0]
    assert item["object"] == ct.name
    fixed = sitk.GetArrayFromImage(_read(path.parent / item["fixed"]))
    assert -1100 < float(fixed.min()) and float(np.median(fixed[12:20, 12:20, 12:20])) > -200


# ----------------------------------------------------------------------------------------------------------------
# command line
# ----------------------------------------------------------------------------------------------------------------
def test_cli(tmp_path, capsys):
    from monai_rigidreg.simulation.simulate_command import add_parser, run

    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers(dest="command"))
    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    out = tmp_path / "cli"
    args = parser.parse_args(
        [
            "simulate",
            "--output-dir",
            str(out),
            "--phantom",
            "shepp-logan-asym",
            "--num-cases",
            "1",
            "--seed",
            "2",
            "--device",
            "cpu",
            "--no-progress",
            *sets,
        ]
    )
    assert args.func is run
    assert run(args) == 0
    assert (out / "dataset.json").is_file() and str(out / "dataset.json") in capsys.readouterr().out
    args = parser.parse_args(["simulate", "--output-dir", str(out), "--seed", "3", "--device", "cpu", *sets])
    assert run(args) == 2 and "already exists" in capsys.readouterr().err


def test_set_value_of_the_wrong_type_is_a_clean_error(tmp_path, capsys):
    """``simulate --set cbct_views=many`` names the option and the value (an InputError, exit status 2), as does a
    physics field of the wrong type or out of range; values of the right kind still pass."""
    from monai_rigidreg.simulation import make_config
    from monai_rigidreg.simulation.simulate_command import main

    for key, value in [("cbct_views", "many"), ("seed", 1.5), ("cbct_size", "big"), ("sod", "far"),
                       ("mask_outside_fov", "no"), ("photons", "lots"), ("phantom", 3)]:
        with pytest.raises(InputError, match=f"{key}.*{value!r}"):
            make_config("fast", **{key: value})
    with pytest.raises(InputError, match="photons"):
        make_config("fast", photons=-1.0)
    cfg = make_config("fast", cbct_views=np.int64(60), sod=900, mask_outside_fov=False, simct_size=(32, 32, 32))
    assert cfg.cbct_views == 60 and cfg.mask_outside_fov is False and cfg.simct_size == (32, 32, 32)
    out = tmp_path / "x"
    assert main(["simulate", "--output-dir", str(out), "--device", "cpu", "--set", "cbct_views=many"]) == 2
    err = capsys.readouterr().err
    assert "cbct_views" in err and "'many'" in err and "Traceback" not in err
    assert not out.exists()


def test_output_dir_that_is_a_file_or_below_a_file(tmp_path, capsys):
    """An --output-dir that is a file, or whose parent is a file, is refused before anything is simulated."""
    from monai_rigidreg.simulation.simulate_command import main

    afile = tmp_path / "notes.txt"
    afile.write_text("keep me")
    with pytest.raises(OutputExistsError, match="is a file"):
        simulate_dataset(afile, num_cases=1, device="cpu", progress=False, **TINY)
    with pytest.raises(InputError, match="parent of it is a file"):
        simulate_dataset(afile / "data", num_cases=1, device="cpu", progress=False, **TINY)
    for out in (afile, afile / "data"):
        assert main(["simulate", "--output-dir", str(out), "--device", "cpu", "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("monai-rigidreg simulate: error:") and str(afile) in err
    assert afile.read_text() == "keep me"


def test_volume_dtype_is_a_storage_choice(tmp_path):
    """Volumes are stored as int16 HU by default and as float32 on request (``--set volume_dtype=float32``); the
    choice is not part of the dataset's configuration identity, and anything else is refused."""
    from conftest import TINY_SIM

    from monai_rigidreg.simulation import make_config, simulate_pair

    settings = {k: v for k, v in TINY_SIM.items() if k != "preset"}
    a = simulate_pair(tmp_path / "a", params=[3.0, 0, 0, 0, 0, 5.0], seed=1, device="cpu", **settings)
    b = simulate_pair(tmp_path / "b", params=[3.0, 0, 0, 0, 0, 5.0], seed=1, device="cpu", volume_dtype="float32",
                      **settings)
    for key in ("fixed", "moving"):
        ia, ib = sitk.ReadImage(str(a[key])), sitk.ReadImage(str(b[key]))
        assert ia.GetPixelID() == sitk.sitkInt16 and ib.GetPixelID() == sitk.sitkFloat32
        diff = sitk.GetArrayFromImage(ia).astype(np.float64) - sitk.GetArrayFromImage(ib)
        assert np.abs(diff).max() <= 0.5 + 1e-3  # the same simulation, rounded to whole HU
    assert make_config("fast", volume_dtype="float32").identity() == make_config("fast").identity()
    with pytest.raises(InputError, match="volume_dtype"):
        make_config("fast", volume_dtype="float16")


@pytest.mark.parametrize("nu", [23, 32, 140])
def test_ramp_filter_is_the_linear_convolution_with_the_spatial_kernel(nu):
    """Whatever the padded FFT length (5-smooth, >= 2 nu), a row is convolved with the spatial Ram-Lak kernel
    ``h[0] = 1 / (4 tau^2)``, ``h[odd n] = -1 / (pi n tau)^2`` (times ``tau``) without wrap-around."""
    from monai_rigidreg.simulation.reconstruction import padded_length, ramp_filter

    p = padded_length(nu)
    assert p >= 2 * nu and p % 2 == 0 and p <= 2 * nu + 16
    m = p
    for f in (2, 3, 5):
        while m % f == 0:
            m //= f
    assert m == 1
    tau = 1.7
    rows = torch.randn(3, nu, generator=torch.Generator().manual_seed(nu), dtype=torch.float64)
    n = torch.arange(-(nu - 1), nu, dtype=torch.float64)
    h = torch.where(n.remainder(2) == 1, -1.0 / (math.pi * n * tau) ** 2, torch.zeros_like(n))
    h[nu - 1] = 1.0 / (4 * tau**2)
    want = torch.stack([torch.stack([(r * h[i - torch.arange(nu) + nu - 1]).sum() * tau for i in range(nu)])
                        for r in rows])
    torch.testing.assert_close(ramp_filter(rows, tau).double(), want, atol=1e-5, rtol=1e-4)


def test_multi30_protocol_and_the_cli_choices():
    """``multi30``: eight 6-DoF motions with |rx| = |ry| = |rz| = 30 degrees, every sign pattern once; the
    ``simulate`` command offers exactly the package's protocols."""
    import argparse

    from monai_rigidreg.simulation import cli as sim_cli
    from monai_rigidreg.simulation.protocols import PROTOCOLS, protocol_cases

    cases = protocol_cases("multi30")
    assert len(cases) == 8 and cases[0].params == (5.0, 15.0, -10.0, 30.0, 30.0, -30.0)
    rot = np.array([c.params[3:] for c in cases])
    assert np.all(np.abs(rot) == 30.0)
    assert len({tuple(np.sign(r)) for r in rot}) == 8
    assert all(np.all(np.abs(c.params[:3]) >= 5.0) for c in cases)
    parser = argparse.ArgumentParser()
    sim_cli.add_parser(parser.add_subparsers())
    action = next(a for sp in parser._subparsers._group_actions for a in sp.choices["simulate"]._actions
                  if "--protocol" in a.option_strings)
    assert tuple(action.choices) == PROTOCOLS
