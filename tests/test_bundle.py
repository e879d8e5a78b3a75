"""The MONAI bundle: metadata, CPU training with checkpoint + resume, torchrun (gloo), offline inference, export."""

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

BUNDLE = Path(__file__).resolve().parents[1] / "bundles" / "cbct_ct_rigid"
TINY = ["--network_size", "[32,32,32]", "--network_spacing", "[8.0,8.0,8.0]", "--network_def#pool_size", "2",
        "--network_def#channels", "[4,8,8,8]", "--num_workers", "0", "--cascade_steps", "2"]

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
                          timeout=timeout, env=env)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    return out


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
    assert fmt["inputs"]["image"]["num_channels"] == 2
    assert fmt["inputs"]["image"]["channel_def"] == {"0": "moving CBCT", "1": "fixed CT"}
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
    shutil.copy(tmp_path / "ckpt" / "model.pt", bundle_copy / "models" / "model.pt")


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


def test_inference_registers_offline_and_exports(bundle_copy, tiny_dataset, tmp_path):
    if not (bundle_copy / "models" / "model.pt").is_file():
        pytest.skip("needs the checkpoint of test_train_writes_checkpoint_and_resumes")
    item = json.loads(Path(tiny_dataset).read_text())["training"][0]
    root = Path(tiny_dataset).parent
    out_dir = tmp_path / "out"
    run_bundle(["run", "--config_file", str(bundle_copy / "configs" / "inference.json"), "--bundle_root",
                str(bundle_copy), "--fixed", str(root / item["fixed"]), "--moving", str(root / item["moving"]),
                "--output_dir", str(out_dir), *[a for a in TINY if a not in ("--num_workers", "0")]], bundle_copy)
    for name in ("transform.tfm", "registered.nii.gz", "result.json", "qc.png"):
        assert (out_dir / name).is_file(), name
    tfm = sitk.ReadTransform(str(out_dir / "transform.tfm"))
    result = json.loads((out_dir / "result.json").read_text())
    np.testing.assert_allclose(tfm.GetParameters()[3:], [result["params"][k] for k in ("tx", "ty", "tz")], atol=1e-6)
    cfg = ["--meta_file", str(bundle_copy / "configs" / "metadata.json"), "--config_file",
           str(bundle_copy / "configs" / "inference.json"), "--bundle_root", str(bundle_copy),
           "--network_def#channels", "[4,8,8,8]", "--network_def#pool_size", "2"]
    # the metadata's spatial shape must match the network: use a copy of the metadata with the tiny shape
    meta = json.loads((bundle_copy / "configs" / "metadata.json").read_text())
    meta["network_data_format"]["inputs"]["image"]["spatial_shape"] = [32, 32, 32]
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    cfg[1] = str(tmp_path / "meta.json")
    run_bundle(["verify_net_in_out", "network_def", *cfg, "--n", "1", "--any", "32"], bundle_copy)
    ts = tmp_path / "model.ts"
    # the alignment stage builds its grid from the input shape: exported by tracing at the network grid size
    run_bundle(["ckpt_export", "network_def", "--filepath", str(ts), "--ckpt_file",
                str(bundle_copy / "models" / "model.pt"), "--use_trace", "True", "--input_shape", "[1, 2, 32, 32, 32]",
                *cfg], bundle_copy)
    import torch

    scripted = torch.jit.load(str(ts))
    assert tuple(scripted(torch.rand(1, 2, 32, 32, 32)).shape) == (1, 6)
