"""Benchmark of ``DualEncoderRigidNet`` on CPU: speed/memory table and a fusion ablation.

Usage::

    python -m benchmarks.speed.bench_network              # forward time / peak memory at 64^3, 96^3, 128^3
    python -m benchmarks.speed.bench_network --ablation   # train each fusion on the same synthetic task, compare errors

Speed: inference forward of one (moving, fixed) pair, ``torch.set_num_threads(threads)`` (default 2), median of
``--repeats`` runs after one warm-up; plus one training step (forward + warp + default paper loss + backward) of
one pair. Each grid size runs in a fresh subprocess so that the peak resident memory (``ru_maxrss``) is its own;
"extra" is the peak minus the resident memory before the first forward.

Ablation: 32^3 network grid at 4 mm (128 mm field of view); analytic phantoms (soft body + random Gaussian blobs,
:mod:`monai_rigidreg.simulation.toy`) with uniform random translations +-10 mm and rotations +-10 degrees; every
variant trains for the same steps, batch, seed and learning-rate schedule on the supervised point-distance loss
(``RigidRegistrationLoss(w_sup=1)``, other terms off) and is evaluated on the same held-out pairs.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np
import torch

from benchmarks.bench_common import script_parser
from monai_rigidreg.core.geometry import Grid, grid_points, point_distances_torch
from monai_rigidreg.losses import RigidRegistrationLoss
from monai_rigidreg.networks import FUSIONS, DualEncoderRigidNet, RigidTransformer
from monai_rigidreg.simulation.toy import phantom_pair_batch, random_params


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _child(size: int, threads: int, repeats: int, fusion: str) -> dict:
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    net = DualEncoderRigidNet(fusion=fusion)
    x = torch.rand(1, 2, size, size, size)
    base = _rss_mb()
    net.eval()
    with torch.no_grad():
        net(x)  # warm-up
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            net(x)
            times.append(time.perf_counter() - t0)
    peak_inf = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    # one training step: forward, warp, paper loss, backward
    grid = Grid.centered((size,) * 3, (4.0,) * 3)
    warp = RigidTransformer(grid)
    loss = RigidRegistrationLoss()
    net.train()
    train_times = []
    for _ in range(2):
        t0 = time.perf_counter()
        pred = net(x)
        loss(warp(x[:, :1], pred), x[:, 1:], pred, grid=grid).total.backward()
        train_times.append(time.perf_counter() - t0)
    peak_train = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {
        "size": size,
        "forward_s": float(np.median(times)),
        "forward_min_s": float(np.min(times)),
        "rss_before_mb": base,
        "peak_inference_mb": peak_inf,
        "peak_train_mb": peak_train,
        "train_step_s": float(min(train_times)),
        "params": sum(p.numel() for p in net.parameters()),
    }


def speed_table(sizes: list[int], threads: int, repeats: int, fusion: str) -> None:
    rows = []
    for s in sizes:
        cmd = [sys.executable, os.path.abspath(__file__), "--_child", str(s), "--threads", str(threads)]
        cmd += ["--repeats", str(repeats), "--fusion", fusion]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1]
        rows.append(json.loads(out))
    print(f"DualEncoderRigidNet(fusion={fusion!r}) defaults, CPU, torch.set_num_threads({threads}), batch 1 pair")
    print(f"parameters: {rows[0]['params']:,}")
    hdr = (
        f"{'grid':>6} | {'forward median (s)':>18} | {'forward min (s)':>15} | {'peak RSS infer (MB)':>19} | "
        f"{'extra infer (MB)':>16} | {'train step (s)':>14} | {'peak RSS train (MB)':>19}"
    )
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        print(
            f"{r['size']:>4}^3 | {r['forward_s']:>18.3f} | {r['forward_min_s']:>15.3f} |"
            f" {r['peak_inference_mb']:>19.0f} | {r['peak_inference_mb'] - r['rss_before_mb']:>16.0f} |"
            f" {r['train_step_s']:>14.3f} |"
            f" {r['peak_train_mb']:>19.0f}"
        )


def _errors(pred: torch.Tensor, true: torch.Tensor, pts: torch.Tensor, center) -> tuple[float, float, float]:
    t_err = (pred[:, :3] - true[:, :3]).abs().mean().item()
    r_err = (pred[:, 3:] - true[:, 3:]).abs().mean().item()
    return t_err, r_err, point_distances_torch(pred.double(), true.double(), pts, center).mean().item()


def ablation(steps: int, batch: int, n_val: int, lr: float, seed: int, threads: int, size: int) -> None:
    torch.set_num_threads(threads)
    grid = Grid.centered((size,) * 3, (4.0,) * 3)
    center = grid.center()
    pts = torch.as_tensor(grid_points(grid, 4))
    gv = torch.Generator().manual_seed(10_000 + seed)
    p_val = random_params(n_val, gv, 10.0, 10.0)
    m_val, f_val = phantom_pair_batch(grid, p_val, gv)
    loss_fn = RigidRegistrationLoss(0.0, 0.0, 0.0, 0.0, 0.0, w_sup=1.0)
    print(
        f"Ablation: {size}^3 grid at 4 mm, t +-10 mm, r +-10 deg, {steps} steps x batch {batch}, Adam lr {lr} "
        f"(linear decay), supervised point-distance loss, {n_val} validation pairs, seed {seed}, {threads} threads"
    )
    hdr = (
        f"{'fusion':>12} | {'params':>8} | {'|t| err (mm)':>12} | {'|r| err (deg)':>13} | {'TRE (mm)':>8} | "
        f"{'train loss last 20':>18} | {'time (s)':>8}"
    )
    print(hdr)
    print("-" * len(hdr))
    zero = torch.zeros_like(p_val)
    te, re_, tre = _errors(zero, p_val, pts, center)
    print(f"{'identity':>12} | {0:>8} | {te:>12.2f} | {re_:>13.2f} | {tre:>8.2f} | {'-':>18} | {'-':>8}")
    for fusion in FUSIONS:
        torch.manual_seed(seed)
        g = torch.Generator().manual_seed(seed)
        # the default architecture with one stage fewer: a 32^3 grid gives the same 4^3 final map as 64^3
        net = DualEncoderRigidNet(fusion=fusion, channels=(8, 16, 32), strides=(2, 2, 2))
        opt = torch.optim.Adam(net.parameters(), lr=lr)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0 - s / steps)
        losses = []
        t0 = time.perf_counter()
        for _ in range(steps):
            p = random_params(batch, g, 10.0, 10.0)
            moving, fixed = phantom_pair_batch(grid, p, g)
            pred = net.forward_pair(moving, fixed)
            terms = loss_fn(moving, fixed, pred, p, grid=grid)
            opt.zero_grad()
            terms.total.backward()
            opt.step()
            sched.step()
            losses.append(float(terms.total.detach()))
        elapsed = time.perf_counter() - t0
        net.eval()
        with torch.no_grad():
            pred = torch.cat([net.forward_pair(m_val[i : i + 8], f_val[i : i + 8]) for i in range(0, n_val, 8)])
        te, re_, tre = _errors(pred.double(), p_val, pts, center)
        n_par = sum(q.numel() for q in net.parameters())
        print(
            f"{fusion:>12} | {n_par:>8} | {te:>12.2f} | {re_:>13.2f} | {tre:>8.2f} | {np.mean(losses[-20:]):>18.2f} |"
            f" {elapsed:>8.0f}"
        )


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--ablation", action="store_true", help="train and compare the fusion variants")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 96, 128])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--fusion", default="flatten", choices=FUSIONS, help="fusion of the speed table")
    parser.add_argument("--steps", type=int, default=150, help="ablation training steps per variant")
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--n-val", type=int, default=32)
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", type=int, default=32, help="ablation grid size (voxels per axis, 4 mm)")
    parser.add_argument("--_child", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args._child:
        print(json.dumps(_child(args._child, args.threads, args.repeats, args.fusion)))
    elif args.ablation:
        ablation(args.steps, args.batch, args.n_val, args.lr, args.seed, args.threads, args.size)
    else:
        speed_table(args.sizes, args.threads, args.repeats, args.fusion)


if __name__ == "__main__":
    main()
