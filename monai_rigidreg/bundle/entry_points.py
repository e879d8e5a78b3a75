"""What the bundle's configs call: the inputs checked before the network is built (``bundle_check_inputs``), the
registrations run (``bundle_run``, ``bundle_register_files``) and the evaluation (``bundle_evaluate``).

``python -m monai.bundle run`` prints a traceback for anything raised in a config expression; through
:func:`bundle_errors` the package's own errors end the run with their message on one line and the command line's
exit status instead.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from monai_rigidreg.core.errors import InputError, RigidRegError, Terminated, sigterm_raises
from monai_rigidreg.io.volumes import check_output_dir
from monai_rigidreg.registration.files import register_files
from monai_rigidreg.registration.inputs import check_cascade_steps, check_register_inputs

if TYPE_CHECKING:
    from monai_rigidreg.registration.pairs import RegistrationEvaluator
    from monai_rigidreg.registration.registrar import RigidRegistrar

__all__ = ["bundle_errors", "check_bundle_options", "bundle_check_inputs", "bundle_evaluate", "bundle_register_files",
           "bundle_run"]


@contextlib.contextmanager
def bundle_errors() -> Iterator[None]:
    """``python -m monai.bundle run`` prints a traceback for anything raised in a config expression, ending with
    MONAI's "Failed to evaluate ConfigExpression"; the package's own errors end the run instead with their message
    on one line and the exit status of the command line (2; 130 for Ctrl-C, 143 for SIGTERM)."""
    try:
        with sigterm_raises(only_if_default=True):
            yield
    except RigidRegError as exc:
        print(f"monai-rigidreg bundle: error: {exc}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None
    except KeyboardInterrupt as exc:
        print("monai-rigidreg bundle: " + ("terminated" if isinstance(exc, Terminated) else "interrupted"),
              file=sys.stderr, flush=True)
        raise SystemExit(143 if isinstance(exc, Terminated) else 130) from None


def check_bundle_options(flags: dict[str, Any] | None = None, device: Any = None) -> None:
    """The bundle's switches and device as ``python -m monai.bundle run`` hands them over: its command line reads
    ``--refine False`` as the boolean but ``--refine false`` as the text ``"false"``, which Python takes as true (the
    refinement ran). Each of ``flags`` must be a boolean (or 0 / 1); ``device`` a ``torch.device`` or a name torch
    knows on this machine (``cpu``, ``cuda``, ``cuda:N``).

    Raises:
        InputError: the first value that is neither, naming the option.
    """
    for name, value in (flags or {}).items():
        if not (isinstance(value, (bool, np.bool_)) or (isinstance(value, int) and value in (0, 1))):
            raise InputError(f"--{name} must be True or False (with capitals on monai.bundle's command line: it "
                             f"reads 'true' or 'false' as text), got {value!r}")
    if device is not None and not hasattr(device, "type"):
        from monai_rigidreg.core.device import resolve_device

        if str(device) == "auto":
            raise InputError("--device auto: leave --device out for the automatic choice, or give cpu, cuda or "
                             "cuda:N")
        resolve_device(device)


WHERE_TO_RUN = ("--bundle_root must name the bundle folder: from the repository root pass --config_file "
                "bundles/cbct_ct_rigid/configs/inference.json --bundle_root bundles/cbct_ct_rigid; from inside the "
                "bundle folder --config_file configs/inference.json (its default bundle_root '.' is then right)")
"""Where ``python -m monai.bundle run`` is run from, said where the bundle's weights are not found."""


