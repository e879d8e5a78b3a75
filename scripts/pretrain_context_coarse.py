"""Pretrain the context network's coarse level alone (``monai_rigidreg.engine.coarse_pretrain``), then write the
whole network's weights for ``scripts/train_context_model.sh``'s ``INIT``.

    python scripts/pretrain_context_coarse.py --init training/context_run/models/checkpoint_checkpoint_epoch=42.pt \
        --schedule 10:10:600 25:15:600 40:30:400 --output training/context_run_v3/init.pt \
        --log training/context_run_v3/pretrain_log.json

``--init``: weights the network starts from (the tensors whose names and shapes match; e.g. an earlier run's local
levels); ``--schedule``: bands ``MM:DEG:STEPS`` in order (a curriculum); samples from the training sampler over the
same sources as the training script (``--data``, the training CTs of ``--shared`` or those ``--cts`` names).
Progress is logged every 25 steps and saved with ``--log``. Exit status 2 with the reason for a missing input; an
existing ``--output`` is not overwritten.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--output", type=Path, required=True, help="the weights file to write (not overwritten)")
    ap.add_argument("--init", type=Path, default=None)
    ap.add_argument("--schedule", nargs="+", default=["10:10:600", "25:15:600", "40:30:400"], metavar="MM:DEG:STEPS")
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--data", type=Path, default=Path("data"))
    ap.add_argument("--shared", type=Path, default=Path("../shared/data"))
    ap.add_argument("--cts", nargs="+", default=None, metavar="NAME",
                    help="the real CTs of --shared to sample (file stems; default: the package's training CTs; "
                         "a leave-one-CT-out fold names its five: scripts/train_loco.sh)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--log", type=Path, default=None, help="write the progress records here (JSON)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if args.output.exists():
        print(f"pretrain_context_coarse: {args.output} exists: choose another path", file=sys.stderr)
        return 2
    named = [args.shared / f"{n}.nii.gz" for n in args.cts] if args.cts else []
    missing = [p for p in [args.init, args.data / "train.json", *named] if p is not None and not p.is_file()]
    if missing:
        print(f"pretrain_context_coarse: missing {', '.join(map(str, missing))}", file=sys.stderr)
        return 2
    try:
        schedule_spec = [tuple(float(v) for v in s.split(":")) for s in args.schedule]
        assert all(len(s) == 3 and s[2] >= 1 for s in schedule_spec)
    except (ValueError, AssertionError):
        print(f"pretrain_context_coarse: --schedule wants MM:DEG:STEPS, got {args.schedule}", file=sys.stderr)
        return 2

    import torch
    from monai.bundle import ConfigParser

    from monai_rigidreg.engine import RigidPairSampler, load_sources
    from monai_rigidreg.engine.coarse_pretrain import pretrain_coarse
    from monai_rigidreg.engine.handlers import load_matching_weights
    from monai_rigidreg.engine.sampler import MotionRange
    from monai_rigidreg.engine.threads import ThreadTuner
    from monai_rigidreg.io.shared_data import training_ct_paths

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    parser = ConfigParser()
    parser.read_config(["bundles/cbct_ct_rigid/configs/train.json", "bundles/cbct_ct_rigid/configs/train_context.json"])
    model = parser.get_parsed_content("network_def")
    if args.init is not None:
        taken, fresh, _ = load_matching_weights(model, torch.load(args.init, map_location="cpu", weights_only=True))
        logging.info("started from %s: %d of %d tensors", args.init, len(taken), len(taken) + len(fresh))
    size = tuple(parser["network_size"])
    spacing = tuple(float(s) for s in parser["network_spacing"])
    factor = int(parser["context_factor"])
    datalists = [str(p) for p in (args.data / "train.json", args.data / "clinical" / "dataset.json") if p.is_file()]
    cts = [str(p) for p in (named or training_ct_paths(args.shared))]
    logging.info("real CTs: %s", ", ".join(Path(c).name for c in cts))
    sources = load_sources(datalists=datalists, cts=cts, network_spacing=spacing[0],
                           context_spacing=spacing[0] * factor, isocenter_max=float(parser["isocenter_max"]))

    def samples(band: MotionRange):
        return iter(RigidPairSampler(sources, size, spacing, context_factor=factor, motions=(band,),
                                     case_motions=(band,), seed=args.seed + int(band.max_translation)))

    schedule = [(MotionRange(mm, deg), int(steps)) for mm, deg, steps in schedule_spec]

    def show(r: dict) -> None:
        logging.info("step %d (%d samples), band %g mm / %g deg: match %.3f nats, cells within one cell %.3f, %.0f s",
                     r["step"], r["samples"], r["band_mm"], r["band_deg"], r["match_nats"], r["near_share"],
                     r["seconds"])

    tuner = ThreadTuner(max_threads=args.threads)  # the thread count that runs faster beside what else runs
    history = pretrain_coarse(model.regression, samples, schedule, batch_size=args.batch, lr=args.lr, on_log=show,
                              on_step=tuner.tick)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    torch.save(model.state_dict(), args.output)
    if args.log is not None:
        args.log.write_text(json.dumps({"command": " ".join(sys.argv), "history": history}, indent=1) + "\n")
    logging.info("written %s", args.output)
    return 0


if __name__ == "__main__":
    sys.exit(main())
