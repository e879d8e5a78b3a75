"""Ablation of the Gauss-Newton fine stage's feature maps and iterations (no trained weights involved).

Usage::

    python -m benchmarks.ablation.bench_alignment_features --datalist data/val_paper/dataset.json
    python -m benchmarks.ablation.bench_alignment_features               # simulates the paper-protocol set first

Every variant runs ``DualEncoderRigidNet`` with an untrained (zero-output) regression head, so the estimate is
the fine stage's alone, started from the identity, on the bundle's network grid (64^3 at 2 mm, centred on the CT)
with the bundle's validation preprocessing. Printed per variant: mean TRE over a +-80 mm point cube (as the
bundle's ``val_tre``), median TRE, cases under 2 mm, per-axis mean absolute error and seconds per case (2 threads).

Without ``--datalist`` the set is simulated as ``scripts/make_training_data.sh`` simulates the bundle's
validation set (stock Shepp-Logan, paper protocol, seed 900, 128 mm interior CBCT), about 7 minutes on 2 cores.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from monai.data import load_decathlon_datalist

from benchmarks.bench_common import script_parser
from monai_rigidreg.core.geometry import PARAM_NAMES
from monai_rigidreg.engine.data import registration_transforms
from monai_rigidreg.engine.metrics import RigidErrorMetric
from monai_rigidreg.networks import DualEncoderRigidNet, GaussNewtonStage, TwoStageRigidNet

SPACING = 2.0
SIZE = 64
# name -> GaussNewtonStage keyword arguments (the fine stage; the untrained regression starts at the identity)
VARIANTS: dict[str, dict] = {
    "intensity only": {"highpass_weight": 0.0, "gradient_weight": 0.0},
    "intensity + gradient x2": {"highpass_weight": 0.0, "gradient_weight": 2.0},
    "default: intensity + local contrast x3": {},  # support eroded 8 mm
    "default + gradient x2": {"gradient_weight": 2.0},
    "default, local contrast x1": {"highpass_weight": 1.0},
    "default, local contrast sigma 8 mm": {"highpass_sigma_mm": 8.0},
    "default, support erosion 1 voxel": {"support_erosion_mm": 0.0},
    "default, support erosion 4 mm": {"support_erosion_mm": 4.0},
    "default, support erosion 16 mm": {"support_erosion_mm": 16.0},
    "default, 12-8-4 iterations": {"iterations": (12, 8, 4)},
    "default, linear intensity bias terms": {"bias_degree": 1},
    "default, quadratic intensity bias terms": {"bias_degree": 2},
    "default, cubic intensity bias terms": {"bias_degree": 3},
    "12-8-4 + quadratic bias terms (the bundle's)": {"iterations": (12, 8, 4), "bias_degree": 2},
    "0.2.1 + symmetric steps on the last level": {
        "iterations": (12, 8, 4), "bias_degree": 2, "jacobian": ("fixed", "fixed", "symmetric")},
}


def load_set(datalist: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    data = load_decathlon_datalist(datalist, is_segmentation=False, data_list_key="training")
    tf = registration_transforms("val", (SIZE,) * 3, (SPACING,) * 3)
    items = [tf(d) for d in data]
    moving = torch.stack([torch.as_tensor(np.asarray(i["moving"])) for i in items]).float()
    fixed = torch.stack([torch.as_tensor(np.asarray(i["fixed"])) for i in items]).float()
    params = torch.stack([torch.as_tensor(np.asarray(i["rigid_params"]["params"])) for i in items]).float()
    return moving, fixed, params


def run_variant(moving, fixed, params, **kwargs) -> dict[str, float]:
    settings = {"iterations": (8, 5, 3), **kwargs}
    net = TwoStageRigidNet(DualEncoderRigidNet(), GaussNewtonStage((SPACING,) * 3, **settings)).eval()
    preds, t0 = [], time.perf_counter()
    with torch.no_grad():
        for i in range(len(moving)):
            preds.append(net.forward_pair(moving[i:i + 1], fixed[i:i + 1]))
    sec = (time.perf_counter() - t0) / len(moving)
    pred = torch.cat(preds)
    per_case = RigidErrorMetric("tre")(pred, params).flatten()
    row = {"tre": float(per_case.mean()), "median": float(per_case.median()), "ok": int((per_case < 2.0).sum()),
           "sec": sec}
    for q in PARAM_NAMES:
        row[q] = float(RigidErrorMetric(q)(pred, params).mean())
    return row


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--datalist", help="paper-protocol datalist (default: simulate one into --work-dir)")
    ap.add_argument("--work-dir", default="bench_out/alignment_features")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    datalist = args.datalist
    if datalist is None:
        out = Path(args.work_dir) / "val_paper"
        if not (out / "dataset.json").is_file():
            grid = ["--set", "simct_size=128", "--set", "simct_spacing=2.0", "--set", "simct_views=360", "--set",
                    "cbct_views=180", "--set", "cbct_size=64", "--set", "cbct_spacing=2.0", "--set",
                    "projection_spacing=2.0"]
            subprocess.run([sys.executable, "-m", "monai_rigidreg.cli", "simulate", "--no-progress", "--output-dir",
                            str(out), "--phantom", "shepp-logan", "--protocol", "paper", "--num-cases", "21",
                            "--seed", "900", *grid], check=True)
        datalist = str(out / "dataset.json")
    moving, fixed, params = load_set(datalist)
    print(f"{len(moving)} cases from {datalist}; network grid {SIZE}^3 at {SPACING} mm; fine stage only")
    head = f"{'variant':42s} {'TRE':>6s} {'median':>6s} {'<2mm':>5s} " + " ".join(f"{n:>6s}" for n in PARAM_NAMES)
    print(head + f" {'s/case':>6s}")
    print("-" * len(head + "       "))
    for name, kw in VARIANTS.items():
        r = run_variant(moving, fixed, params, **kw)
        axes = " ".join(f"{r[n]:6.3f}" for n in PARAM_NAMES)
        print(f"{name:42s} {r['tre']:6.3f} {r['median']:6.3f} {r['ok']:5d} {axes} {r['sec']:6.2f}", flush=True)
    print("TRE, median and t* in mm; r* in degrees (mean absolute error per axis)")


if __name__ == "__main__":
    main()
