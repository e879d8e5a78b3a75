"""Capture range of the shipped network: success rate against motion size, trained regression vs none.

Usage::

    python -m benchmarks.accuracy.bench_capture_range --datalist data/val_paper/dataset.json \
        [--bundle PATH] [--repeats 2]

For each motion size ``m`` every case of the datalist gets ``--repeats`` extra random rigid motions (uniform in
``+-m`` mm on each translation axis and ``+-m`` degrees on each rotation axis, all six axes at once, seeded),
composed with its recorded motion, through the bundle's training preprocessing without CBCT degradation
(``registration_transforms`` with ``degrade=False``). Two networks register them on the bundle grid: the shipped
weights, and the same network with its regression head zeroed (the fine stage started from the identity only). Printed
per size: success rate (TRE < 2 mm over a +-80 mm point cube), median TRE, and the mean supervised error of the
regression alone (coarse estimate), which training is meant to shrink.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from monai.data import load_decathlon_datalist
from monai.utils import set_determinism

from benchmarks.bench_common import script_parser
from monai_rigidreg.bundle.loader import bundle_settings, default_bundle_path, load_bundle_network
from monai_rigidreg.engine.data import registration_transforms
from monai_rigidreg.engine.metrics import RigidErrorMetric


def load_network(bundle: Path, weights: str | None, zero_head: bool) -> torch.nn.Module:
    net, _ = load_bundle_network(bundle, weights=weights)
    if zero_head:  # the learned estimate replaced by the identity: what the fine stage reaches on its own
        net.regression = _Identity(net.regression)
    return net


class _Identity(torch.nn.Module):
    """A stand-in regression that always estimates no motion (``[B, 6]`` zeros)."""

    def __init__(self, regression: torch.nn.Module) -> None:
        super().__init__()
        self.in_channels = regression.in_channels

    def forward_pair(self, moving: torch.Tensor, fixed: torch.Tensor) -> torch.Tensor:
        return moving.new_zeros(moving.shape[0], 6)


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--datalist", required=True)
    ap.add_argument("--bundle", default=None, help="bundle directory (default: the shipped one)")
    ap.add_argument("--weights", default=None, help="checkpoint (default: the bundle's models/model.pt)")
    ap.add_argument("--sizes", default="5,10,15,20,25,30", help="motion sizes (mm and degrees per axis)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--align-jacobian", default=None,
                    help="override the fine stage's Jacobian per level, e.g. fixed,fixed,symmetric (see "
                         "bench_gauss_newton_variants.py)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    bundle = Path(args.bundle) if args.bundle else default_bundle_path()
    settings = bundle_settings(bundle)
    size, spacing = tuple(settings["network_size"]), tuple(settings["network_spacing"])
    data = load_decathlon_datalist(args.datalist, is_segmentation=False, data_list_key="training")
    nets = {"trained": load_network(bundle, args.weights, False),
            "no regression": load_network(bundle, args.weights, True)}
    if args.align_jacobian:
        for net in nets.values():
            net.fine_stage.jacobian = tuple(args.align_jacobian.split(","))
    print(f"{len(data)} cases x {args.repeats} motions per size; grid {size} at {spacing} mm; bundle {bundle}")
    print(f"{'size':>5s} | " + " | ".join(f"{n + ': ok, median':>26s}" for n in nets) + " | regression error (mm)")
    for m in [float(v) for v in args.sizes.split(",")]:
        set_determinism(seed=int(m))
        tf = registration_transforms("train", size, spacing, translate_range=m, rotate_range=m, axis_prob=1.0,
                                     degrade=False)
        moving, fixed, params = [], [], []
        for _ in range(args.repeats):
            for d in data:
                it = tf(d)
                moving.append(torch.as_tensor(np.asarray(it["moving"])))
                fixed.append(torch.as_tensor(np.asarray(it["fixed"])))
                params.append(torch.as_tensor(np.asarray(it["rigid_params"]["params"])))
        mov, fix, gt = torch.stack(moving).float(), torch.stack(fixed).float(), torch.stack(params).float()
        cells, coarse_err = [], float("nan")
        for name, net in nets.items():
            preds, coarse = [], []
            with torch.no_grad():
                for i in range(len(mov)):
                    stages = net.forward_stages(mov[i:i + 1], fix[i:i + 1])
                    preds.append(stages["params"])
                    coarse.append(stages["coarse"])
            tre = RigidErrorMetric("tre")(torch.cat(preds), gt).flatten()
            cells.append(f"{100 * float((tre < 2).float().mean()):18.0f}% {float(tre.median()):6.2f}")
            if name == "trained":
                coarse_err = float(RigidErrorMetric("tre")(torch.cat(coarse), gt).mean())
        print(f"{m:5.0f} | " + " | ".join(cells) + f" | {coarse_err:8.2f}", flush=True)
    print("ok: share of cases with TRE < 2 mm; median TRE in mm; regression error: mean TRE of the trained "
          "regression's own (coarse) estimate")


if __name__ == "__main__":
    main()
