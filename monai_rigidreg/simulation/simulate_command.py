"""``monai-rigidreg simulate``: the command line of the paired-dataset simulator.

Wire it into a main parser with::

    sub = parser.add_subparsers(dest="command")
    simulation.simulate_command.add_parser(sub)
    args = parser.parse_args()
    sys.exit(args.func(args))
"""

from __future__ import annotations

import argparse
import ast
import sys
from typing import Any

from monai_rigidreg.core.errors import RigidRegError

__all__ = ["add_parser", "run"]


def _parse_set(items: list[str] | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items or []:
        if "=" not in item:
            raise argparse.ArgumentTypeError(f"--set expects KEY=VALUE, got {item!r}")
        key, raw = item.split("=", 1)
        try:
            value = ast.literal_eval(raw)
        except (ValueError, SyntaxError):
            value = raw
        out[key.strip().replace("-", "_")] = value
    return out


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``simulate`` subcommand to an ``argparse`` subparsers object; it sets ``func=run``."""
    p = subparsers.add_parser(
        "simulate",
        help="simulate paired Sim-CT / CBCT volumes with known rigid motion",
        description="Simulate a paired planning-CT (fan-beam FBP) / CBCT (cone-beam FDK) dataset with ground-truth "
        "rigid transforms and write NIfTI volumes (HU) plus a MONAI datalist DIR/dataset.json (each case's motion as "
        "params about its center, the Sim-CT centre, and as a 4x4 matrix, fixed -> moving, LPS mm). With a CT as "
        "--phantom the pair keeps the CT's frame (the Sim-CT centred on the CT's centre), so a CBCT registers against "
        "the input CT itself; dataset.json's 'frame' says where the volumes lie. The Sim-CT is simulated from the CT "
        "on the preset's grid: --preset fast gives a 4 mm Sim-CT and a 5 mm CBCT, paper 1 mm (--set simct_spacing=, "
        "cbct_spacing= choose others).",
    )
    p.add_argument("--output-dir", required=True, metavar="DIR", help="output directory")
    p.add_argument(
        "--phantom",
        default="shepp-logan",
        metavar="shepp-logan|shepp-logan-asym|random|synth|PATH",
        help="a built-in phantom (shepp-logan, shepp-logan-asym, random: random ellipsoids, synth: synthetic anatomy) "
        "or a CT (NIfTI, MHA, NRRD file or DICOM folder, HU); default shepp-logan",
    )
    p.add_argument("--protocol", default=None, choices=("paper", "random", "multi30"),
                   help="motion protocol (default paper: the reference study's 63 motions; random: uniform within "
                   "--set max_translation=, max_rotation=; multi30: |rx| = |ry| = |rz| = 30 degrees, 8 cases)")
    p.add_argument("--motion", type=float, nargs=6, default=None, metavar=("TX", "TY", "TZ", "RX", "RY", "RZ"),
                   help="one chosen motion (mm and degrees, about the Sim-CT centre) instead of a protocol; "
                   "--num-cases defaults to 1")
    p.add_argument("--num-cases", type=int, default=None, metavar="N",
                   help="number of cases (default: the whole protocol, 1 with --motion)")
    p.add_argument("--preset", default="fast", choices=("paper", "fast"), help="grid/view preset (default fast)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    p.add_argument("--device", default="auto", choices=("cpu", "cuda", "auto"), help="torch device (default auto)")
    p.add_argument("--overwrite", action="store_true", help="recompute and overwrite existing outputs")
    p.add_argument("--workers", type=int, default=0, metavar="N", help="worker processes (default 0: none)")
    p.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override a configuration or CBCT physics field, e.g. --set cbct_spacing=2.0 --set photons=1e4 "
        "(repeatable)",
    )
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=run)
    return p


def run(args: argparse.Namespace) -> int:
    """Run the ``simulate`` subcommand; returns the exit status (0 ok, 2 bad input or existing output)."""
    from monai_rigidreg.simulation.dataset import simulate_dataset

    motion = getattr(args, "motion", None)
    if motion is not None and args.protocol is not None:
        print("monai-rigidreg simulate: error: give --protocol or --motion, not both", file=sys.stderr)
        return 2
    extra = {"motion": tuple(motion)} if motion is not None else {}
    try:
        path = simulate_dataset(
            args.output_dir,
            phantom=args.phantom,
            protocol=args.protocol or "paper",
            num_cases=args.num_cases,
            preset=args.preset,
            seed=args.seed,
            device=args.device,
            overwrite=args.overwrite,
            workers=args.workers,
            progress=not getattr(args, "no_progress", False),
            **{**_parse_set(getattr(args, "set", None)), **extra},
        )
    except (RigidRegError, argparse.ArgumentTypeError) as exc:
        print(f"monai-rigidreg simulate: error: {exc}", file=sys.stderr)
        return 2
    print(path)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry point (``python -m monai_rigidreg.simulation.simulate_command simulate ...``)."""
    parser = argparse.ArgumentParser(prog="monai-rigidreg")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
