"""``monai-rigidreg demo``: the whole job on an embedded default, offline.

Simulates a Sim-CT / CBCT pair from the package's own phantom under a known 6-DoF motion, registers it with the
shipped bundle weights (and, with ``--refine``, SimpleITK), and prints the errors against the known motion and
where the outputs are.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from pathlib import Path

from monai_rigidreg.core.command_text import outputs_listing
from monai_rigidreg.core.errors import InputError

__all__ = ["add_parser", "run", "run_demo", "DEMO_MOTION", "DEMO_SIMULATION"]

logger = logging.getLogger(__name__)

DEMO_MOTION = (8.0, -5.0, 6.0, 4.0, -3.0, 7.0)
"""The demo's known motion: (tx, ty, tz) mm, (rx, ry, rz) degrees."""
DEMO_SIMULATION: dict = {"simct_size": 128, "simct_spacing": 2.0, "cbct_size": 96, "cbct_spacing": 2.0}
"""The demo's grids: Sim-CT 128^3 and CBCT 96^3 (a 192 mm field of view), both at the network's 2 mm, so the
simulation takes seconds on a laptop CPU (the ``fast`` preset's 4-5 mm grids are coarser than the network grid and
cost accuracy)."""


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo",
        help="simulate a CBCT/CT pair with known motion, register it with the shipped weights, report the errors",
        description="End-to-end demonstration on a generated phantom (no data or download needed).",
    )
    p.add_argument("--output-dir", type=Path, default=Path("demo_output"), metavar="DIR",
                   help="where the pair, the registration and the report go (default: demo_output; refused where "
                   "it exists and is not empty, unless --overwrite)")
    p.add_argument("--phantom", default="shepp-logan-asym",
                   help="shepp-logan | shepp-logan-asym | random | synth (synthetic anatomy) | path to a CT (default: "
                   "shepp-logan-asym)")
    p.add_argument("--motion", type=float, nargs=6, default=list(DEMO_MOTION), metavar=("TX", "TY", "TZ", "RX", "RY",
                   "RZ"), help="known motion, mm and degrees")
    p.add_argument("--refine", action="store_true", help="also refine with SimpleITK Mattes MI")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N (default: auto)")
    p.add_argument("--bundle", type=Path, default=None, help="MONAI bundle directory (default: the shipped one)")
    p.add_argument("--seed", type=int, default=0, help="the simulation's random seed (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace an earlier demo's output folder")
    p.set_defaults(func=run)
    return p


def run_demo(output_dir: str | Path, phantom: str = "shepp-logan-asym", motion=DEMO_MOTION, refine: bool = False,
             device: str = "auto", bundle: str | Path | None = None, seed: int = 0, overwrite: bool = False,
             sim_overrides: dict | None = None) -> dict:
    """Run the demo; returns ``{"true", "pred", "abs_error", "tre_mm", "confidence", "paths", "timings"}``.

    ``sim_overrides`` update :data:`DEMO_SIMULATION` and go to
    :func:`~monai_rigidreg.simulation.simulate_pair` (any :class:`~monai_rigidreg.simulation.SimulationConfig`
    field; the demo's grid sizes and spacings win over a ``preset`` unless they are overridden too). An existing,
    non-empty ``output_dir`` is refused unless ``overwrite``. Everything is written into a hidden sibling folder
    and moved into place when complete, so a failed or interrupted demo leaves nothing behind.
    """
    # imported here: this module also defines the `demo` sub-command's parser, which `monai-rigidreg --help` builds,
    # and the simulator and the registration stack import torch (seconds)
    import numpy as np

    from monai_rigidreg.core.device import resolve_device
    from monai_rigidreg.core.geometry import PARAM_NAMES, parameter_errors, target_registration_error
    from monai_rigidreg.evaluation.evaluate import body_points
    from monai_rigidreg.export.outputs import write_outputs
    from monai_rigidreg.export.record import complete_record
    from monai_rigidreg.io.staging import staged_output_dir
    from monai_rigidreg.io.volumes import load_volume
    from monai_rigidreg.registration.registrar import RigidRegistrar
    from monai_rigidreg.simulation.pair import simulate_pair

    resolve_device(device)  # a bad device string is refused before anything is simulated
    motion = tuple(float(v) for v in motion)
    if len(motion) != 6 or not all(math.isfinite(v) for v in motion):
        raise InputError(f"--motion needs six finite numbers (tx ty tz mm, rx ry rz degrees), got {list(motion)}")
    final = Path(output_dir)
    # written aside, moved into place when complete; --overwrite replaces only an earlier demo folder
    with staged_output_dir(final, overwrite, replaceable=("data", "registration", "demo.json")) as out:
        t0 = time.perf_counter()
        settings = {**DEMO_SIMULATION, **(sim_overrides or {})}
        logger.info("demo 1/3: simulating a Sim-CT and a CBCT of the %s phantom under the known motion", phantom)
        sim = simulate_pair(out / "data", phantom=phantom, params=list(motion), seed=seed, device=device, **settings)
        t_sim = time.perf_counter() - t0
        fixed = load_volume(sim["fixed"])
        moving = load_volume(sim["moving"])
        logger.info("demo 2/3: registering with the shipped network (%.1f s so far)", time.perf_counter() - t0)
        registrar = RigidRegistrar.from_bundle(bundle, device=device)
        result = registrar(fixed, moving, refine=refine)
        logger.info("demo 3/3: writing the outputs and the QC figure")
        # the audit trail names the pair where it ends up; the couch shifts at the CBCT's centre, HFS assumed
        complete_record(result, moving, *(final / Path(sim[k]).relative_to(out) for k in ("fixed", "moving")),
                        bundle=registrar.source, device=str(registrar.device))
        paths = write_outputs(result, fixed, moving, out / "registration", overwrite=True,
                              names=(Path(sim["fixed"]).name, Path(sim["moving"]).name))
        truth = np.asarray(sim["params"], dtype=np.float64)
        tre = float(target_registration_error(result.params, truth, body_points(fixed), center=result.center))
        report = {
            "true": dict(zip(PARAM_NAMES, truth.tolist())),
            "pred": dict(zip(PARAM_NAMES, np.round(result.params, 3).tolist())),
            "abs_error": dict(zip(PARAM_NAMES, np.round(parameter_errors(result.params, truth), 3).tolist())),
            "tre_mm": round(tre, 3),
            "confidence": round(result.confidence, 3),
            "timings": {"simulation_s": round(t_sim, 2), **{k: round(v, 3) for k, v in result.timings.items()}},
            "paths": {k: str(final / Path(v).relative_to(out))
                      for k, v in {**paths, "fixed": sim["fixed"], "moving": sim["moving"]}.items()},
        }
        (out / "demo.json").write_text(json.dumps(report, indent=2))
    return report


def run(args: argparse.Namespace) -> int:
    r = run_demo(args.output_dir, args.phantom, tuple(args.motion), args.refine, args.device, args.bundle, args.seed,
                 args.overwrite)
    print("parameter   true     predicted  |error|   (mm / degrees)")
    for k in r["true"]:
        print(f"  {k:4s}  {r['true'][k]:8.3f}  {r['pred'][k]:9.3f}  {r['abs_error'][k]:7.3f}")
    print(f"target registration error (body): {r['tre_mm']:.3f} mm   confidence: {r['confidence']:.2f}")
    print("timings (s): " + ", ".join(f"{k}={v}" for k, v in r["timings"].items()))
    print(outputs_listing(r["paths"]))
    return 0
