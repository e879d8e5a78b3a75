"""Classical baselines (SimpleITK, elastix), the evaluation tables and the QC figure."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import oblique_direction, smooth_random_image

from monai_rigidreg.core.geometry import Grid, grid_points, params_to_sitk, target_registration_error
from monai_rigidreg.evaluation import CaseResult, format_report, motion_conditions, summarize, write_report
from monai_rigidreg.export.qc_figure import edge_letters, orthogonal_slices, qc_figure, resampled_slices
from monai_rigidreg.io import resample
from monai_rigidreg.registration.classical import elastix_available, register_elastix, register_sitk

TRUE = [6.0, -4.0, 3.0, 5.0, -3.0, 8.0]


@pytest.fixture(scope="module")
def pair():
    fixed = smooth_random_image((32, 32, 32), (2.5, 2.5, 2.5), (-38.75,) * 3, (1, 0, 0, 0, 1, 0, 0, 0, 1), seed=1,
                                sigma_mm=4.0) * 1000
    center = Grid.from_sitk(fixed).center()
    # moving(y) = fixed(T^-1(y)): then Resample(moving, fixed, T) = fixed, i.e. T is the registration transform
    moving = resample(fixed, fixed, params_to_sitk(TRUE, center).GetInverse(), default_value=0)
    return fixed, moving, center


def test_sitk_baseline_recovers_known_motion(pair):
    fixed, moving, center = pair
    res = register_sitk(fixed, moving)
    np.testing.assert_allclose(res.center, center)
    tre = target_registration_error(res.params, TRUE, grid_points(Grid.from_sitk(fixed), 4), center=center)
    assert tre < 0.5
    np.testing.assert_allclose(res.params, TRUE, atol=0.5)
    # started from the answer, it stays there
    res2 = register_sitk(fixed, moving, initial_params=TRUE)
    np.testing.assert_allclose(res2.params, TRUE, atol=0.3)
    # deterministic: the same call gives the same numbers (SimpleITK's seed 0, its wall clock, is refused)
    np.testing.assert_allclose(register_sitk(fixed, moving).params, res.params, atol=1e-6)
    with pytest.raises(ValueError, match="wall clock"):
        register_sitk(fixed, moving, seed=0)


@pytest.mark.skipif(not elastix_available(), reason="itk-elastix (optional extra 'elastix') is not installed")
def test_elastix_baseline_recovers_known_motion(pair):
    fixed, moving, center = pair
    res = register_elastix(fixed, moving)
    tre = target_registration_error(res.params, TRUE, grid_points(Grid.from_sitk(fixed), 4), center=center)
    assert tre < 0.5


def test_motion_conditions():
    assert motion_conditions([15, 0, 0, 0, 0, 0]) == ["Translation 1.5 cm", "All cases"]
    assert motion_conditions([-15, 10, 0, 0, 0, 0])[0] == "Translation 1.5 cm"
    assert motion_conditions([10, 0, 0, 0, 0, 0]) == ["All cases"]
    assert motion_conditions([0, 0, 0, -30, 0, 0]) == ["Rotation theta_x = 30 deg", "All cases"]
    assert motion_conditions([0, 0, 0, 30, 5, 0]) == ["All cases"]


def test_summary_numbers_and_files(tmp_path):
    cases = [
        CaseResult("a", "net", [15, 0, 0, 0, 0, 0], [14, 0.5, 0, 0, 0, 0.2], 1.0, 0.1,
                   extra={"confidence": 0.9, "flagged": False}),
        CaseResult("b", "net", [0, 15, 0, 0, 0, 0], [0, 12, 0, 0, 0, 0], 3.0, 0.3,
                   extra={"confidence": 0.1, "flagged": True}),
        CaseResult("c", "net", [0, 0, 0, 30, 0, 0], [0, 0, 0, 29, 0, 0], 1.5, 0.2,
                   extra={"confidence": 0.3, "flagged": True}),
        CaseResult("a", "sitk", [15, 0, 0, 0, 0, 0], [15, 0, 0, 0, 0, 0], 0.0, 2.0),
    ]
    s = summarize(cases)
    tr = s["net"]["conditions"]["Translation 1.5 cm"]
    assert tr["n"] == 2
    assert tr["mae"]["tx"] == pytest.approx((0.5, np.std([1, 0], ddof=1)))
    assert tr["mae"]["ty"][0] == pytest.approx(1.75)
    assert s["net"]["conditions"]["Rotation theta_x = 30 deg"]["mae"]["rx"] == (1.0, 0.0)
    assert s["net"]["conditions"]["All cases"]["n"] == 3
    assert s["net"]["success_rate"] == pytest.approx(2 / 3)
    assert s["net"]["time_median_s"] == pytest.approx(0.2)
    assert s["sitk"]["success_rate"] == 1.0
    # the failure flag: the one failure (b) caught, one of two successes (c) a false alarm; none for sitk
    assert s["net"]["flag"] == {"failures": 1, "failures_flagged": 1, "successes": 2, "successes_flagged": 1}
    assert "flag" not in s["sitk"]
    text = format_report(s)
    assert "| net | Translation 1.5 cm | 2 | 0.50 ± 0.71 | 1.75 ± 1.77 | 0.00 ± 0.00 |" in text
    assert "| net | Rotation theta_x = 30 deg | 1 | 1.00 ± 0.00 |" in text
    assert "| net | 1 | 1 | 2 | 1 |" in text
    paths = write_report(cases, tmp_path)
    rows = list(csv.DictReader(open(paths["csv"])))
    assert len(rows) == 4 and rows[1]["abs_err_ty"] == "3.0000" and rows[1]["success"] == "0"
    assert (rows[1]["confidence"], rows[1]["flagged"]) == ("0.1000", "1") and rows[3]["flagged"] == ""
    assert json.loads(paths["json"].read_text())["summary"]["net"]["n"] == 3


def test_qc_figure_writes_png_and_refuses_overwrite(tmp_path, pair):
    fixed, moving, center = pair
    registered = resample(moving, fixed, params_to_sitk(TRUE, center))
    p = qc_figure(fixed, moving, registered, tmp_path / "qc.png", title="test")
    img = sitk.ReadImage(str(p))
    assert img.GetSize()[0] > 800
    with pytest.raises(FileExistsError):
        qc_figure(fixed, moving, registered, p)


@pytest.mark.parametrize("interpolator", ["linear", "nearest"])
def test_qc_slices_are_those_of_the_whole_resampled_volume(interpolator):
    """The QC figure resamples the three displayed slices only: on an oblique, anisotropic CT grid and a rotated
    CBCT the values equal the whole volume's resampling sliced (a slice off by one voxel or transposed differs)."""
    fixed = smooth_random_image((30, 26, 18), (1.1, 1.3, 2.2), (-15.0, -12.0, -20.0), oblique_direction(8, -6, 14),
                                seed=2)
    moving = smooth_random_image((24, 24, 20), (1.5, 1.5, 1.5), (-17.0, -16.0, -14.0), oblique_direction(0, 5, -9),
                                 seed=3)
    tfm = params_to_sitk([2.0, -1.5, 3.0, 4.0, -3.0, 6.0], Grid.from_sitk(fixed).center())
    for transform, center in ((tfm, (11, 9, 7)), (None, None)):
        whole = orthogonal_slices(resample(moving, fixed, transform, interpolator, -5.0), center)
        parts = resampled_slices(moving, fixed, transform, center, interpolator, -5.0)
        for a, b in zip(whole, parts):
            assert a.shape == b.shape
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-5)
        assert np.ptp(parts[2]) > 0.1  # real image content, not padding alone


