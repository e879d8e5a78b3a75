"""A context-network training step at each thread count, on a quiet machine and beside a busy process.

The training runs of this project share their 2 cores with whatever else a session runs (tests, benchmarks,
evaluations) and with their own DataLoader worker. This script times one training step (forward, loss, backward,
Adam; the bundle's ``train_context.json`` network and loss, batch ``--batch`` from the training sampler) at
``--threads`` intra-op threads, first with nothing else started by it, then beside ``--busy`` single-threaded
processes that spin for the whole measurement: what :class:`monai_rigidreg.engine.threads.ThreadTuner` chooses
between. Run it with the training paused (the load is printed).

Usage::

    python -m benchmarks.speed.bench_training_threads \\
        --results benchmarks/results/0.6.3.dev/bench_training_threads_2026-12-07.txt
"""

from __future__ import annotations

import multiprocessing as mp
import statistics
import time

import monai_rigidreg  # noqa: F401  (first: its thread policy applies before torch loads)

# isort: split
import torch

from benchmarks.bench_common import end_run, script_parser, start_cpu_run


def _spin(stop: mp.Event) -> None:  # type: ignore[valid-type]
    while not stop.is_set():
        for _ in range(100_000):
            pass


def main(argv: list[str] | None = None) -> int:
    ap = script_parser(__doc__)
    ap.add_argument("--datalist", nargs="+", default=["data/train.json"])
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--steps", type=int, default=5, help="steps timed per setting (after one warm-up step)")
    ap.add_argument("--thread-counts", type=int, nargs="+", default=[2, 1])
    ap.add_argument("--busy", type=int, nargs="+", default=[0, 1], help="busy processes beside the steps")
    args, out, monitor, t0 = start_cpu_run(ap, argv, __spec__.name if __spec__ else "bench_training_threads",
                                           "the bundle's train_context.json network (untrained)", threads=2)
    import numpy as np
    from monai.data import list_data_collate

    from benchmarks.speed.bench_training_throughput import context_config, context_sampler
    from monai_rigidreg.engine import RegistrationPrepareBatch, StagedInferer

    cfg = context_config()
    sampler, _ = context_sampler(cfg, args.datalist, [])
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    network = cfg.get_parsed_content("network_def", instantiate=True)
    network.train()
    criterion = cfg.get_parsed_content("loss", instantiate=True)
    inferer = StagedInferer()
    optimizer = torch.optim.Adam(network.parameters(), lr=1e-5)
    inputs, targets = RegistrationPrepareBatch()(list_data_collate([sampler.draw(rng) for _ in range(args.batch)]),
                                                 device="cpu")

    def step() -> float:
        t = time.perf_counter()
        optimizer.zero_grad()
        criterion(inferer(inputs, network), targets).backward()
        optimizer.step()
        return time.perf_counter() - t

    out()
    out(f"| busy processes beside | threads | s per step (median of {args.steps}) | steps |")
    out("|---|---|---|---|")
    ctx = mp.get_context("spawn")
    for busy in args.busy:
        stop = ctx.Event()
        spinners = [ctx.Process(target=_spin, args=(stop,), daemon=True) for _ in range(busy)]
        for p in spinners:
            p.start()
        try:
            for threads in args.thread_counts:
                torch.set_num_threads(threads)
                step()  # warm-up at this count
                times = [step() for _ in range(args.steps)]
                out(f"| {busy} | {threads} | {statistics.median(times):.2f} | "
                    f"{' '.join(f'{t:.2f}' for t in times)} |")
        finally:
            stop.set()
            for p in spinners:
                p.join()
    out()
    end_run(out, monitor, t0, args.results, [f"batch {args.batch}; each busy process spins one core in a loop"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
