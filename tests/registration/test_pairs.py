"""Batch registration: many pairs, the network loaded once (``register --datalist`` and the bundle's evaluator),
a failing pair skipped without partial output; the bundle's MONAI infer-workflow properties."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import TINY_SIM, small_registrar_for_tests, true_motion_registrar

from monai_rigidreg.cli import main
from monai_rigidreg.core.errors import InputError
from monai_rigidreg.io import load_volume
from monai_rigidreg.registration import RigidRegistrar
from monai_rigidreg.registration.pairs import RegistrationEvaluator, registration_pairs

BUNDLE = Path(__file__).resolve().parents[2] / "bundles" / "cbct_ct_rigid"
MOTIONS = ([4.0, -3.0, 2.0, 2.0, -1.0, 3.0], [-3.0, 2.0, 4.0, -2.0, 1.0, -3.0])
"""The true motions of the datalist's two good pairs, case0 and case1 (mm, degrees, CT -> CBCT about the CT centre)."""


@pytest.fixture(scope="module")
def pairs_file(tmp_path_factory):
    """Two simulated pairs and one whose CBCT is missing, in a datalist with relative paths."""
    from monai_rigidreg.simulation import simulate_pair

    root = tmp_path_factory.mktemp("batch")
    items = []
    for k, motion in enumerate(MOTIONS):
        sim = simulate_pair(root / f"p{k}", phantom="shepp-logan-asym", params=motion, seed=10 + k,
                            **{key: v for key, v in TINY_SIM.items() if key != "preset"})
        items.append({"case_id": f"case{k}", "fixed": str(Path(sim["fixed"]).relative_to(root)),
                      "moving": str(Path(sim["moving"]).relative_to(root))})
    items.append({"case_id": "broken", "fixed": items[0]["fixed"], "moving": "p0/missing.nii.gz"})
    (root / "pairs.json").write_text(json.dumps(items))
    return root / "pairs.json"


def test_register_datalist_registers_every_pair_and_skips_the_broken_one(pairs_file, tmp_path, monkeypatch, capsys):
    # each pair's estimate replaced by its own true motion (found by its CBCT): the untrained network's identity
    # would give every case the same outputs, so pairs mixed up or an inverted transform file would pass unseen
    items = json.loads(pairs_file.read_text())[:2]
    cbcts = [sitk.GetArrayFromImage(load_volume(pairs_file.parent / item["moving"])) for item in items]

    def motion_of(fixed, moving):
        (k,) = [k for k, a in enumerate(cbcts) if np.array_equal(a, sitk.GetArrayViewFromImage(moving))]
        return MOTIONS[k]

    reg = true_motion_registrar(small_registrar_for_tests(), motion_of)
    loads = []
    monkeypatch.setattr(RigidRegistrar, "from_bundle", classmethod(lambda cls, *a, **k: loads.append(1) or reg))
    out = tmp_path / "out"
    assert main(["register", "--datalist", str(pairs_file), "--output-dir", str(out), "--no-qc"]) == 2
    err = capsys.readouterr().err
    assert "1 of 3 pairs failed and were skipped (broken)" in err and "Traceback" not in err
    assert loads == [1]  # the network is loaded once for the whole batch
    assert sorted(p.name for p in out.iterdir()) == ["case0", "case1"]  # nothing of the broken pair
    for case, motion in zip(("case0", "case1"), MOTIONS):
        result = json.loads((out / case / "result.json").read_text())
        assert [result["params"][n] for n in ("tx", "ty", "tz", "rx", "ry", "rz")] == pytest.approx(motion)
        # transform.tfm: that pair's transform, CT points -> CBCT points (Euler3D: radians, then mm)
        tfm = sitk.ReadTransform(str(out / case / "transform.tfm"))
        assert tfm.GetParameters() == pytest.approx([*np.deg2rad(motion[3:]), *motion[:3]], abs=1e-9)
        np.testing.assert_allclose(tfm.GetCenter(), result["center"], atol=1e-9)
    assert main(["register", "--datalist", str(pairs_file), "--fixed", "x", "--output-dir", str(tmp_path / "o")]) == 2


def test_evaluator_one_pair_writes_into_the_folder_itself_and_raises_its_error(pairs_file, tmp_path):
    items = registration_pairs(datalist=pairs_file, dataset_dir=pairs_file.parent)
    assert [i["case_id"] for i in items] == ["case0", "case1", "broken"]
    # a datalist of one pair still writes out/<case_id>; a single --fixed/--moving pair writes into the folder
    summary = RegistrationEvaluator(small_registrar_for_tests(), items[:1], tmp_path / "one", qc=False).run()
    assert summary["done"] == ["case0"] and (tmp_path / "one" / "case0" / "result.json").is_file()
    single = registration_pairs(items[0]["fixed"], items[0]["moving"])
    RegistrationEvaluator(small_registrar_for_tests(), single, tmp_path / "single", qc=False).run()
    assert (tmp_path / "single" / "result.json").is_file()
    with pytest.raises(InputError, match="no such file"):
        RegistrationEvaluator(small_registrar_for_tests(), registration_pairs(items[2]["fixed"], items[2]["moving"]),
                              tmp_path / "bad", qc=False).run()
    assert not (tmp_path / "bad").exists()
    # case ids that would share a folder (or hide it) are refused before any work
    clash = [{**items[0], "case_id": "pt 1"}, {**items[1], "case_id": "pt_1"}]
    with pytest.raises(InputError, match="same output folder"):
        RegistrationEvaluator(small_registrar_for_tests(), clash, tmp_path / "clash")
    dots = RegistrationEvaluator(small_registrar_for_tests(), [{**items[0], "case_id": ".."}, items[1]], tmp_path)
    assert dots.output_dir_for(0) == tmp_path / "0000"
    with pytest.raises(InputError, match="not both"):
        registration_pairs("a", "b", datalist=pairs_file)


def test_bundle_has_the_monai_infer_workflow_properties(pairs_file, tmp_path):
    from monai.bundle import ConfigWorkflow

    items = registration_pairs(datalist=pairs_file, dataset_dir=pairs_file.parent)
    wf = ConfigWorkflow(config_file=str(BUNDLE / "configs" / "inference.json"), workflow_type="infer",
                        meta_file=str(BUNDLE / "configs" / "metadata.json"), bundle_root=str(BUNDLE),
                        logging_file=None, fixed=items[0]["fixed"], moving=items[0]["moving"],
                        output_dir=str(tmp_path / "wf"))
    wf.initialize()
    assert wf.check_properties() == []
    assert isinstance(wf.evaluator, RegistrationEvaluator) and wf.evaluator.registrar.inferer is wf.inferer


def test_bundle_batch_run_with_the_shipped_weights(pairs_file, tmp_path):
    """``python -m monai.bundle run --datalist``: the good pairs registered, the broken one named, exit status 2."""
    out = tmp_path / "out"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "monai.bundle", "run", "--config_file",
                           str(BUNDLE / "configs" / "inference.json"), "--bundle_root", str(BUNDLE), "--datalist",
                           str(pairs_file), "--dataset_dir", str(pairs_file.parent), "--output_dir", str(out)],
                          capture_output=True, text=True,
                          encoding="utf-8", errors="replace", timeout=400, env=env, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "1 of 3 pairs failed" in proc.stderr and "Traceback" not in proc.stderr
    assert (out / "case0" / "qc.png").is_file() and (out / "case1" / "registration.dcm").exists() is False