def test_qc_difference_colours_and_field_of_view_outline():
    """The difference panels' colour map (seismic: -1 dark blue, 0 white, +1 dark red; a sign flip swaps blue and red)
    and the outline of a field-of-view mask (its border pixels only)."""
    from monai_rigidreg.export.qc_figure import _outline, _to_rgb

    rgb = _to_rgb(np.array([[-1.0, -0.5, 0.0, 0.5, 1.0, np.nan]]), "diff")[0]
    # (a 256-entry table: values between its entries are off by a step, at most 2 of 255); NaN, outside the CBCT's
    # field of view: grey
    np.testing.assert_allclose(rgb, [[0, 0, 77], [0, 0, 255], [255, 255, 255], [255, 0, 0], [128, 0, 0],
                                     [150, 150, 150]], atol=2)
    gray = _to_rgb(np.array([[0.0, 0.5, 1.0]]), "gray")[0]
    np.testing.assert_array_equal(gray, [[0, 0, 0], [128, 128, 128], [255, 255, 255]])
    mask = np.zeros((7, 9), bool)
    mask[2:5, 3:8] = True
    border = _outline(mask)
    assert border.sum() == 2 * 5 + 2 * 3 - 4 and not border[3, 4:7].any() and border[2, 3] and border[4, 7]


