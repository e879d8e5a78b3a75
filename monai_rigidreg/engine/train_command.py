"""``monai-rigidreg train``: train the registration network with the MONAI bundle (wraps 'python -m monai.bundle run').

Runs the bundle's configs/train.json (or multi_gpu_train.json through torchrun with --nproc N). Logs and curves go to
--output-dir (default ./runs), checkpoints and the best model.pt to --ckpt-dir (default <output-dir>/models); nothing
is written into the installed package: copy model.pt into a bundle of your own to use it (--bundle).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

from monai_rigidreg.core.command_text import add_command
from monai_rigidreg.core.errors import InputError, OutputExistsError

__all__ = ["add_parser", "run", "bundle_command", "check_train_args", "refuse_earlier_run", "RUN_FILES"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``train`` sub-command to ``subparsers`` (``monai-rigidreg``'s); it sets ``func=run``."""
    p = add_command(subparsers, "train", __doc__, run)
    p.add_argument("--datalist", required=True, type=Path, help="training datalist (monai-rigidreg simulate)")
    p.add_argument("--val-datalist", required=True, type=Path, help="validation datalist (fixed paper-protocol set)")
    p.add_argument("--bundle", type=Path, default=None, help="bundle directory (default: the shipped one)")
    p.add_argument("--output-dir", type=Path, default=Path("runs"), help="TensorBoard logs, history, curves.png")
    p.add_argument("--ckpt-dir", type=Path, default=None,
                   help="checkpoints and model.pt (default: <output-dir>/models)")
    p.add_argument("--epochs", type=int, default=None, help="epochs to train (default: the bundle's train.json)")
    p.add_argument("--epoch-length", type=int, default=None, help="iterations per epoch")
    p.add_argument("--learning-rate", type=float, default=None,
                   help="the optimizer's learning rate (default: the bundle's train.json)")
    p.add_argument("--device", default=None, help="cpu | cuda | cuda:N (default: CUDA if available)")
    p.add_argument("--seed", type=int, default=None,
                   help="random seed of the sampling and the network's start (default: the bundle's train.json)")
    p.add_argument("--num-workers", type=int, default=None, help="DataLoader workers")
    p.add_argument("--resume", action="store_true", help="continue from the newest checkpoint in --ckpt-dir")
    p.add_argument("--init-weights", type=Path, default=None,
                   help="start the network from these weights (e.g. the shipped models/model.pt: fine-tuning); "
                        "optimizer and schedule start afresh; a run resumed from a checkpoint ignores it")
    p.add_argument("--nproc", type=int, default=1, help=">1: torchrun with multi_gpu_train.json (gloo on CPU)")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                   help="further bundle overrides, e.g. network_def#channels=[16,32,64,64]")
    return p


RUN_FILES = ("history.json", "curves.png", "model.pt")
"""Files a training run leaves in ``--output-dir`` / ``--ckpt-dir`` (with ``checkpoint_*.pt``): a folder holding
any of them holds an earlier run, which only ``--resume`` may continue."""


