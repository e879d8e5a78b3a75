"""Shifted-view sum versus convolution in :func:`monai_rigidreg.core.image_ops.separable_filter` (CPU milliseconds).

Times one separable filter pass with a kernel of ``K`` taps on every filtered axis, for each implementation:

* ``shifted``: ``method="shifted"``, a weighted sum of ``K`` shifted views of the padded tensor;
* ``conv``: ``method="conv"``, one single-channel ``conv1d``/``conv2d`` per axis;
* ``matrix``: ``method="matrix"``, one product with the dense ``[n, n]`` filter matrix per axis (by request only:
  the CBCT scatter blur, whose kernel is nearly as long as the detector axes);
* ``MONAI``: ``monai.networks.layers.separable_filtering`` (grouped ``conv3d``/``conv2d``), for reference.

Shapes are those of the callers: ``[1, 136, 136, 136]`` (the anti-aliased CT crop, zero padding, three axes) and
``[360, 128, 128]`` (projection stack of the CBCT simulation, replicate padding, two axes: the scatter blur of
sigma 20-30 px has 121-181 taps). The first ``K`` where ``conv`` is faster gives
``image_ops.SHIFTED_SUM_MAX_TAPS``. A last table times forward + backward of the SSIM loss's ``valid`` blurs (7
taps by default): it decides which implementation ``method="auto"`` uses when autograd records the call.

Each time is the fastest of ``--repeats`` runs; the implementations take turns within each repeat, and
``conv / shifted`` is the median over the repeats of the ratio of the two times of one repeat (> 1: the shifted sum
is faster), which decides the ``faster`` column (shifted versus conv only: the choice ``method="auto"`` makes; the
dense matrix is used where a caller asks for it). The load average is printed: on an oversubscribed machine (more
runnable processes than cores) the shifted sum, dozens of short multi-threaded operations that each wait for their
slowest thread, slows down several times more than one long convolution, and the tables then mislead.

Run: ``python -m benchmarks.speed.bench_gaussian [--threads 2] [--repeats 5]``.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable

import torch
from monai.networks.layers import separable_filtering

from benchmarks.bench_common import script_parser
from monai_rigidreg.core.image_ops import SHIFTED_SUM_MAX_TAPS, separable_filter

LENGTHS = (3, 9, 17, 33, 65, 129, 181, 257, 361)


def _times_ms(fns: dict[str, Callable[[], object]], repeats: int) -> dict[str, list[float]]:
    """``repeats`` timings (ms) of each function; the functions take turns within each repeat, so that the
    timings of one repeat share the disturbances of a busy machine."""
    for fn in fns.values():
        fn()  # warm-up
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t = time.perf_counter()
            fn()
            times[name].append(1e3 * (time.perf_counter() - t))
    return times


def _ratio(times: dict[str, list[float]]) -> float:
    """Median over the repeats of conv time / shifted time (> 1: the shifted sum is faster)."""
    return statistics.median(c / s for c, s in zip(times["conv"], times["shifted"]))


def _table(title: str, x: torch.Tensor, axes: int, padding: str, repeats: int) -> int | None:
    """Print one table; return the first length where ``conv`` beats ``shifted`` (None: never)."""
    print(f"\n{title}\n")
    print("| taps K | shifted ms | conv ms | matrix ms | MONAI separable_filtering ms | conv / shifted | faster |")
    print("|---:|---:|---:|---:|---:|---:|---|")
    monai_in = x.reshape(-1, 1, *x.shape[x.ndim - axes :])  # MONAI wants [B, C, spatial...]
    crossover = None
    for k in LENGTHS:
        kernel = torch.rand(k, dtype=x.dtype)
        ks = [(kernel + kernel.flip(0)) / 2] * axes
        t = _times_ms({
            "shifted": lambda ks=ks: separable_filter(x, ks, padding, "shifted"),
            "conv": lambda ks=ks: separable_filter(x, ks, padding, "conv"),
            "matrix": lambda ks=ks: separable_filter(x, ks, padding, "matrix"),
            "monai": lambda ks=ks: separable_filtering(monai_in, ks, mode=padding),
        }, repeats)
        ratio = _ratio(t)
        faster = "conv" if ratio < 1 else "shifted"
        if faster == "conv" and crossover is None:
            crossover = k
        print(f"| {k} | {min(t['shifted']):.1f} | {min(t['conv']):.1f} | {min(t['matrix']):.1f} | "
              f"{min(t['monai']):.1f} | {ratio:.2f} "
              f"| {faster} |", flush=True)
    return crossover


def _backward_table(repeats: int) -> bool:
    """Forward + backward of the ``valid`` blurs of the SSIM loss (6 blurs of a [2, 1, 64, 64, 64] batch);
    whether the shifted sum was faster at every length."""
    print("\nforward + backward, [2, 1, 64, 64, 64], padding 'valid', 3 axes, 6 blurs (as masked_ssim)\n")
    print("| taps K | shifted ms | conv ms | conv / shifted | faster |")
    print("|---:|---:|---:|---:|---|")
    x = torch.rand(2, 1, 64, 64, 64, requires_grad=True)
    shifted_always = True
    for k in (3, 7, 11):
        ks = [torch.rand(k)] * 3

        def step(method: str, ks: list[torch.Tensor] = ks) -> None:
            total = sum(separable_filter(x * (i + 1), ks, "valid", method).sum() for i in range(6))
            total.backward()

        t = _times_ms({"shifted": lambda: step("shifted"), "conv": lambda: step("conv")}, repeats)
        ratio = _ratio(t)
        shifted_always &= ratio >= 1
        faster = "conv" if ratio < 1 else "shifted"
        print(f"| {k} | {min(t['shifted']):.1f} | {min(t['conv']):.1f} | {ratio:.2f} | {faster} |", flush=True)
    return shifted_always


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5, help="runs per entry (the fastest is reported)")
    ap.add_argument("--skip-backward", action="store_true", help="no forward + backward table")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"# torch {torch.__version__}, {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"{args.threads} threads, best of {args.repeats}; float32; SHIFTED_SUM_MAX_TAPS = {SHIFTED_SUM_MAX_TAPS}; "
          f"load average before {os.getloadavg()[0]:.2f}")
    gen = torch.Generator().manual_seed(0)
    c3 = _table("[1, 136, 136, 136], padding 'zeros', 3 axes", torch.rand(1, 136, 136, 136, generator=gen), 3,
                "zeros", args.repeats)
    c2 = _table("[360, 128, 128], padding 'replicate', 2 axes", torch.rand(360, 128, 128, generator=gen), 2,
                "replicate", args.repeats)
    line = f"\nfirst K where conv is faster: 3-D volume {c3}, 2-D stack {c2}"
    if not args.skip_backward:
        line += f"; with backward the shifted sum is faster at every K: {_backward_table(args.repeats)}"
    print(line + f"\n# load average after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