def test_qc_panels_zoom_to_the_cbct_grey_out_what_it_misses_and_say_the_difference_s_sign():
    """A 128 mm CBCT of a 500 mm CT, 90 mm off the CT's centre and registered with a large motion: every panel is
    zoomed to the CBCT's field of view (its box covers the field of view, and little more), the difference panels are
    grey exactly where the CBCT sees nothing, the "before" panels pass through the CBCT's own centre (its coronal
    was blank: it went through the registered centre, which the unregistered CBCT misses) and the difference is
    CT - CBCT over the stated window."""
    from monai_rigidreg.export.qc_figure import _NEUTRAL, _to_rgb, qc_panels

    fixed = smooth_random_image((100, 100, 40), (5.0, 5.0, 5.0), (-250.0, -250.0, -100.0),
                                (1, 0, 0, 0, 1, 0, 0, 0, 1), seed=4, sigma_mm=6.0) * 3000
    center = Grid.from_sitk(fixed).center()
    tfm = params_to_sitk([40.0, -30.0, 20.0, 8.0, -5.0, 25.0], center)
    grid = Grid.centered((32, 32, 32), (4.0, 4.0, 4.0), center=center + np.array([90.0, -30.0, 20.0]))
    moving = resample(fixed, grid, tfm.GetInverse(), default_value=-1000)  # the CBCT sees the CT moved by T
    registered = resample(moving, fixed, tfm, default_value=-1000)
    q = qc_panels(fixed, moving, registered, window=(-1000.0, 1000.0), transform=tfm)
    assert q["diff_window_hu"] == 1000.0 and "difference = CT - registered CBCT" in q["titles"][4]
    assert "CT - CBCT before" in q["titles"][3] and "window \u00b11000 HU" in q["subtitles"][4]
    centre = grid.center()
    assert q["centers"]["before"] == fixed.TransformPhysicalPointToIndex(tuple(centre))
    for group, column in (("before", 3), ("after", 4)):
        for r in range(3):
            mask, (r0, r1, c0, c1) = q["fov"][group][r], q["boxes"][group][r]
            rows, cols = np.nonzero(mask)
            assert rows.size and r0 <= rows.min() and rows.max() < r1 and c0 <= cols.min() and cols.max() < c1
            assert (r1 - r0) <= 1.3 * (np.ptp(rows) + 1) + 4 and (c1 - c0) <= 1.3 * (np.ptp(cols) + 1) + 4  # zoomed
            assert r > 0 or (r1 - r0) * (c1 - c0) < 0.2 * mask.size  # the axial: a fifth of the 500 mm slice
            tile, kind = q["panels"][r][column]
            seen = mask[r0:r1, c0:c1]
            assert kind == "diff" and tile.shape == seen.shape
            np.testing.assert_array_equal(np.isnan(tile), ~seen)  # grey exactly where the CBCT sees nothing
            rgb = _to_rgb(tile, "diff")
            assert (rgb[~seen] == _NEUTRAL).all() and not (rgb[seen] == _NEUTRAL).all(-1).any()
            before, _ = q["panels"][r][0]
            assert np.ptp(before[seen] if group == "before" else before) > 0.05  # the CBCT, not a blank slice
    # registered with the true motion: the difference after is small inside the field of view (resampling twice
    # leaves some); the sign: a CBCT 100 HU darker than the CT reads +100 HU (red)
    inside = q["panels"][1][4][0][~np.isnan(q["panels"][1][4][0])]
    assert float(np.median(np.abs(inside))) < 0.05
    darker = qc_panels(fixed, moving, registered - 100.0, window=(-1000.0, 1000.0), transform=tfm)
    values = darker["panels"][0][4][0]
    assert abs(float(np.nanmedian(values)) - 0.1) < 0.02


