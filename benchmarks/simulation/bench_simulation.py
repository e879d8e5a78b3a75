"""Benchmark of the simulator on 2 CPU threads: one CBCT (128^3) and one Sim-CT (256^3), time, peak memory
and reconstruction quality against the voxelized phantom.

Each row runs in its own process (so the peak resident memory, ``resource.getrusage``, is that row's). Times
cover projection, physics and reconstruction of one volume (the phantom voxelization, done once per object, is
listed separately). Quality: RMSE (HU) and SSIM (MONAI ``SSIMMetric``, HU clipped to [-1000, 1000]) of the
reconstruction against the stock Shepp-Logan phantom voxelized on the same grid, inside the field of view,
with ideal (noise- and scatter-free) projections, so they measure the projector and the reconstruction.

Usage::

    python -m benchmarks.simulation.bench_simulation          # all rows (several minutes; --repeats N: median)
    python -m benchmarks.simulation.bench_simulation --quick  # small grids, a smoke test
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

ROWS = {
    # name: (kind, size, spacing, views, projection spacing)
    "cbct-2mm-360": ("cbct", 128, 2.0, 360, 2.0),
    "cbct-2mm-180": ("cbct", 128, 2.0, 180, 2.0),
    "cbct-1mm-360 (paper, interior)": ("cbct", 128, 1.0, 360, 2.0),
    "cbct-1mm-180 (paper, interior)": ("cbct", 128, 1.0, 180, 2.0),
    "simct-1mm-360": ("simct", 256, 1.0, 360, None),
    "simct-1mm-180": ("simct", 256, 1.0, 180, None),
}
QUICK = {
    "cbct-quick": ("cbct", 48, 5.0, 90, 5.0),
    "simct-quick": ("simct", 64, 4.0, 90, None),
}


def _quality(rec_mu, ref_mu, mask) -> tuple[float, float]:
    import torch
    from monai.metrics import SSIMMetric

    from monai_rigidreg.simulation import mu_to_hu

    a = mu_to_hu(rec_mu).clamp(-1000, 1000) * mask
    b = mu_to_hu(ref_mu).clamp(-1000, 1000) * mask
    rmse = float(torch.sqrt(((a - b)[mask > 0] ** 2).mean()))
    ssim = float(SSIMMetric(spatial_dims=3, data_range=2000.0, win_size=7)(a[None, None], b[None, None]).mean())
    return rmse, ssim


def _timed(fn, repeats: int) -> tuple[float, float]:
    """``(first call, median of repeats)`` seconds; the first call includes the process's first-use costs."""
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times[0], sorted(times)[len(times) // 2]


def run_row(name: str, spec: tuple, repeats: int = 3) -> dict:
    import torch

    torch.set_num_threads(2)
    from monai_rigidreg.core.geometry import Grid
    from monai_rigidreg.simulation import CBCTPhysics, make_phantom, simulate_cbct, simulate_simct

    kind, n, sp, views, proj_sp = spec
    grid = Grid.centered((n,) * 3, (sp,) * 3)
    t0 = time.perf_counter()
    if kind == "cbct":
        # the object as the paper preset builds it: Sim-CT extent (256 mm) + 32 mm margins at the projection spacing
        obj_grid = Grid.centered((round((256 + 64) / proj_sp),) * 3, (proj_sp,) * 3)
        obj, _ = make_phantom("shepp-logan", obj_grid, radius_mm=128.0)
        t_vox = time.perf_counter() - t0
        first, seconds = _timed(lambda: simulate_cbct(obj, obj_grid, grid, (5, -5, 10, 5, 0, -5), views=views,
                                                      physics=CBCTPhysics(), device="cpu"), repeats)
        rec, fov, geom = simulate_cbct(obj, obj_grid, grid, views=views, physics=CBCTPhysics.ideal(), device="cpu")
        mask = fov.float()
        extra = f"detector {geom.detector_shape[0]}x{geom.detector_shape[1]}, object {obj_grid.size[0]}^3"
    else:
        obj, _ = make_phantom("shepp-logan", grid, radius_mm=128.0)
        t_vox = time.perf_counter() - t0
        first, seconds = _timed(lambda: simulate_simct(obj, grid, views, device="cpu"), repeats)
        rec = simulate_simct(obj, grid, views, device="cpu")
        mask = torch.ones_like(rec)
        extra = "fan beam, 1 row per slice"
    ref, _ = make_phantom("shepp-logan", grid, radius_mm=128.0)
    rmse, ssim = _quality(rec, ref, mask)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {
        "row": name,
        "seconds": seconds,
        "first_s": first,
        "voxelize_s": t_vox,
        "peak_mb": peak_mb,
        "rmse_hu": rmse,
        "ssim": ssim,
        "note": extra,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small grids only (smoke test)")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per row; the median is reported (default 3)")
    parser.add_argument("--row", help=argparse.SUPPRESS)
    args = parser.parse_args()
    rows = QUICK if args.quick else ROWS
    if args.row:
        print(json.dumps(run_row(args.row, rows[args.row], args.repeats)))
        return 0
    import torch

    print(f"monai-rigidreg simulation benchmark: torch {torch.__version__}, 2 CPU threads, stock Shepp-Logan")
    print("time = projection + CBCT physics + reconstruction of one volume (default physics for the CBCT): median of")
    print(f"{args.repeats} runs in one process ('first s': the first of them, with the process's first-use costs);")
    print("quality = ideal projections vs the voxelized phantom inside the FOV (HU clipped to [-1000, 1000])")
    header = (f"{'row':32s} {'seconds':>8s} {'first s':>8s} {'voxelize s':>10s} {'peak MB':>8s} {'RMSE HU':>8s} "
              f"{'SSIM':>6s}  note")
    print(header)
    print("-" * len(header))
    for name in rows:
        cmd = [sys.executable, __file__, "--row", name, "--repeats", str(args.repeats)]
        cmd += ["--quick"] if args.quick else []
        # passive OpenMP waiting: on a CPU shared with other processes, spinning threads slow everything down
        env = {**os.environ, "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
        res = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if res.returncode != 0:
            print(f"{name:32s} FAILED: {res.stderr.strip().splitlines()[-1] if res.stderr else res.returncode}")
            continue
        r = json.loads(res.stdout.strip().splitlines()[-1])
        print(
            f"{r['row']:32s} {r['seconds']:8.2f} {r['first_s']:8.2f} {r['voxelize_s']:10.1f} {r['peak_mb']:8.0f} "
            f"{r['rmse_hu']:8.1f} {r['ssim']:6.3f}  {r['note']}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
