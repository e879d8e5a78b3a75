"""Couch shifts in IEC 61217 terms (monai_rigidreg.export.couch_shifts): axis tables, signs, rotation order, 3-DoF
variant."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import params_to_matrix, params_to_sitk, rotation_matrix, transform_points
from monai_rigidreg.export.couch_shifts import PATIENT_POSITIONS, CouchShifts, couch_shifts, lps_to_iec

ISO = np.array([12.0, -30.0, 45.0])
CT_CENTRE = np.array([0.5, 2.0, -8.0])

# IEC image of patient +x (left), +y (posterior), +z (superior): the module docstring's table, written out
EXPECTED_AXES = {
    "HFS": [(1, 0, 0), (0, 0, -1), (0, 1, 0)],
    "HFP": [(-1, 0, 0), (0, 0, 1), (0, 1, 0)],
    "FFS": [(-1, 0, 0), (0, 0, -1), (0, -1, 0)],
    "FFP": [(1, 0, 0), (0, 0, 1), (0, -1, 0)],
    "HFDL": [(0, 0, -1), (-1, 0, 0), (0, 1, 0)],
    "HFDR": [(0, 0, 1), (1, 0, 0), (0, 1, 0)],
    "FFDL": [(0, 0, -1), (1, 0, 0), (0, -1, 0)],
    "FFDR": [(0, 0, 1), (-1, 0, 0), (0, -1, 0)],
}


def _translation(t):
    m = np.eye(4)
    m[:3, 3] = t
    return m


@pytest.mark.parametrize("position", sorted(EXPECTED_AXES))
def test_axis_table_for_every_patient_position(position):
    a = lps_to_iec(position)
    for j, expected in enumerate(EXPECTED_AXES[position]):
        np.testing.assert_array_equal(a[:, j], expected)
    assert np.isclose(np.linalg.det(a), 1.0)  # a proper rotation: IEC and LPS are both right-handed
    np.testing.assert_array_equal(lps_to_iec(position.lower() + " "), a)  # DICOM strings may be padded


def test_table_covers_the_supported_positions():
    assert set(PATIENT_POSITIONS) == set(EXPECTED_AXES)


def test_pure_translation_hfs_signs():
    # patient found 3 mm to their left, 4 mm anterior (y = -4), 5 mm superior
    s = couch_shifts(_translation([3.0, -4.0, 5.0]), "HFS", ISO)
    # couch: 3 mm to the patient's right (-X), 4 mm down, 5 mm away from the gantry (feet-ward)
    np.testing.assert_allclose(s.translation, [-3.0, -5.0, -4.0], atol=1e-12)
    np.testing.assert_allclose(s.rotation, 0.0, atol=1e-12)
    np.testing.assert_allclose(s.translation_3dof, s.translation, atol=1e-12)
    np.testing.assert_allclose(s.isocentre_displacement, [3.0, -4.0, 5.0], atol=1e-12)
    assert not s.patient_position_assumed and s.patient_position == "HFS"


def test_pure_translation_ffs_signs():
    s = couch_shifts(_translation([3.0, -4.0, 5.0]), "FFS", ISO)
    # feet first: the patient's left is the observer's left (-X), superior is away from the gantry (-Y)
    np.testing.assert_allclose(s.translation, [3.0, 5.0, -4.0], atol=1e-12)
    np.testing.assert_allclose(s.rotation, 0.0, atol=1e-12)


def test_pure_translation_hfp_signs():
    s = couch_shifts(_translation([3.0, -4.0, 5.0]), "HFP", ISO)
    # prone: anterior is down, so anatomy 4 mm anterior sits 4 mm low and the couch goes up
    np.testing.assert_allclose(s.translation, [3.0, -5.0, 4.0], atol=1e-12)
    np.testing.assert_allclose(s.rotation, 0.0, atol=1e-12)


@pytest.mark.parametrize("position", sorted(EXPECTED_AXES))
def test_translation_magnitudes_equal_the_displacement(position):
    t = np.array([1.5, -2.5, 7.0])
    s = couch_shifts(_translation(t), position, ISO)
    np.testing.assert_allclose(s.translation, lps_to_iec(position) @ -t, atol=1e-12)
    np.testing.assert_allclose(np.sort(np.abs(s.translation)), np.sort(np.abs(t)), atol=1e-12)


@pytest.mark.parametrize(
    "lps_params, expected",
    [
        # HFS: patient x (left) = IEC X, patient y (posterior) = IEC -Z, patient z (superior) = IEC Y
        ([0, 0, 0, 3.0, 0, 0], (-3.0, 0.0, 0.0)),  # rx: patient pitched +3 about X -> pitch -3
        ([0, 0, 0, 0, 3.0, 0], (0.0, 0.0, 3.0)),  # ry: about -Z, i.e. -3 about Z -> couch rotation +3
        ([0, 0, 0, 0, 0, 3.0], (0.0, -3.0, 0.0)),  # rz: about +Y -> roll -3
    ],
)
def test_single_axis_rotation_about_the_isocentre_hfs(lps_params, expected):
    s = couch_shifts(params_to_matrix(lps_params, ISO), "HFS", ISO)
    np.testing.assert_allclose(s.translation, 0.0, atol=1e-9)
    np.testing.assert_allclose(s.rotation, expected, atol=1e-9)


@pytest.mark.parametrize("position", ["HFS", "FFP", "HFDL"])
def test_rotation_about_the_isocentre_recovers_the_angles_in_the_stated_order(position):
    pitch, roll, yaw = 4.0, -6.0, 9.0
    rc_iec = rotation_matrix(*np.deg2rad([pitch, roll, yaw]))  # Rz(yaw) @ Rx(pitch) @ Ry(roll)
    a = lps_to_iec(position)
    r_lps = (a.T @ rc_iec @ a).T  # the patient's rotation is the inverse of the correction
    m = np.eye(4)
    m[:3, :3] = r_lps
    m[:3, 3] = ISO - r_lps @ ISO  # about the isocentre
    s = couch_shifts(m, position, ISO)
    np.testing.assert_allclose(s.translation, 0.0, atol=1e-9)
    np.testing.assert_allclose(s.translation_3dof, 0.0, atol=1e-9)
    np.testing.assert_allclose(s.rotation, [pitch, roll, yaw], atol=1e-9)


def _correction_in_lps(s: CouchShifts, position: str) -> np.ndarray:
    """The couch correction as a 4x4 in LPS: translate by the shifts, then rotate about the isocentre."""
    a = lps_to_iec(position)
    rc_iec = rotation_matrix(*np.deg2rad(s.rotation))
    q = np.eye(4)
    q[:3, :3] = a
    q[:3, 3] = -a @ np.asarray(s.isocentre)  # LPS -> IEC (origin at the isocentre)
    c_iec = np.eye(4)
    c_iec[:3, :3] = rc_iec
    c_iec[:3, 3] = rc_iec @ s.translation
    return np.linalg.inv(q) @ c_iec @ q


@pytest.mark.parametrize("position", sorted(EXPECTED_AXES))
def test_rotation_about_the_ct_centre_with_the_isocentre_elsewhere(position):
    params = [2.0, -1.0, 3.0, 2.5, -3.0, 4.0]
    m = params_to_matrix(params, CT_CENTRE)
    s = couch_shifts(params_to_sitk(params, CT_CENTRE), position, ISO)  # a SimpleITK transform works too
    d = transform_points(m, ISO)[0] - ISO
    np.testing.assert_allclose(s.isocentre_displacement, d, atol=1e-9)
    np.testing.assert_allclose(s.translation_3dof, lps_to_iec(position) @ -d, atol=1e-9)
    assert np.linalg.norm(d - params[:3]) > 1.0  # the rotation about the CT centre moves the isocentre
    # 3-DoF: the isocentre anatomy lands on the isocentre
    seen = transform_points(m, ISO)[0]
    np.testing.assert_allclose(seen + lps_to_iec(position).T @ s.translation_3dof, ISO, atol=1e-9)
    # 6-DoF: translation then rotation about the isocentre undoes T for every anatomy point
    pts = np.random.default_rng(0).uniform(-100, 100, size=(20, 3))
    corrected = transform_points(_correction_in_lps(s, position), transform_points(m, pts))
    np.testing.assert_allclose(corrected, pts, atol=1e-9)
    # a couch that rotates first needs the rotated translation
    rc = rotation_matrix(*np.deg2rad(s.rotation))
    np.testing.assert_allclose(s.translation_if_rotation_first, rc @ s.translation, atol=1e-12)


def test_missing_patient_position_assumes_hfs(caplog):
    m = _translation([1.0, 2.0, 3.0])
    with caplog.at_level(logging.WARNING, logger="monai_rigidreg.export.couch_shifts"):
        s = couch_shifts(m, None, ISO)
    assert s.patient_position == "HFS" and s.patient_position_assumed
    assert any("HFS" in r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    np.testing.assert_allclose(s.translation, couch_shifts(m, "HFS", ISO).translation)
    assert couch_shifts(m, "  ", ISO).patient_position_assumed  # an empty DICOM value counts as missing
    d = s.to_dict()
    assert d["patient_position"] == "HFS" and d["patient_position_assumed"] is True
    json.dumps(d)


def test_to_dict_states_the_conventions():
    s = couch_shifts(params_to_matrix([1, 2, 3, 1, 2, 3], CT_CENTRE), "FFS", ISO)
    d = json.loads(json.dumps(s.to_dict()))
    assert "Rz(couch_rotation) @ Rx(pitch) @ Ry(roll)" in d["rotation_order"]
    assert "toward the gantry" in d["convention"]
    assert set(d["6dof"]) == {"lateral", "longitudinal", "vertical", "pitch", "roll", "couch_rotation"}
    assert set(d["3dof"]) == {"lateral", "longitudinal", "vertical"}
    np.testing.assert_allclose(d["isocentre_lps_mm"], ISO)
    assert d["patient_position"] == "FFS" and d["patient_position_assumed"] is False


@pytest.mark.parametrize("position", ["XYZ", "LFS", "SITTING", "HF"])
def test_unknown_patient_position_is_an_input_error(position):
    with pytest.raises(InputError, match="patient position"):
        couch_shifts(np.eye(4), position, ISO)


def test_bad_transform_or_isocentre_is_an_input_error():
    with pytest.raises(InputError, match="rigid"):
        couch_shifts(np.diag([2.0, 1.0, 1.0, 1.0]), "HFS", ISO)
    with pytest.raises(InputError, match="4x4"):
        couch_shifts(np.eye(3), "HFS", ISO)
    with pytest.raises(InputError, match="isocentre"):
        couch_shifts(np.eye(4), "HFS", [1.0, 2.0])