def test_qc_orientation_letters_follow_the_direction_cosines():
    img = sitk.Image(4, 4, 4, sitk.sitkFloat32)
    axial, coronal, sagittal = edge_letters(img)  # identity LPS direction
    assert (axial["left"], axial["right"], axial["top"], axial["bottom"]) == ("R", "L", "A", "P")
    assert (coronal["left"], coronal["right"], coronal["top"], coronal["bottom"]) == ("R", "L", "S", "I")
    assert (sagittal["left"], sagittal["right"], sagittal["top"], sagittal["bottom"]) == ("A", "P", "S", "I")
    img.SetDirection((-1, 0, 0, 0, -1, 0, 0, 0, 1))  # stored the RAS way: x runs to the right, y anterior
    axial = edge_letters(img)[0]
    assert (axial["left"], axial["right"], axial["top"], axial["bottom"]) == ("L", "R", "P", "A")


def test_qc_figure_with_transform_outlines_the_field_of_view(tmp_path, pair):
    fixed, moving, center = pair
    tfm = params_to_sitk(TRUE, center)
    registered = resample(moving, fixed, tfm)
    p = qc_figure(fixed, moving, registered, tmp_path / "qc.png", title="test", transform=tfm,
                  names=("ct.nii.gz", "cbct.nii.gz"))
    arr = sitk.GetArrayFromImage(sitk.ReadImage(str(p)))
    yellow = (arr[..., 0] > 200) & (arr[..., 1] > 200) & (arr[..., 2] < 80)
    assert yellow.sum() > 500  # orientation letters and the field-of-view outline are drawn in yellow


def test_summary_json_is_strict_json_when_a_case_has_no_error(tmp_path):
    """A case whose error could not be measured (NaN TRE, no confidence) is written as null in summary.json, which
    strict readers then accept; the other case's numbers are unchanged."""
    import json

    from monai_rigidreg.evaluation.report import CaseResult, write_report

    cases = [CaseResult("a", "net", [15, 0, 0, 0, 0, 0], [14, 0.5, 0, 0, 0, 0.2], 1.0, 0.1,
                        extra={"confidence": 0.9, "flagged": False}),
             CaseResult("b", "net", [0, 15, 0, 0, 0, 0], [0, 12, 0, 0, 0, 0], float("nan"), 0.3,
                        extra={"confidence": float("nan"), "flagged": True})]
    paths = write_report(cases, tmp_path)
    text = paths["json"].read_text()
    assert "NaN" not in text
    data = json.loads(text)
    by_id = {c["case_id"]: c for c in data["cases"]}
    assert by_id["b"]["tre_mm"] is None and by_id["b"]["extra"]["confidence"] is None
    assert by_id["a"]["tre_mm"] == 1.0 and by_id["a"]["extra"]["confidence"] == 0.9
