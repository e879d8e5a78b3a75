"""Make a bundle folder that runs a ContextCorrelationNet checkpoint: the shipped bundle's configs and docs, the
regression of ``configs/train_context.json`` (with the inference passes) in ``inference.json``, and the network's
weights from a training checkpoint (or a ``model.pt``) as ``models/model.pt``.

``monai-rigidreg register --bundle OUT``, ``benchmarks/bench_real_ct.py --bundle OUT`` and
``benchmarks/bench_clinical_geometry.py --bundle OUT`` then run it. Used to measure a training run while it goes on,
and to make the shipped bundle from the run's final weights.

    python scripts/export_context_bundle.py training/context_run/models/checkpoint_checkpoint_epoch=40.pt \
        scratch/context_bundle --passes 4 1
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import torch

from monai_rigidreg.networks.context_net import COARSE_STARTS

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "bundles" / "cbct_ct_rigid"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint", type=Path, help="a training checkpoint (with 'network') or a model.pt state dict")
    ap.add_argument("output", type=Path, help="the bundle folder to write (replaced if it holds an earlier export)")
    ap.add_argument("--passes", type=int, nargs=2, default=[4, 1],
                    help="inference passes of the 8 mm and 4 mm levels (the shipped bundles 0.6.0 and 0.6.1: 4 1, "
                         "the network alone's; 0.5.0: 2 1)")
    ap.add_argument("--coarse-start", choices=COARSE_STARTS, default="coarse",
                    help="where the local levels start at inference (ContextCorrelationNet's coarse_start)")
    args = ap.parse_args(argv)
    state = torch.load(args.checkpoint, map_location="cpu", weights_only=True)
    if isinstance(state, dict) and "network" in state:
        state = state["network"]
    if not isinstance(state, dict) or not any(k.startswith("regression.") for k in state):
        print(f"export_context_bundle: {args.checkpoint} holds no TwoStageRigidNet weights", file=sys.stderr)
        return 2
    marker = args.output / ".context_export"
    if args.output.exists():
        if not marker.is_file():
            print(f"export_context_bundle: {args.output} exists and is not an earlier export: not replaced",
                  file=sys.stderr)
            return 2
        shutil.rmtree(args.output)
    shutil.copytree(SHIPPED, args.output, ignore=shutil.ignore_patterns("model.pt", "*.ts"))
    train = json.loads((SHIPPED / "configs" / "train_context.json").read_text())
    regression = dict(train["network_def#regression"])
    regression["passes"] = list(args.passes)
    regression["coarse_start"] = args.coarse_start
    regression.pop("train_autocast", None)  # a training setting (inference runs in float32)
    regression["context_factor"] = train["context_factor"]
    inference_path = args.output / "configs" / "inference.json"
    inference = json.loads(inference_path.read_text())
    inference["network_def"]["regression"] = regression
    inference_path.write_text(json.dumps(inference, indent=4) + "\n")
    torch.save(state, args.output / "models" / "model.pt")
    marker.write_text(json.dumps({"checkpoint": str(args.checkpoint.resolve()), "passes": list(args.passes),
                                      "coarse_start": args.coarse_start}) + "\n")
    print(f"bundle with {args.checkpoint.name} -> {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
