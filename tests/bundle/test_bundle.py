"""The MONAI bundle: metadata, offline inference with the shipped weights, the regression-only switch, TorchScript
export compared with the eager model, CPU training with checkpoint + resume and torchrun (gloo) (the last two
``slow``)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

BUNDLE = Path(__file__).resolve().parents[2] / "bundles" / "cbct_ct_rigid"
TINY_NET = ["network_size=[32,32,32]", "network_spacing=[8.0,8.0,8.0]", "network_def#regression#channels=[4,8,8]",
            "network_def#regression#feat_channels=[8,8]", "context_size=[48,48,48]"]
TINY = [a for kv in TINY_NET for a in (f"--{kv.split('=')[0]}", kv.split("=", 1)[1])] + [
    "--num_workers", "0", "--cascade_steps", "2"]

# What MONAI's model-zoo metadata schema requires (the schema itself is downloaded by verify_metadata, which
# needs a network; this is its required-field content, checked offline).
METADATA_SCHEMA = {
    "type": "object",
    "required": ["schema", "version", "changelog", "monai_version", "pytorch_version", "numpy_version",
                 "required_packages_version", "task", "description", "authors", "copyright", "network_data_format"],
    "properties": {
        "network_data_format": {
            "type": "object",
            "required": ["inputs", "outputs"],
            "properties": {
                "inputs": {"type": "object", "additionalProperties": {"$ref": "#/definitions/tensor"}},
                "outputs": {"type": "object", "additionalProperties": {"$ref": "#/definitions/tensor"}},
            },
        }
    },
    "definitions": {
        "tensor": {
            "type": "object",
            "required": ["type", "format", "num_channels", "spatial_shape", "dtype", "value_range", "is_patch_data",
                         "channel_def"],
        }
    },
}


def run_bundle(args: list[str], cwd: Path, timeout: int = 400, module: str = "monai.bundle") -> str:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, capture_output=True, text=True,
                          encoding="utf-8", errors="replace",
                          timeout=timeout, env=env)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    return out


@pytest.fixture(scope="module")
def shipped_bundle(tmp_path_factory):
    """A copy of the shipped bundle with its weights (nothing is written into the checkout)."""
    dst = tmp_path_factory.mktemp("shipped") / "cbct_ct_rigid"
    shutil.copytree(BUNDLE, dst, ignore=shutil.ignore_patterns("*.ts", "runs", "eval"))
    return dst


@pytest.fixture(scope="module")
def bundle_copy(tmp_path_factory):
    dst = tmp_path_factory.mktemp("bundle") / "cbct_ct_rigid"
    shutil.copytree(BUNDLE, dst, ignore=shutil.ignore_patterns("model.pt", "*.ts", "runs", "eval"))
    (dst / "models").mkdir(exist_ok=True)
    return dst


def test_metadata_has_model_zoo_fields():
    jsonschema = pytest.importorskip("jsonschema")
    meta = json.loads((BUNDLE / "configs" / "metadata.json").read_text())
    jsonschema.validate(meta, METADATA_SCHEMA)
    fmt = meta["network_data_format"]
    assert fmt["inputs"]["image"]["num_channels"] == 3  # moving, fixed and the CT context (ContextCorrelationNet)
    channels = fmt["inputs"]["image"]["channel_def"]
    assert (channels["0"], channels["1"]) == ("moving CBCT", "fixed CT")
    assert channels["2"].startswith("fixed CT on the context")
    assert fmt["outputs"]["pred"]["num_channels"] == 6
    inference = json.loads((BUNDLE / "configs" / "inference.json").read_text())
    assert fmt["inputs"]["image"]["spatial_shape"] == inference["network_size"]


def test_shipped_weights_load_and_are_small():
    model = BUNDLE / "models" / "model.pt"
    if not model.is_file():
        pytest.fail("the bundle ships no models/model.pt")
    assert model.stat().st_size < 20 * 2**20
    from monai_rigidreg.bundle import load_bundle_network

    net, settings = load_bundle_network(BUNDLE)
    assert settings["network_size"] == json.loads((BUNDLE / "configs" / "inference.json").read_text())["network_size"]
    assert sum(p.numel() for p in net.parameters()) > 0
    # the composed network as shipped: the learned regression, then the weight-free fine stage at the grid spacing
    from monai_rigidreg.networks import GaussNewtonStage, TwoStageRigidNet

    assert isinstance(net, TwoStageRigidNet) and isinstance(net.fine_stage, GaussNewtonStage)
    assert net.fine_stage.grid_spacing == tuple(settings["network_spacing"])
    assert sum(p.numel() for p in net.fine_stage.parameters()) == 0


@pytest.mark.slow
def test_train_writes_checkpoint_and_resumes(bundle_copy, tiny_dataset, tmp_path):
    common = ["run", "--config_file", str(bundle_copy / "configs" / "train.json"), "--bundle_root", str(bundle_copy),
              "--datalist", str(tiny_dataset), "--val_datalist", str(tiny_dataset), "--epoch_length", "2",
              "--output_dir", str(tmp_path / "runs"), "--ckpt_dir", str(tmp_path / "ckpt"), *TINY]
    run_bundle([*common, "--epochs", "1"], bundle_copy)
    assert (tmp_path / "ckpt" / "checkpoint_checkpoint_epoch=1.pt").is_file()
    assert (tmp_path / "ckpt" / "model.pt").is_file()  # best validation TRE so far
    history = json.loads((tmp_path / "runs" / "history.json").read_text())
    assert history[0]["epoch"] == 1 and "val_tre" in history[0] and "loss_sup" in history[0]
    assert (tmp_path / "runs" / "curves.png").is_file()
    out = run_bundle([*common, "--epochs", "2", "--resume", "True"], bundle_copy)
    assert "resuming from" in out
    assert "epoch 1 until 2 epochs" in out  # ignite continues after the restored epoch
    assert (tmp_path / "ckpt" / "checkpoint_checkpoint_epoch=2.pt").is_file()
    assert len(json.loads((tmp_path / "runs" / "history.json").read_text())) == 1  # this run's single epoch
    # the coarse level's estimate reached the criterion as a value of the staged inferer (deep supervision)
    assert "loss_level0" in json.loads((tmp_path / "runs" / "history.json").read_text())[0]


@pytest.mark.slow
def test_torchrun_two_processes_gloo(bundle_copy, tiny_dataset, tmp_path):
    configs = json.dumps([str(bundle_copy / "configs" / "train.json"),
                          str(bundle_copy / "configs" / "multi_gpu_train.json")])
    out = run_bundle(["--standalone", "--nproc_per_node=2", "-m", "monai.bundle", "run", "--config_file", configs,
                      "--bundle_root", str(bundle_copy), "--datalist", str(tiny_dataset), "--val_datalist",
                      str(tiny_dataset), "--epochs", "1", "--epoch_length", "2", "--output_dir", str(tmp_path / "r"),
                      "--ckpt_dir", str(tmp_path / "c"), "--device", "$torch.device('cpu')", *TINY],
                     bundle_copy, module="torch.distributed.run")
    assert (tmp_path / "c" / "checkpoint_checkpoint_epoch=1.pt").is_file()  # written by rank 0
    assert out.count("Epoch[1] Complete") >= 2  # both ranks trained


def _cases_csv(path: Path) -> list[dict[str, str]]:
    import csv

    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow
def test_torchrun_evaluation_registers_each_case_once_as_one_process_does(shipped_bundle, tiny_dataset, tmp_path):
    """``multi_gpu_evaluate.json`` under ``torchrun --nproc_per_node=2`` (gloo on the CPU): the three cases split
    between the ranks (2 + 1: no padding), every case once in the merged report, with the numbers of the same
    evaluation in one process; the report (markdown, html, overlays) is written once, by rank 0."""
    cfg = shipped_bundle / "configs"
    one = json.dumps([str(cfg / "inference.json"), str(cfg / "evaluate.json")])
    two = json.dumps([str(cfg / "inference.json"), str(cfg / "evaluate.json"), str(cfg / "multi_gpu_evaluate.json")])
    common = ["--bundle_root", str(shipped_bundle), "--datalist", str(tiny_dataset), "--device", "$torch.device('cpu')"]
    run_bundle(["run", "--config_file", one, "--output_dir", str(tmp_path / "one"), *common], shipped_bundle)
    out = run_bundle(["--standalone", "--nproc_per_node=2", "-m", "monai.bundle", "run", "--config_file", two,
                      "--output_dir", str(tmp_path / "two"), *common], shipped_bundle, module="torch.distributed.run")
    single, merged = _cases_csv(tmp_path / "one" / "cases.csv"), _cases_csv(tmp_path / "two" / "cases.csv")
    ids = [json.loads(Path(tiny_dataset).read_text())["training"][i]["case_id"] for i in range(3)]
    assert [(r["case_id"], r["method"]) for r in merged] == [(i, "network") for i in ids]  # each once, in order
    for a, b in zip(single, merged):
        for k in a:
            if k.startswith(("pred_", "true_", "abs_err_")) or k in ("tre_mm", "success", "confidence", "flagged"):
                assert a[k] == b[k], (a["case_id"], k)
    report = (tmp_path / "two" / "report.md").read_text(encoding="utf-8")
    assert out.count(report.splitlines()[0]) == 1  # printed once, by rank 0
    summary = json.loads((tmp_path / "two" / "summary.json").read_text())
    assert summary["summary"]["network"]["n"] == 3
    html = (tmp_path / "two" / "report.html").read_text(encoding="utf-8")
    pngs = sorted(p.name for p in (tmp_path / "two" / "report_files").iterdir())
    assert len(pngs) == 3 and all(name in html for name in pngs)  # overlays of both ranks, one per case
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging folder left


def _inference(bundle: Path, pair: dict, out_dir: Path, *extra: str) -> dict:
    run_bundle(["run", "--config_file", str(bundle / "configs" / "inference.json"), "--bundle_root", str(bundle),
                "--fixed", str(pair["fixed"]), "--moving", str(pair["moving"]), "--output_dir", str(out_dir), *extra],
               bundle)
    return json.loads((out_dir / "result.json").read_text())


def test_inference_registers_offline_with_the_shipped_weights(shipped_bundle, fast_pair, tmp_path):
    """``python -m monai.bundle run`` on the inference config: the four outputs, consistent with each other, and the
    known motion of the simulated pair recovered; ``--fine_stage False`` runs the regression alone."""
    from conftest import KNOWN_MOTION

    from monai_rigidreg.core.geometry import target_registration_error
    from monai_rigidreg.evaluation.evaluate import body_points
    from monai_rigidreg.io import load_volume

    result = _inference(shipped_bundle, fast_pair, tmp_path / "out")
    for name in ("transform.tfm", "registered.nii.gz", "result.json", "qc.png"):
        assert (tmp_path / "out" / name).is_file(), name
    names = ("tx", "ty", "tz", "rx", "ry", "rz")
    params = [result["params"][k] for k in names]
    # transform.tfm: the whole estimate (Euler3D: rx, ry, rz in radians, then mm) about result.json's centre, not
    # its translations alone (a rotation convention wrong there would not show)
    tfm = sitk.ReadTransform(str(tmp_path / "out" / "transform.tfm"))
    np.testing.assert_allclose(tfm.GetParameters(), [*np.deg2rad(params[3:]), *params[:3]], atol=1e-6)
    np.testing.assert_allclose(tfm.GetFixedParameters()[:3], result["center"], atol=1e-6)
    assert np.abs(params[3:]).min() > 1.0  # rotated about every axis (KNOWN_MOTION)
    # ... and registered.nii.gz is the CBCT resampled on the CT's grid under it
    fixed, moving = load_volume(fast_pair["fixed"]), load_volume(fast_pair["moving"])
    again = sitk.Resample(moving, fixed, tfm, sitk.sitkLinear, float(sitk.GetArrayViewFromImage(moving).min()))
    np.testing.assert_allclose(sitk.GetArrayFromImage(again),
                               sitk.GetArrayFromImage(load_volume(tmp_path / "out" / "registered.nii.gz")), atol=1e-3)
    pts = body_points(fixed)
    tre = target_registration_error(params, KNOWN_MOTION, pts, center=result["center"])
    assert tre < 2.0  # as register() on the same pair (tests/test_register.py)
    # the regression alone (tests/test_alignment.py pins that the switch returns exactly its estimate): another answer
    alone = _inference(shipped_bundle, fast_pair, tmp_path / "alone", "--fine_stage", "False")
    assert np.abs(np.subtract([alone["params"][k] for k in names], [result["params"][k] for k in names])).max() > 0.01


def test_export_by_tracing_matches_the_eager_model(shipped_bundle, tmp_path):
    """``verify_net_in_out`` and ``ckpt_export --use_trace`` on the shipped weights; the TorchScript model gives
    the eager model's estimate on a structured input with a known shift."""
    import torch

    from monai_rigidreg.bundle import load_bundle_network
    from monai_rigidreg.core.warp import warp_volume_params

    cfg = ["--meta_file", str(shipped_bundle / "configs" / "metadata.json"), "--config_file",
           str(shipped_bundle / "configs" / "inference.json"), "--bundle_root", str(shipped_bundle)]
    run_bundle(["verify_net_in_out", "network_def", *cfg, "--n", "1", "--any", "64"], shipped_bundle)
    ts = tmp_path / "model.ts"
    # the fine stage builds its grid from the input shape: exported by tracing at the network grid size
    run_bundle(["ckpt_export", "network_def", "--filepath", str(ts), "--ckpt_file",
                str(shipped_bundle / "models" / "model.pt"), "--use_trace", "True", "--input_shape",
                "[1, 3, 64, 64, 64]", *cfg], shipped_bundle)
    traced = torch.jit.load(str(ts))
    eager, settings = load_bundle_network(shipped_bundle)
    grid_size = tuple(settings["network_size"])
    from monai_rigidreg.core.geometry import Grid

    grid = Grid.centered(grid_size, settings["network_spacing"])
    g = torch.Generator().manual_seed(0)
    fixed = torch.nn.functional.avg_pool3d(torch.rand(1, 1, *grid_size, generator=g), 5, 1, 2)
    fixed = (fixed - fixed.min()) / (fixed.max() - fixed.min())
    moving = warp_volume_params(fixed, torch.tensor([[4.0, -2.0, 3.0, 2.0, 0.0, -3.0]]), grid)
    # the CT context (channel 2): the fixed volume pooled onto the context grid, as a network without one builds it
    from monai_rigidreg.networks.context_net import context_from_fixed

    x = torch.cat([moving, fixed, context_from_fixed(fixed, 2, grid_size)], 1)
    with torch.no_grad():
        want = eager(x)
        got = traced(x)
    assert tuple(got.shape) == (1, 6)
    torch.testing.assert_close(got, want, atol=1e-3, rtol=0)