def check_train_args(args: argparse.Namespace) -> None:
    """The options and datalists of ``train``, checked before ``monai.bundle`` starts (whose errors are tracebacks).

    Raises:
        InputError: a missing or unusable datalist (not JSON, no non-empty list of items with ``fixed`` and
            ``moving``), a count or rate out of range, an unknown device, a missing ``--bundle`` config or
            ``--init-weights`` file.
    """
    # imported here, as every heavy import of this module: `monai-rigidreg --help` builds this command's parser, and
    # the bundle's loader, the volumes' checks and the datalist reader import torch
    from monai_rigidreg.bundle.loader import default_bundle_path
    from monai_rigidreg.core.device import resolve_device
    from monai_rigidreg.evaluation.evaluate import load_datalist

    for path in (args.datalist, args.val_datalist):
        load_datalist(path, "training")  # JSON, a non-empty list of items with fixed and moving, where train.json reads
    for name, value, least in (("--epochs", args.epochs, 1), ("--epoch-length", args.epoch_length, 1),
                               ("--num-workers", args.num_workers, 0), ("--nproc", args.nproc, 1)):
        if value is not None and value < least:
            raise InputError(f"{name} must be at least {least}, got {value}")
    if args.learning_rate is not None and not (math.isfinite(args.learning_rate) and args.learning_rate > 0):
        raise InputError(f"--learning-rate must be a positive number, got {args.learning_rate}")
    if args.device:
        resolve_device(args.device)  # an unknown name, or CUDA where there is none
    bundle = (args.bundle or default_bundle_path()).resolve()
    if not (bundle / "configs" / "train.json").is_file():
        raise InputError("not a bundle: it has no configs/train.json", bundle)
    if args.init_weights is not None:
        if not args.init_weights.is_file():
            raise InputError("--init-weights: no such file", args.init_weights)
        import torch

        try:
            state = torch.load(args.init_weights, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint: its own error text is named
            raise InputError(f"--init-weights: not a readable PyTorch checkpoint ({type(exc).__name__}: "
                             f"{str(exc).splitlines()[0] if str(exc) else ''})", args.init_weights) from exc
        if not (isinstance(state, dict) and state and all(torch.is_tensor(v) for v in state.values())):
            keys = sorted(state)[:5] if isinstance(state, dict) else type(state).__name__
            raise InputError(f"--init-weights needs the network's weights (a state dict such as models/model.pt), "
                             f"got {keys}: a training checkpoint continues with --resume and its --ckpt-dir",
                             args.init_weights)
    for kv in args.set:
        if "=" not in kv:
            raise InputError(f"--set expects KEY=VALUE, got {kv!r}")


def refuse_earlier_run(output_dir: Path, ckpt_dir: Path) -> None:
    """Without ``--resume``, folders holding an earlier run (:data:`RUN_FILES`, checkpoints) are refused: training
    would replace its model.pt and history.json."""
    found = [f for d in (output_dir, ckpt_dir) for f in (*(d / n for n in RUN_FILES), *d.glob("checkpoint_*.pt"))
             if f.is_file()]
    if found:
        raise OutputExistsError(found[0].parent, f"it holds an earlier training run ({found[0].name}); pass --resume "
                                                 "to continue it, or choose another --output-dir / --ckpt-dir")


def bundle_command(args: argparse.Namespace) -> list[str]:
    """The ``monai.bundle run`` command line for ``args`` (after :func:`check_train_args`)."""
    from monai_rigidreg.bundle.loader import default_bundle_path, refuse_package_folders
    from monai_rigidreg.io.volumes import check_output_dir

    bundle = (args.bundle or default_bundle_path()).resolve()
    check_train_args(args)
    sets = dict(kv.split("=", 1) for kv in args.set)
    # --set output_dir=... / ckpt_dir=... override the options on the bundle's command line: checked as they are
    output_dir = Path(sets.get("output_dir", args.output_dir)).resolve()
    ckpt_dir = Path(sets.get("ckpt_dir", args.ckpt_dir or output_dir / "models")).resolve()
    for folder in (output_dir, ckpt_dir):
        check_output_dir(folder, allow_existing=True)  # a file, or under a file: refused before anything runs
    refuse_package_folders(output_dir, ckpt_dir)
    if not args.resume:
        refuse_earlier_run(output_dir, ckpt_dir)
    configs = [str(bundle / "configs" / "train.json")]
    if args.nproc > 1:
        configs.append(str(bundle / "configs" / "multi_gpu_train.json"))
    overrides = {
        "bundle_root": str(bundle),
        "datalist": str(args.datalist.resolve()),
        "val_datalist": str(args.val_datalist.resolve()),
        "output_dir": str(output_dir),
        "ckpt_dir": str(ckpt_dir),
        "epochs": args.epochs,
        "epoch_length": args.epoch_length,
        "learning_rate": args.learning_rate,
        "seed": args.seed,
        "num_workers": args.num_workers,
        "resume": True if args.resume else None,
        "init_weights": str(args.init_weights.resolve()) if args.init_weights else None,
    }
    if args.device and args.device != "auto":  # auto: the bundle's own choice (CUDA where there is one)
        overrides["device"] = f"$torch.device('{args.device}')"
    cmd = [sys.executable, "-m", "monai.bundle", "run", "--config_file", json.dumps(configs),
           "--meta_file", str(bundle / "configs" / "metadata.json"),
           "--logging_file", str(bundle / "configs" / "logging.conf")]
    if args.nproc > 1:
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={args.nproc}",
               "-m", "monai.bundle", *cmd[3:]]
    for k, v in overrides.items():
        if v is not None:
            cmd += [f"--{k}", str(v)]
    for kv in args.set:
        if "=" not in kv:
            raise InputError(f"--set expects KEY=VALUE, got {kv!r}")
        k, v = kv.split("=", 1)
        cmd += [f"--{k}", v]
    return cmd


def run(args: argparse.Namespace) -> int:
    cmd = bundle_command(args)
    print("running:", " ".join(cmd), flush=True)
    return subprocess.call(cmd)

