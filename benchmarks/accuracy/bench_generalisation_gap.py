"""The learned network alone on the training stream's draws from the CTs it was trained on and from CTs it never saw.

A network that has learned to register rather than to recognise its training bodies does as well on anatomy it
never saw as on its own training CTs under the same draws. This script measures that gap directly: it builds two
samplers (:class:`~monai_rigidreg.engine.RigidPairSampler`, real CTs as ``ct`` sources only, the same seed, motion
bands, fields of view, couches and image-domain CBCT degradation as training), one over the real CTs the network
was trained on and one over the held-out ones, runs the network alone on ``--samples`` draws of each (the bundle's
``network_def`` with the checkpoint's weights, evaluation mode, the bundle's inference passes: no image-similarity
optimisation) and prints, per side and per CT, the grid point distance (mm: the mean distance between the true and
the estimated transform's images of every 4th network-grid voxel, the training's supervised measure), its median
and the shares under 2 and 5 mm, then the same by the share of the network grid inside the CBCT's field of view and
by the number of axes rotated by more than 25 degrees.

    python -m benchmarks.accuracy.bench_generalisation_gap --samples 200 --threads 1
    python -m benchmarks.accuracy.bench_generalisation_gap \
        training/context_run_v3/models/checkpoint_checkpoint_epoch=257.pt --samples 200

The trained-on CTs are :data:`~monai_rigidreg.io.shared_data.TRAINING_CTS` (or ``BENCH_TRAINED_ON``'s, a
leave-one-CT-out fold); the held-out side is the other real CTs found in ``--shared``. The draws are not the
benchmarks' CBCTs (no projection-domain simulation; bodies cut by the sampler's fields of view of 55-130 mm radius),
so these shares are a diagnosis of what training transfers, not accuracy figures: those come from
``bench_real_ct.py`` and ``bench_clinical_geometry.py``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_common import Tee, end_run, script_parser, set_threads, start_run, trained_on
from monai_rigidreg.io.shared_data import HELD_OUT_CTS, TRAINING_CTS

REAL_CTS = (*TRAINING_CTS, *HELD_OUT_CTS)
"""The six real CTs of ``../shared/data`` (file stems)."""

ROTATED_DEG = 25.0
"""An axis counts as rotated by a large angle above this (degrees)."""


def _rounded(values: Sequence[float]) -> list[float]:
    return [round(float(v), 4) for v in values]


def _row(label: str, dist: Sequence[float]) -> str:
    d = np.asarray(dist, dtype=np.float64)
    if d.size == 0:
        return f"| {label} | 0 | - | - | - | - |"
    return (f"| {label} | {d.size} | {d.mean():.2f} | {np.median(d):.2f} | {(d < 2.0).mean():.2f} | "
            f"{(d < 5.0).mean():.2f} |")


def _grouped(out: Tee, title: str, sides: dict[str, list[dict[str, Any]]], key: Callable[[dict[str, Any]], str],
             order: Sequence[str]) -> None:
    out(f"### {title}")
    out()
    out("| side, group | n | mean (mm) | median (mm) | share < 2 mm | share < 5 mm |")
    out("|---|---|---|---|---|---|")
    for side, rows in sides.items():
        for group in order:
            dist = [r["distance_mm"] for r in rows if key(r) == group]
            if dist:
                out(_row(f"{side}, {group}", dist))
    out()


def fov_group(share: float) -> str:
    """The field-of-view share's group label (share of the network grid inside the CBCT's field of view).

    >>> fov_group(0.95), fov_group(0.5), fov_group(0.1)
    ('>= 0.8', '0.4-0.6', '< 0.2')
    """
    edges = (0.2, 0.4, 0.6, 0.8)
    if share < edges[0]:
        return "< 0.2"
    if share >= edges[-1]:
        return ">= 0.8"
    i = int(np.searchsorted(edges, share, side="right")) - 1
    return f"{edges[i]:.1f}-{edges[i + 1]:.1f}"


FOV_ORDER = ("< 0.2", "0.2-0.4", "0.4-0.6", "0.6-0.8", ">= 0.8")


def rotated_axes(params: Sequence[float], limit: float = ROTATED_DEG) -> int:
    """How many of the three angles (degrees, the last three of six parameters) exceed ``limit`` in magnitude.

    >>> rotated_axes([10.0, 0.0, 0.0, 30.0, -26.0, 5.0])
    2
    """
    return int(sum(abs(float(a)) > limit for a in list(params)[3:6]))


def split_cts(shared: Path, seen: Sequence[str]) -> dict[str, list[str]]:
    """The real CTs found in ``shared`` (``<stem>.nii.gz``) split into those named in ``seen`` (the trained-on side,
    in ``seen``'s order) and the others (the held-out side, in :data:`REAL_CTS`'s order).

    >>> split_cts(Path("/nonexistent"), ["head_tigre_ct"])
    {'trained on': [], 'held out': []}
    """
    found = [n for n in REAL_CTS if (Path(shared) / f"{n}.nii.gz").is_file()]
    return {"trained on": [n for n in seen if n in found], "held out": [n for n in found if n not in seen]}


def paired_changes(rows: Sequence[dict[str, Any]], baseline: Sequence[dict[str, Any]], limit: float = 5.0
                   ) -> tuple[int, int]:
    """``(fixed, broken)``: how many draws are under ``limit`` (mm) only in ``rows`` and only in ``baseline``, the
    same draws of two checkpoints (each row's ``params`` and ``ct`` must agree: ``ValueError`` otherwise).

    >>> def draw(params, mm):
    ...     return {"ct": "a", "params": [params], "distance_mm": mm}
    >>> paired_changes([draw(1.0, 0.5), draw(2.0, 9.0)], [draw(1.0, 7.0), draw(2.0, 8.0)])
    (1, 0)
    """
    if len(rows) != len(baseline) or any(r["ct"] != b["ct"] or r["params"] != b["params"]
                                         for r, b in zip(rows, baseline)):
        raise ValueError("the baseline holds other draws (another seed, sample count or CT split)")
    fixed = sum(r["distance_mm"] < limit <= b["distance_mm"] for r, b in zip(rows, baseline))
    broken = sum(b["distance_mm"] < limit <= r["distance_mm"] for r, b in zip(rows, baseline))
    return int(fixed), int(broken)


def main() -> None:
    """The command (the module doc): parse the options, draw and register both sides, print the tables."""
    ap = script_parser(__doc__)
    ap.add_argument("checkpoint", type=Path, nargs="?", default=None,
                    help="a training checkpoint or model.pt (default: the shipped bundle's weights)")
    ap.add_argument("--samples", type=int, default=200, help="draws per side (default 200)")
    ap.add_argument("--shared", type=Path, default=Path("../shared/data"), help="the real CTs (<stem>.nii.gz)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=123)
    ap.add_argument("--results", type=Path, default=None, help="a file for the printed report (and a .json beside)")
    ap.add_argument("--baseline", type=Path, default=None,
                    help="another checkpoint's .json of the same draws (same seed, --samples and CTs): the draws "
                         "under 5 mm in only one of the two, per side")
    args = ap.parse_args()
    if args.samples < 1:
        ap.error("--samples must be at least 1")
    baseline = None
    if args.baseline is not None:
        try:
            baseline = json.loads(args.baseline.read_text())
        except (OSError, ValueError) as exc:
            ap.error(f"--baseline {args.baseline}: {exc}")
    set_threads(args.threads)  # torch's and SimpleITK's (the sources are resampled by SimpleITK)
    out = Tee()
    monitor, t0 = start_run(out, __spec__.name if __spec__ else "bench_generalisation_gap", args.threads, "cpu",
                            str(args.checkpoint or "the shipped bundle"))
    import torch

    from monai_rigidreg.bundle.loader import load_bundle_network
    from monai_rigidreg.engine import RigidPairSampler, load_sources
    from monai_rigidreg.engine.criterion import canonical_grid
    from monai_rigidreg.losses import RigidRegistrationLoss
    from monai_rigidreg.transforms import RIGID_KEY

    net, settings = load_bundle_network(weights=args.checkpoint)
    reg = net.regression
    size = tuple(int(s) for s in settings["network_size"])
    spacing = tuple(float(s) for s in settings["network_spacing"])
    grid = canonical_grid(size, spacing)
    sup = RigidRegistrationLoss(w_ssim=0.0, w_ncc=0.0, w_mi=0.0, w_grad=0.0, w_sup=1.0, w_reg=0.0)
    names = split_cts(args.shared, trained_on())
    for side, found in names.items():
        if not found:
            ap.error(f"no {side} CT in {args.shared} (the real CTs: {', '.join(REAL_CTS)})")
    out(f"network passes {tuple(reg.passes)}, coarse passes {reg.coarse_passes}; {args.samples} draws per side, "
        f"seed {args.seed}; the training's motion bands, fields of view, couches and degradation")
    out(f"trained on: {', '.join(names['trained on'])}")
    out(f"held out: {', '.join(names['held out'])}")
    out()
    sides: dict[str, list[dict[str, Any]]] = {}
    factor = int(reg.context_factor)
    for side, found in names.items():
        sources = load_sources(cts=[str(args.shared / f"{n}.nii.gz") for n in found], network_spacing=spacing[0],
                               context_spacing=spacing[0] * factor)
        sampler = RigidPairSampler(sources, size, spacing, context_size=reg.context_size, context_factor=factor,
                                   seed=args.seed)
        it = iter(sampler)
        rows = []
        for _ in range(args.samples):
            s = next(it)
            moving, fixed, context = (s[k][None].float() for k in ("moving", "fixed", "context"))
            truth = torch.as_tensor(np.asarray(s[RIGID_KEY]["params"]), dtype=torch.float32).reshape(1, 6)
            with torch.no_grad():
                estimate = reg.forward_levels(moving, fixed, context)[-1].float()
            rows.append({"ct": s["source"], "params": _rounded(truth[0].tolist()),
                         "estimate": _rounded(estimate[0].tolist()),
                         "distance_mm": round(float(sup.sup_term(estimate, truth, grid)), 4),
                         "identity_mm": round(float(sup.sup_term(torch.zeros_like(truth), truth, grid)), 4),
                         "fov_share": round(float(s["moving_fov"].float().mean()), 4)})
        sides[side] = rows
    out("### per side and CT (grid point distance)")
    out()
    out("| side, CT | n | mean (mm) | median (mm) | share < 2 mm | share < 5 mm |")
    out("|---|---|---|---|---|---|")
    for side, rows in sides.items():
        out(_row(f"{side}, all", [r["distance_mm"] for r in rows]))
        out(_row(f"{side}, identity (no estimate)", [r["identity_mm"] for r in rows]))
        for name in names[side]:
            out(_row(f"{side}, {name}", [r["distance_mm"] for r in rows if r["ct"] == name]))
    out()
    _grouped(out, "by the share of the network grid inside the CBCT's field of view", sides,
             lambda r: fov_group(r["fov_share"]), FOV_ORDER)
    _grouped(out, f"by the number of axes rotated by more than {ROTATED_DEG:.0f} degrees", sides,
             lambda r: str(rotated_axes(r["params"])), ("0", "1", "2", "3"))
    full = {side: [r["distance_mm"] for r in rows if r["fov_share"] >= 0.8] for side, rows in sides.items()}
    shares = {side: float((np.asarray(d) < 5.0).mean()) if d else float("nan") for side, d in full.items()}
    out(f"Gap where the field of view covers >= 0.8 of the grid: share < 5 mm {shares['trained on']:.2f} on the "
        f"trained-on CTs, {shares['held out']:.2f} held out")
    out()
    if baseline is not None:
        for side, rows in sides.items():
            try:
                fixed, broken = paired_changes(rows, baseline.get(side, []))
            except ValueError as exc:
                out(f"Against {args.baseline}, {side}: not compared ({exc})")
                continue
            out(f"Against {args.baseline}, {side}: {fixed} draws under 5 mm only here, {broken} only there "
                f"(of {len(rows)})")
        out()
    if args.results is not None:
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.with_suffix(".json").write_text(json.dumps(sides) + "\n")
    end_run(out, monitor, t0, args.results, [])


if __name__ == "__main__":
    main()
