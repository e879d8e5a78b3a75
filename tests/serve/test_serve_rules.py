"""The DICOM service's decisions and bookkeeping without a network: its configuration file, how a CBCT is told from a
planning CT, when a series is whole, which planning CT a CBCT goes to, when a result is flagged, the on-disk index,
and a command line that answers without importing torch or MONAI. The service against real DICOM nodes (Orthanc,
dcmtk) is ``tests/serve/test_serve.py``."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import SimpleITK as sitk

from monai_rigidreg.cli import main
from monai_rigidreg.core.errors import InputError
from monai_rigidreg.serve._pipeline import flag_reasons
from monai_rigidreg.serve.config import EXAMPLE, Classification, CtSelection, Thresholds, config_from_dict, load_config
from monai_rigidreg.serve.rules import SeriesFacts, SliceFacts, check_series_complete, choose_ct, classify_series
from monai_rigidreg.serve.sender import backoff_s
from monai_rigidreg.serve.store import Store, header_facts

MINIMAL = {"storage_dir": "store", "allowed_ae_titles": ["CONSOLE"]}


# -- configuration -------------------------------------------------------------------------------------------------
def test_example_config_loads_and_relative_paths_follow_the_file(tmp_path):
    path = tmp_path / "etc" / "serve.json"
    path.parent.mkdir()
    path.write_text(json.dumps({**EXAMPLE, "storage_dir": "data", "log_file": "log/serve.log"}))
    cfg = load_config(path)
    assert cfg.storage_dir == path.parent.resolve() / "data" and cfg.log_file == path.parent.resolve() / "log/serve.log"
    assert cfg.allowed_ae_titles == ("CONSOLE1", "PACS") and str(cfg.destinations[0]) == "PACS@pacs.example.org:104"
    assert cfg.classification.unmarked == "ct" and cfg.ct_selection.several == "refuse"
    assert cfg.thresholds == Thresholds(0.5, 20.0, 5.0) and cfg.completion_timeout_s == 10.0
    # the printed example is the same file
    out = subprocess.run([sys.executable, "-m", "monai_rigidreg.cli", "serve", "example-config", "--storage-dir",
                          str(tmp_path / "s")], capture_output=True, text=True, check=True, env=_env())
    assert config_from_dict(json.loads(out.stdout)).storage_dir == tmp_path / "s"


@pytest.mark.parametrize(("change", "message"), [
    ({"allowed_ae_titles": []}, "at least one AE title"),
    ({"allowed_ae_titles": ["THIS_AE_TITLE_IS_TOO_LONG"]}, "AE title"),
    ({"port": 70000}, "port"),
    ({"completion_timeout_s": "10"}, "completion_timeout_s must be a number"),
    ({"colour": "blue"}, "unknown key(s) colour"),
    ({"thresholds": {"confidence": 2}}, "thresholds.confidence must be between"),
    ({"classification": {"unmarked": "guess"}}, "classification.unmarked must be one of"),
    ({"ct_selection": {"several": "first"}}, "ct_selection.several must be one of"),
    ({"destinations": [{"ae_title": "PACS", "host": "h"}]}, "destinations[0].port is required"),
    ({"classification": {"cbct_ae_titles": ["A"], "ct_ae_titles": ["A"]}}, "both CBCT and CT senders"),
    ({"classification": {"marker_fields": ["Series Description"]}}, "not a DICOM attribute keyword"),
])
def test_config_refuses_what_it_cannot_honour_with_the_key_named(change, message, tmp_path):
    path = tmp_path / "serve.json"
    path.write_text(json.dumps({**MINIMAL, **change}))
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")
                       .replace("]", r"\]")):
        load_config(path)
    path.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        load_config(path)


# -- CBCT or planning CT ---------------------------------------------------------------------------------------------
def _series(uid="1.1", **kw) -> SeriesFacts:
    base = dict(patient_id="P1", study_uid="9.1", for_uid=f"{uid}.9", modality="CT", calling_aets=("CONSOLE",))
    return SeriesFacts(series_uid=uid, **{**base, **kw})


def test_cbct_markers_and_sending_ae_decide_the_role_and_disagreement_is_refused():
    rule = Classification(cbct_ae_titles=("LINAC1",), ct_ae_titles=("CTSIM",))
    assert classify_series(_series(markers={"SeriesDescription": "Pelvis CBCT"}), rule)[0] == "cbct"
    assert classify_series(_series(markers={"ImageType": "ORIGINAL\\PRIMARY\\CONE BEAM"}), rule)[0] == "cbct"
    role, reason = classify_series(_series(), rule)
    assert role == "ct" and "no CBCT marker" in reason
    assert classify_series(_series(calling_aets=("LINAC1",)), rule)[0] == "cbct"  # the AE alone
    assert classify_series(_series(calling_aets=("CTSIM",)), rule)[0] == "ct"
    role, reason = classify_series(_series(calling_aets=("CTSIM",), markers={"SeriesDescription": "CBCT"}), rule)
    assert role is None and "planning-CT AE title" in reason and "'CBCT'" in reason
    role, reason = classify_series(_series(calling_aets=("CTSIM", "LINAC1")), rule)
    assert role is None and "both" in reason
    role, reason = classify_series(_series(modality="MR"), rule)
    assert role is None and "'MR'" in reason
    strict = Classification(unmarked="refuse")
    assert classify_series(_series(), strict)[0] is None
    assert classify_series(_series(markers={"StationName": "XVI_CBCT"}), strict)[0] == "cbct"


# -- a whole series --------------------------------------------------------------------------------------------------
def _slices(n=20, gap=2.0, skip=(), images=None, iop=(1, 0, 0, 0, 1, 0)):
    return [SliceFacts(sop_uid=f"1.{k}", ipp=(0.0, 0.0, k * gap), iop=iop, rows=64, cols=64, spacing=(2.0, 2.0),
                       images_in_acquisition=images) for k in range(n) if k not in skip]


def test_truncated_or_inconsistent_series_are_named():
    assert check_series_complete(_slices(), 16) == ""
    assert "missing slice(s): a gap of 6.00 mm" in check_series_complete(_slices(skip=(7, 8)), 16)
    assert "18 of 20 images received" in check_series_complete(_slices(images=20)[:18], 16)
    assert "only 10 image(s)" in check_series_complete(_slices(10), 16)
    assert "aborted after 20" in check_series_complete(_slices(), 16, aborted=True)
    doubled = _slices() + [SliceFacts("2.0", (0.0, 0.0, 4.0), (1, 0, 0, 0, 1, 0), 64, 64, (2.0, 2.0))]
    assert "same position" in check_series_complete(doubled, 16)
    mixed = _slices()[:-1] + _slices(iop=(1, 0, 0, 0, 0, -1))[-1:]
    assert "different orientation" in check_series_complete(mixed, 16)
    # oblique slices: the positions are measured along the normal
    tilt = (1, 0, 0, 0, np.cos(0.3), np.sin(0.3))
    normal = np.cross(tilt[:3], tilt[3:])
    oblique = [SliceFacts(f"1.{k}", tuple(k * 2.0 * normal), tilt, 64, 64, (2.0, 2.0)) for k in range(20)]
    assert check_series_complete(oblique, 16) == ""


# -- which planning CT -----------------------------------------------------------------------------------------------
def test_ct_choice_by_patient_frame_and_study_refuses_ambiguity():
    cbct = _series("5.1", study_uid="9.2", markers={"SeriesDescription": "CBCT"})
    rule = CtSelection()
    assert choose_ct(cbct, [], rule).state == "hold"
    assert choose_ct(cbct, [_series("2.1", patient_id="OTHER")], rule).state == "hold"
    one = choose_ct(cbct, [_series("2.1")], rule)
    assert one.state == "chosen" and one.ct.series_uid == "2.1" and "only planning CT" in one.reason
    # the issuer tells two patients with one ID apart
    assert choose_ct(_series("5.1", issuer="HOSP_A"), [_series("2.1", issuer="HOSP_B")], rule).state == "hold"
    shared = choose_ct(cbct, [_series("2.1", for_uid=cbct.for_uid)], rule)
    assert shared.state == "refuse" and "Frame of Reference" in shared.reason
    two = [_series("2.1", series_datetime="20260101120000", description="plan A"),
           _series("3.1", series_datetime="20260301120000", description="plan B", study_uid="9.2")]
    refused = choose_ct(cbct, two, rule)
    assert refused.state == "refuse" and "2 planning CTs" in refused.reason and "plan A" in refused.reason
    assert "--ct UID" in refused.reason
    assert choose_ct(cbct, two, CtSelection(several="newest")).ct.series_uid == "3.1"
    assert choose_ct(cbct, two, CtSelection(same_study="prefer")).ct.series_uid == "3.1"
    assert choose_ct(cbct, two[:1], CtSelection(same_study="require")).state == "hold"
    assert choose_ct(cbct, two, rule, explicit="2.1").ct.series_uid == "2.1"
    assert choose_ct(cbct, two, rule, explicit="7.7").state == "refuse"
    assert choose_ct(_series("5.1", patient_id=""), two, rule).state == "refuse"


# -- flags -----------------------------------------------------------------------------------------------------------
def test_flag_reasons_follow_the_package_flag_and_the_thresholds():
    # the couch shift at the isocentre (5.4 mm: the rotation about the CT centre moves the isocentre too) is not the
    # translation parameter (5.0 mm), and the largest angle (6.0) not the rotation's size (6.1), so the message says
    # which was compared
    summary = {"flagged": False, "confidence": 0.9, "params": dict(tx=3.0, ty=4.0, tz=0.0, rx=1.0, ry=-6.0, rz=0.0),
               "couch_shift": {"3dof": {"lateral": -3.0, "longitudinal": 2.0, "vertical": 4.0}}}
    assert flag_reasons(summary, Thresholds(0.5, 20.0, 10.0)) == []
    reasons = flag_reasons(summary, Thresholds(0.95, 4.0, 5.0))
    assert reasons == ["confidence 0.90 below 0.95", "translation 5.4 mm above 4 mm",
                       "rotation 6.0 degrees above 5 degrees"]
    no_couch = {k: v for k, v in summary.items() if k != "couch_shift"}  # where none could be given: the parameters
    assert flag_reasons(no_couch, Thresholds(None, 4.0, None)) == ["translation 5.0 mm above 4 mm"]
    assert flag_reasons(summary, Thresholds(None, 5.2, None)) != flag_reasons(no_couch, Thresholds(None, 5.2, None))
    assert "own check flagged it" in flag_reasons({**summary, "flagged": True}, Thresholds(None, None, None))[0]
    assert flag_reasons(summary, Thresholds(None, None, None)) == []


def test_send_retries_back_off_to_a_ceiling():
    assert [backoff_s(k, 5.0, 60.0) for k in (1, 2, 3, 4, 5, 9)] == [5.0, 10.0, 20.0, 40.0, 60.0, 60.0]


# -- the index ---------------------------------------------------------------------------------------------------------
def _tiny_series(folder, series_uid, n=4):
    from monai_rigidreg.serve.testing import write_ct_series

    img = sitk.GetImageFromArray(np.zeros((n, 8, 8), np.int16))
    img.SetSpacing((2.0, 2.0, 3.0))
    return write_ct_series(img, folder, patient_id="P9", study_uid="1.2.3", series_uid=series_uid,
                           frame_of_reference_uid="1.2.4", series_description="CBCT test")


def test_index_keeps_instances_once_reopens_truncated_series_and_indexes_orphans(tmp_path):
    import pydicom

    files = _tiny_series(tmp_path / "src", "1.2.5")
    store = Store(tmp_path / "store")
    facts = [header_facts(pydicom.dcmread(f)) for f in files]
    assert facts[0]["markers"] == {"SeriesDescription": "CBCT test", "ImageType": "ORIGINAL\\PRIMARY\\AXIAL"}
    first = store.add_instance(facts[0], store.write_instance_file("1.2.5", facts[0]["sop_uid"], files[0].read_bytes()),
                               "CONSOLE")
    assert first.new_series and not first.duplicate
    again = store.add_instance(facts[0], store.series_folder("1.2.5") / "x.dcm", "CONSOLE")
    assert again.duplicate and store.series("1.2.5")["n_instances"] == 1
    store.set_state("1.2.5", "invalid", "missing slices")
    reopened = store.add_instance(facts[1], store.write_instance_file("1.2.5", facts[1]["sop_uid"],
                                                                      files[1].read_bytes()), "CONSOLE2")
    assert reopened.series_state == "receiving" and store.series("1.2.5")["reason"] is None
    assert json.loads(store.series("1.2.5")["calling_aets"]) == ["CONSOLE", "CONSOLE2"]
    # a file a crash left on disk without its index entry is indexed at the next start; an unfinished one removed
    (store.series_folder("1.2.5") / f"{facts[2]['sop_uid']}.dcm").write_bytes(files[2].read_bytes())
    (store.root / "tmp" / "half.part").write_bytes(b"DICM")
    store.close()
    store = Store(tmp_path / "store")
    assert store.reconcile(lambda p: pydicom.dcmread(p, stop_before_pixels=True)) == ["1.2.5"]
    assert store.series("1.2.5")["n_instances"] == 3 and not list((store.root / "tmp").iterdir())
    slices = store.slices("1.2.5")
    assert {s.ipp[2] for s in slices} == {0.0, 3.0, 6.0} and slices[0].images_in_acquisition == 4
    store.add_trigger("1.2.5", ct_series_uid="1.2.9", role="cbct")
    assert [(t["series_uid"], t["ct_series_uid"], t["role"]) for t in store.take_triggers()] == [
        ("1.2.5", "1.2.9", "cbct")]
    assert store.take_triggers() == []
    store.close()


# -- command line ----------------------------------------------------------------------------------------------------
def _env() -> dict[str, str]:
    import monai_rigidreg

    root = str(os.path.dirname(os.path.dirname(monai_rigidreg.__file__)))
    return {**os.environ, "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")])}


def test_serve_help_imports_neither_torch_nor_monai_nor_pynetdicom():
    """``monai-rigidreg serve --help`` (and its actions' help) answers from the standard library: the service's command
    module adds nothing heavy to ``monai-rigidreg --help`` either (whose other commands' modules import torch and
    MONAI today: simulate, train)."""
    code = ("import sys, contextlib, io\nfrom monai_rigidreg.cli import main, build_parser\n"
            "for argv in (['serve', '--help'], ['serve', 'trigger', '--help'], ['serve', 'status', '--help']):\n"
            "    with contextlib.redirect_stdout(io.StringIO()) as out:\n"
            "        try:\n            main(argv)\n        except SystemExit as exc:\n            code = exc.code\n"
            "    assert code == 0 and 'usage' in out.getvalue(), argv\n"
            "import monai_rigidreg.serve.cli\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'monai', 'pynetdicom')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env(), timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_status_and_trigger_without_a_service_say_why(tmp_path, capsys):
    path = tmp_path / "serve.json"
    path.write_text(json.dumps(MINIMAL))
    assert main(["serve", "status", "--config", str(path)]) == 2
    assert "has not run with this storage_dir" in capsys.readouterr().err
    assert main(["serve", "status"]) == 2
    assert "--config FILE is required" in capsys.readouterr().err
    Store(tmp_path / "store").close()  # an index, no service: not running, and an unknown series is refused
    assert main(["serve", "status", "--config", str(path)]) == 3
    assert "NOT RUNNING" in capsys.readouterr().out
    assert main(["serve", "trigger", "--config", str(path), "--series", "1.2.3"]) == 2
    assert "no series 1.2.3 received" in capsys.readouterr().err


def test_one_service_per_storage_folder(tmp_path):
    """A second service on the same storage folder is refused before it listens (it would register the same series
    again); the first one's stop frees the folder."""
    pytest.importorskip("pynetdicom", reason="pynetdicom (the 'serve' extra) is not installed")
    from monai_rigidreg.serve.service import Service
    from monai_rigidreg.serve.testing import free_port

    cfg = config_from_dict({**MINIMAL, "storage_dir": str(tmp_path / "store"), "host": "127.0.0.1",
                            "port": free_port()})
    first = Service(cfg, registrar=object())  # a stand-in model: nothing is registered here
    first.start()
    try:
        assert first.model_ready.wait(10)
        second = Service(cfg, registrar=object())
        with pytest.raises(InputError, match=f"another service is running on this storage_dir \\(pid {os.getpid()}"):
            second.start()
        second.store.close()
    finally:
        first.stop()
    again = Service(cfg, registrar=object())
    again.start()
    again.stop()
    store = Store(tmp_path / "store", readonly=True)
    assert store.service_record()["model"] == "stopped" and any(e["text"] == "stopped" for e in store.events())
    store.close()
