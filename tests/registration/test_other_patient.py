"""Two DICOM inputs whose headers name different patients are refused before anything is registered (issue 35's
"a different patient" negative case, where the headers say it): the command exits 2 and writes nothing; with
``--allow-other-patient`` the pair is registered and the warning kept in ``result.json``."""

from __future__ import annotations

import json

import pytest
from conftest import run_cli, write_dicom_series

import monai_rigidreg
from monai_rigidreg.core.errors import InputError
from monai_rigidreg.io.volumes import load_volume
from monai_rigidreg.registration.inputs import check_same_patient

FOR_CT, FOR_CBCT = "1.2.826.0.1.3680043.2.1125.71", "1.2.826.0.1.3680043.2.1125.72"


def _dicom_pair(pair, root, ct_patient, cbct_patient, ct_issuer=None, cbct_issuer=None):
    ct, cbct = root / "ct", root / "cbct"
    write_dicom_series(load_volume(pair["fixed"]), ct, "1.2.826.0.1.3680043.2.1125.81", frame_of_reference_uid=FOR_CT,
                       patient_id=ct_patient, issuer=ct_issuer)
    write_dicom_series(load_volume(pair["moving"]), cbct, "1.2.826.0.1.3680043.2.1125.82",
                       frame_of_reference_uid=FOR_CBCT, patient_id=cbct_patient, issuer=cbct_issuer)
    return ct, cbct


def test_dicom_inputs_of_two_patients_are_refused_before_registering(pair, tmp_path, capsys, with_small_network):
    ct, cbct = _dicom_pair(pair, tmp_path, "PAT-001", "PAT-002")
    out = tmp_path / "out"
    code, err = run_cli(capsys, ["register", "--fixed", ct, "--moving", cbct, "--output-dir", out, "--no-qc"])
    assert code == 2, err
    assert "different patients" in err and "'PAT-001'" in err and "'PAT-002'" in err and "--allow-other-patient" in err
    assert not out.exists()  # nothing written, not even the folder
    # the user says they are one patient: registered, the warning in the result (and no DICOM REG across patients)
    code, err = run_cli(capsys, ["register", "--fixed", ct, "--moving", cbct, "--output-dir", out, "--no-qc",
                                 "--allow-other-patient"])
    assert code == 0, err
    result = json.loads((out / "result.json").read_text())
    warnings = result["details"]["warnings"]
    assert any("different patients" in w and "--allow-other-patient was given" in w for w in warnings), warnings
    assert not (out / "registration.dcm").exists()
    assert result["provenance"]["inputs"]["moving"]["patient_id"] == "PAT-002"


def test_the_same_patient_registers_without_a_warning_and_python_refuses_too(pair, tmp_path, small_registrar):
    ct, cbct = _dicom_pair(pair, tmp_path / "same", "PAT-001", "PAT-001")
    res = monai_rigidreg.register(ct, cbct, model=small_registrar, resample_moving=False)
    assert not any("different patients" in w for w in res.details.get("warnings", []))
    assert res.provenance["inputs"]["moving"]["patient_id"] == "PAT-001"  # the headers read once, recorded
    assert res.provenance["inputs"]["fixed"]["format"] == "dicom" and res.provenance["bundle"] == small_registrar.source
    other_ct, other_cbct = _dicom_pair(pair, tmp_path / "other", "PAT-001", "PAT-001", "HOSP-A", "HOSP-B")
    with pytest.raises(InputError, match="different patients.*issuer 'HOSP-A'"):
        monai_rigidreg.register(other_ct, other_cbct, model=small_registrar, resample_moving=False)
    res = monai_rigidreg.register(other_ct, other_cbct, model=small_registrar, resample_moving=False,
                                  allow_other_patient=True)
    assert any("different patients" in w for w in res.details["warnings"])


def test_check_same_patient_says_nothing_where_the_headers_cannot_tell():
    dicom = {"format": "dicom"}
    assert check_same_patient({**dicom, "patient_id": "A"}, {**dicom, "patient_id": ""}) == ""
    assert check_same_patient({**dicom, "patient_id": "A"}, {"format": ".nii.gz"}) == ""
    assert check_same_patient({**dicom, "patient_id": " A "}, {**dicom, "patient_id": "A"}) == ""
    assert check_same_patient({**dicom, "patient_id": "A", "issuer_of_patient_id": "H1"},
                              {**dicom, "patient_id": "A"}) == ""  # one issuer only: the IDs decide
    with pytest.raises(InputError, match="different patients"):
        check_same_patient({**dicom, "patient_id": "A"}, {**dicom, "patient_id": "B"})
    assert "registered because" in check_same_patient({**dicom, "patient_id": "A"}, {**dicom, "patient_id": "B"},
                                                      allow_other_patient=True)