def bundle_check_inputs(fixed: str | Path | None, moving: str | Path | None, output_dir: str | Path,
                        overwrite: bool = False, cascade_steps: Any = None, datalist: str | Path | None = None,
                        flags: dict[str, Any] | None = None, device: Any = None,
                        checkpoint: str | Path | None = None) -> None:
    """:func:`~monai_rigidreg.registration.inputs.check_register_inputs` for the bundle's ``inference.json`` (its first
    ``initialize`` step, before the network is built): a bad input ends the run with one line naming the problem and
    exit status 2. With a ``datalist`` of pairs (batch registration) the datalist must exist and each pair is checked
    when its turn comes (:class:`~monai_rigidreg.registration.pairs.RegistrationEvaluator`). ``flags`` and ``device``:
    as :func:`check_bundle_options`. ``checkpoint``: the weights the config loads next (``@bundle_root`` +
    ``/models/model.pt``); missing, the run ends saying where to run it from (:data:`WHERE_TO_RUN`) instead of in
    ``torch.load``'s traceback.

    For ``python -m monai.bundle run``: it raises ``SystemExit`` rather than an exception.
    """
    with bundle_errors():
        if checkpoint is not None and not Path(checkpoint).is_file():
            raise InputError(f"no network weights at {checkpoint}: {WHERE_TO_RUN}")
        check_bundle_options(flags, device)
        if not datalist:
            check_register_inputs(fixed, moving, output_dir, overwrite, cascade_steps)
            return
        if fixed or moving:
            raise InputError("give either --fixed/--moving (one pair) or --datalist (pairs), not both")
        if not Path(datalist).is_file():
            raise InputError("no such datalist file", datalist)
        if cascade_steps is not None:
            check_cascade_steps(cascade_steps)
        check_output_dir(output_dir, overwrite, allow_existing=True)


def bundle_evaluate(datalist: str | Path, methods: Any, output_dir: str | Path, registrar: RigidRegistrar,
                    max_cases: Any = None, overwrite: Any = False, sampler: Any = None) -> dict[str, Any]:
    """:func:`~monai_rigidreg.evaluation.evaluate.evaluate_datalist` for the bundle's ``evaluate.json``: prints the
    report; a bad datalist, method or output folder ends the run with one line and exit status 2 (was a traceback).

    With ``sampler`` (``multi_gpu_evaluate.json``: a ``DistributedSampler`` over the datalist's items, under
    ``torchrun``) this process registers the sampler's cases only and rank 0 merges every rank's results and writes
    the one report (:func:`~monai_rigidreg.evaluation.distributed.evaluate_distributed`); rank 0 prints it.
    """
    with bundle_errors():
        check_bundle_options({"overwrite": overwrite})
        if isinstance(methods, str) or not isinstance(methods, (list, tuple)):
            raise InputError(f"--methods must be a list, e.g. \"['network']\", got {methods!r}")
        if sampler is None:
            from monai_rigidreg.evaluation.evaluate import evaluate_datalist

            out = evaluate_datalist(datalist, list(methods), output_dir, registrar=registrar, max_cases=max_cases,
                                    overwrite=bool(overwrite))
            print(out["report"])
            return out
        import torch.distributed as dist

        from monai_rigidreg.evaluation.distributed import evaluate_distributed

        out = evaluate_distributed(datalist, list(methods), output_dir, registrar=registrar, sampler=sampler,
                                   max_cases=max_cases, overwrite=bool(overwrite))
        if not dist.is_initialized() or dist.get_rank() == 0:
            print(out["report"])
        return out


def bundle_register_files(registrar: RigidRegistrar, fixed: str | Path, moving: str | Path, output_dir: str | Path,
                          **kwargs: Any) -> dict[str, Path]:
    """:func:`~monai_rigidreg.registration.files.register_files` for the bundle's ``inference.json`` (``run``): errors
    as in :func:`bundle_check_inputs` (an unreadable image, for example, ends the run with one line and exit status
    2)."""
    with bundle_errors():
        return register_files(registrar, fixed, moving, output_dir, **kwargs)


def bundle_run(evaluator: RegistrationEvaluator) -> dict[str, Any]:
    """``evaluator.run()`` for the bundle's ``inference.json``: errors (and the failed pairs of a batch) end
    ``python -m monai.bundle run`` with one line and exit status 2 (:func:`bundle_errors`)."""
    with bundle_errors():
        return evaluator.run()