def _sha256(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_train_with_default_folders_leaves_the_installed_weights_alone_and_runs_without_tensorboard(
        tiny_dataset, tmp_path):
    """``monai-rigidreg train`` with its default folders writes under the current directory (never into the
    installed bundle), and trains, with a warning, where TensorBoard is not importable."""
    from monai_rigidreg.bundle import default_bundle_path

    shipped = default_bundle_path() / "models" / "model.pt"
    before = _sha256(shipped)
    stub = tmp_path / "no_tensorboard" / "tensorboard"
    stub.mkdir(parents=True)
    (stub / "__init__.py").write_text("raise ImportError('simulated: tensorboard is not installed')\n")
    work = tmp_path / "work"
    work.mkdir()
    # the stub first, then whatever the caller's PYTHONPATH holds (a checkout under test that is not the installed one)
    env = {**os.environ, "OMP_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join([str(stub.parent), *filter(None, [os.environ.get("PYTHONPATH")])])}
    sets = [*TINY_NET, "cascade_steps=1", "log_every=1"]
    cmd = [sys.executable, "-m", "monai_rigidreg.cli", "train", "--datalist", str(tiny_dataset), "--val-datalist",
           str(tiny_dataset), "--epochs", "1", "--epoch-length", "1", "--num-workers", "0", "--set", *sets]
    proc = subprocess.run(cmd, cwd=work, capture_output=True, text=True,
                          encoding="utf-8", errors="replace", timeout=400, env=env)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert "TensorBoard is not installed" in out and "Traceback" not in out
    assert "Iter: 1/1" in out  # per-iteration progress (every log_every iterations)
    assert (work / "runs" / "models" / "model.pt").is_file()
    assert (work / "runs" / "history.json").is_file() and not (work / "runs" / "tensorboard").exists()
    assert _sha256(shipped) == before
    # asking for the installed bundle's folder is refused before anything runs
    proc = subprocess.run([*cmd[:4], "--ckpt-dir", str(shipped.parent), *cmd[4:]], cwd=work, capture_output=True,
                          text=True, encoding="utf-8", errors="replace", timeout=120, env=env)
    assert proc.returncode == 2 and "inside the installed monai-rigidreg package" in proc.stderr
    assert "Traceback" not in proc.stderr and _sha256(shipped) == before


# -- the config reader of the register path (no MONAI import) ------------------------------------------------------


def test_plain_reader_builds_what_monai_config_parser_builds():
    """The shipped inference.json through PlainConfig and through MONAI's ConfigParser: the same settings, the same
    network (module tree, weights loaded strictly, identical estimate on a random pair)."""
    import torch
    from monai.bundle import ConfigParser

    from monai_rigidreg.bundle.config import PlainConfig, open_config
    from monai_rigidreg.bundle.loader import SETTING_KEYS, load_bundle_network

    cfg = BUNDLE / "configs" / "inference.json"
    plain = open_config(cfg, (*SETTING_KEYS, "network_def"))
    assert isinstance(plain, PlainConfig)
    monai_parser = ConfigParser()
    monai_parser.read_config(str(cfg))
    for key in SETTING_KEYS:
        assert plain.get_parsed_content(key) == monai_parser.get_parsed_content(key)
    ours, _ = load_bundle_network()
    theirs = monai_parser.get_parsed_content("network_def")
    assert repr(ours) == repr(theirs)
    theirs.load_state_dict(ours.state_dict())  # strict: the same keys and shapes
    theirs.eval()
    gen = torch.Generator().manual_seed(3)
    fixed, moving = torch.rand(1, 1, 64, 64, 64, generator=gen), torch.rand(1, 1, 64, 64, 64, generator=gen)
    with torch.no_grad():
        torch.testing.assert_close(ours.forward_pair(moving, fixed), theirs.forward_pair(moving, fixed))


def test_plain_reader_subset_and_fallback_to_monai(tmp_path):
    """References with nested keys resolve; MONAI syntax outside the subset (expressions, component keys, circular
    or missing references, YAML) is refused by PlainConfig, and open_config then reads the file with MONAI."""
    from monai.bundle import ConfigParser

    from monai_rigidreg.bundle.config import NotPlain, PlainConfig, open_config

    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({
        "size": [4, 5], "first": "@size#0", "last": "@size#-1", "nested": {"a": {"b": "@first"}},
        "grid": {"_target_": "monai_rigidreg.core.geometry.Grid.centered", "size": [2, 3, 4], "spacing": "@nested#a#c"},
        "expr": "$1 + 1", "disabled": {"_target_": "dict", "_disabled_": True}, "loop": "@loop2", "loop2": "@loop",
        "missing": "@nowhere"}))
    cfg.write_text(cfg.read_text().replace('"spacing": "@nested#a#c"', '"spacing": [1.0, 2.0, 3.0]'))
    plain = PlainConfig(cfg)
    assert plain.get_parsed_content("first") == 4 and plain.get_parsed_content("last") == 5
    assert plain.get_parsed_content("nested#a#b") == 4
    grid = plain.get_parsed_content("grid")
    assert grid.size == (2, 3, 4) and grid.spacing == (1.0, 2.0, 3.0)
    assert "nested#a" in plain and "nested#z" not in plain and "size#2" not in plain
    for key in ("expr", "disabled", "loop", "missing"):
        with pytest.raises(NotPlain):
            plain.get_parsed_content(key)
    assert isinstance(open_config(cfg, ("first", "grid")), PlainConfig)
    fallback = open_config(cfg, ("first", "expr"))
    assert isinstance(fallback, ConfigParser) and fallback.get_parsed_content("expr") == 2
    yaml_cfg = tmp_path / "c.yaml"
    yaml_cfg.write_text("size: [4, 5]\n")
    with pytest.raises(NotPlain):
        PlainConfig(yaml_cfg)


def test_yaml_bundle_config_goes_to_monai(tmp_path):
    """A YAML config is MONAI's to read (it needs PyYAML, an optional dependency of MONAI's)."""
    pytest.importorskip("yaml", reason="MONAI reads YAML configs with PyYAML, which is not installed here")
    from monai.bundle import ConfigParser

    from monai_rigidreg.bundle.config import open_config

    yaml_cfg = tmp_path / "c.yaml"
    yaml_cfg.write_text("size: [4, 5]\n")
    parser = open_config(yaml_cfg, ("size",))
    assert isinstance(parser, ConfigParser) and parser.get_parsed_content("size") == [4, 5]


def test_bundle_with_an_expression_setting_loads_through_monai(tmp_path):
    """A user's bundle whose setting is a MONAI expression still loads (MONAI's parser), with its value."""
    from monai_rigidreg.bundle import load_bundle_network

    bundle = tmp_path / "b"
    shutil.copytree(BUNDLE, bundle, ignore=shutil.ignore_patterns("eval*", "runs"))
    cfg = json.loads((bundle / "configs" / "inference.json").read_text())
    cfg["cascade_steps"] = "$1 + 1"
    (bundle / "configs" / "inference.json").write_text(json.dumps(cfg))
    _, settings = load_bundle_network(bundle)
    assert settings["cascade_steps"] == 2


def test_bundle_switches_and_device_are_checked_before_anything_runs(shipped_bundle, fast_pair, tmp_path):
    """monai.bundle's command line reads ``--refine false`` as the text "false" (true in Python: the refinement had
    run), so a switch that is not a boolean, or a device torch does not know, ends the run with one line and exit
    status 2 before the network is built; evaluate.json's bad datalist or existing report likewise (were
    tracebacks)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    base = [sys.executable, "-m", "monai.bundle", "run", "--bundle_root", str(shipped_bundle)]
    infer = [*base, "--config_file", str(shipped_bundle / "configs" / "inference.json"), "--fixed",
             str(fast_pair["fixed"]), "--moving", str(fast_pair["moving"]), "--output_dir", str(tmp_path / "out")]
    for extra, expected in ((["--refine", "false"], "--refine must be True or False"),
                            (["--fine_stage", "maybe"], "--fine_stage must be True or False"),
                            (["--device", "tpu7"], "device 'tpu7' is not a device name")):
        proc = subprocess.run([*infer, *extra], capture_output=True, text=True, timeout=300, env=env,
                              cwd=shipped_bundle)
        assert proc.returncode == 2 and expected in proc.stderr.strip().splitlines()[-1], proc.stderr[-2000:]
        assert "Traceback" not in proc.stderr and not (tmp_path / "out").exists()
    configs = json.dumps([str(shipped_bundle / "configs" / "inference.json"),
                          str(shipped_bundle / "configs" / "evaluate.json")])
    evaluate = [*base, "--config_file", configs, "--output_dir", str(tmp_path / "eval")]
    proc = subprocess.run([*evaluate, "--datalist", str(tmp_path / "missing.json")], capture_output=True, text=True,
                          timeout=300, env=env, cwd=shipped_bundle)
    assert proc.returncode == 2 and "no such datalist file" in proc.stderr, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    report = tmp_path / "eval"
    report.mkdir()
    (report / "report.md").write_text("an earlier report")
    datalist = tmp_path / "one.json"
    datalist.write_text(json.dumps({"training": [{"fixed": str(fast_pair["fixed"]), "moving": str(fast_pair["moving"]),
                                                  "params": [0.0] * 6}]}))
    proc = subprocess.run([*evaluate, "--datalist", str(datalist)], capture_output=True, text=True, timeout=300,
                          env=env, cwd=shipped_bundle)
    assert proc.returncode == 2 and "already exists" in proc.stderr, proc.stderr[-2000:]
    assert (report / "report.md").read_text() == "an earlier report"
