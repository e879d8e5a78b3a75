"""Helpers shared by the benchmark scripts: printing with a copy for ``--results``, the machine load while a
benchmark runs, and finding the real CTs of ``../shared/data`` (or a user's paths)."""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]


class Tee:
    """Print and keep every line, for ``--results``."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def __call__(self, text: str = "") -> None:
        print(text, flush=True)
        self.lines.append(text)

    def write(self, path: Path | None) -> None:
        """Every line printed so far into ``path`` (``--results``; nothing when ``None``), its folder made."""
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text("\n".join(self.lines) + "\n", encoding="utf-8")


class LoadMonitor(threading.Thread):
    """Samples the 1-minute load average every ``period`` seconds while the benchmark runs."""

    def __init__(self, period: float = 10.0) -> None:
        super().__init__(daemon=True)
        self.period = period
        self.samples: list[float] = [os.getloadavg()[0]]
        self._stop_event = threading.Event()

    def run(self) -> None:
        while not self._stop_event.wait(self.period):
            self.samples.append(os.getloadavg()[0])

    def stop(self) -> None:
        self._stop_event.set()
        self.samples.append(os.getloadavg()[0])

    def describe(self) -> str:
        s = np.asarray(self.samples)
        return f"min {s.min():.2f}, mean {s.mean():.2f}, max {s.max():.2f} over {len(s)} samples"


def ct_name(path: Path) -> str:
    name = path.name
    for suffix in (".nii.gz", ".nii", ".mha", ".mhd", ".nrrd"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name


TRAINED_ON_ENV = "BENCH_TRAINED_ON"
"""Environment variable: the real CTs (space-separated file stems) the evaluated network was trained on, where that
is not the shipped network's list (a leave-one-CT-out fold of ``scripts/train_loco.sh``)."""


def _named_in_env() -> tuple[str, ...]:
    """The CTs :data:`TRAINED_ON_ENV` names (none where it is unset or empty)."""
    return tuple(os.environ.get(TRAINED_ON_ENV, "").split())


def trained_on() -> tuple[str, ...]:
    """The real CTs the evaluated network was trained on: :data:`TRAINED_ON_ENV`'s where set, else
    :data:`~monai_rigidreg.io.shared_data.TRAINING_CTS`."""
    from monai_rigidreg.io.shared_data import TRAINING_CTS

    return _named_in_env() or TRAINING_CTS


def is_training_ct(name: str) -> bool:
    """Whether the real CT of this file stem (``thorax_4dct_phase00_itkelastix``, also with a data folder's suffix
    such as ``_multi30``) is one the evaluated network was trained on (:func:`trained_on`): its cases must not be
    reported as held out."""
    return any(name == t or name.startswith(f"{t}_") for t in trained_on())


def training_mark(name: str) -> str:
    """The heading mark of a CT's section: held out of training, or a training CT."""
    whose = f"the evaluated network, {TRAINED_ON_ENV}" if _named_in_env() else "the shipped network"
    return (f" -- TRAINING CT (used to train {whose}; not held out)" if is_training_ct(name)
            else " (held out of training)")


def add_registrar_options(ap: argparse.ArgumentParser) -> None:
    """The default path's candidates and switches, set on a loaded registrar by :func:`apply_registrar_options`:
    ``--native-final-norm-mm`` (the last level's final pass on the normalised local contrast, off by default) and
    ``--fine-stage-choice-mm`` (the fine-stage choice's limit; ``off``: never run, for the A/B)."""
    ap.add_argument("--native-final-norm-mm", type=float, default=None,
                    help="the last level's final pass on the normalised local contrast at this sigma (mm; "
                         "RigidRegistrar native_final_norm_mm; default: the bundle's, off)")
    ap.add_argument("--fine-stage-choice-mm", default=None, type=_mm_or_off,
                    help="the fine-stage choice's limit (mm; RigidRegistrar fine_stage_choice_mm), or 'off' "
                         "(default: the bundle's)")


def _mm_or_off(text: str) -> float | str:
    if text == "off":
        return text
    value = float(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"expected millimetres >= 0 or 'off', got {text!r}")
    return value


def apply_registrar_options(registrar: Any, args: argparse.Namespace) -> None:
    """Set the options of :func:`add_registrar_options` that were given on ``registrar``."""
    if registrar is None:
        return
    if args.native_final_norm_mm is not None:
        registrar.native_final_norm_mm = float(args.native_final_norm_mm)
    choice = args.fine_stage_choice_mm
    if choice is not None:
        registrar.fine_stage_choice_mm = None if choice == "off" else float(choice)


def registrar_options_line(registrar: Any) -> str:
    """The settings :func:`apply_registrar_options` may change, as ``registrar`` has them (for a report's header)."""
    return (f"registrar: fine_stage_choice_mm {getattr(registrar, 'fine_stage_choice_mm', None)}, "
            f"native_final_norm_mm {getattr(registrar, 'native_final_norm_mm', None)}")


def find_cts(requested: list[str] | None, out: Tee, defaults: tuple[str, ...]) -> list[Path]:
    """The CTs to use (paths, or names of files in the data folder); absent ones are skipped with the reason."""
    from monai_rigidreg.io.shared_data import shared_data_dir

    dirs = [d for d in (shared_data_dir(), REPO.parent / "shared" / "data", Path("../shared/data")) if d is not None]
    found = []
    for r in requested or defaults:
        p = Path(r).expanduser()
        if p.exists():
            found.append(p.resolve())
            continue
        names = [r] if r.endswith((".nii.gz", ".nii", ".mha", ".nrrd")) else [r, f"{r}.nii.gz"]
        hit = next((d / n for n in names for d in dirs if (d / n).is_file()), None)
        if hit is None:
            where = ", ".join(str(d) for d in dict.fromkeys(dirs)) or "no data folder ($MONAI_RIGIDREG_DATA unset)"
            out(f"skipped {r}: not found in {where}")
        else:
            found.append(hit.resolve())
    return found


def set_threads(threads: int) -> None:
    """torch, SimpleITK and ITK thread counts (and the OpenMP/MKL environment) before the libraries start their
    pools: benchmarks compare methods at the same number of threads."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"):
        os.environ[var] = str(threads)
    import SimpleITK as sitk
    import torch

    torch.set_num_threads(threads)
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(threads)



def start_cpu_run(ap: argparse.ArgumentParser, argv: list[str] | None, module: str,
                  bundle: str | Callable[[argparse.Namespace], str], threads: int = 1
                  ) -> tuple[Any, Tee, LoadMonitor, float]:
    """The common start of a CPU benchmark: ``ap`` gains ``--threads`` (default ``threads``) and ``--results``;
    ``argv`` parsed, the threads set (:func:`set_threads`), the head of the report written (:func:`start_run`, with
    ``bundle``, or ``bundle(args)``, as the bundle line). Returns the parsed arguments, the output, the load monitor
    and the start time."""
    ap.add_argument("--threads", type=int, default=threads)
    ap.add_argument("--results", type=Path, default=None, help="also write the report to this file")
    args = ap.parse_args(argv)
    set_threads(args.threads)
    out = Tee()
    monitor, t0 = start_run(out, module, args.threads, "cpu", bundle(args) if callable(bundle) else bundle)
    return args, out, monitor, t0


def start_registrar_run(ap: argparse.ArgumentParser, module: str) -> tuple[Any, Tee, LoadMonitor, float, Any]:
    """The common start of a benchmark that times or scores the shipped bundle's registrar on the CPU: ``ap`` (with
    its own ``--threads``) gains ``--results``; returns the parsed arguments, the output, the load monitor, the start
    time (:func:`start_run`) and the registrar, loaded after :func:`set_threads`."""
    ap.add_argument("--results", type=Path, default=None, help="write the printed report here")
    args = ap.parse_args()
    out = Tee()
    monitor, t0 = start_run(out, module, args.threads, "cpu", "the shipped bundle")
    set_threads(args.threads)
    import monai_rigidreg

    return args, out, monitor, t0, monai_rigidreg.RigidRegistrar.from_bundle(device="cpu")


PEER_MASKS = {"tool": None, "fov": True, "none": False}
"""What the peer tools (``ants``, ``greedy``) get as their moving-image mask in a benchmark (``--peer-mask``): each
tool's default (``tool``: :data:`~monai_rigidreg.registration.peers.PEER_FOV_MASK`), the CBCT's reconstructed field
of view (``fov``) or nothing (``none``, as elastix's default rigid map runs in ``evaluate`` and ``bench_real_ct``)."""


def add_peer_mask_option(ap: argparse.ArgumentParser) -> None:
    """``--peer-mask {tool,fov,none}`` (:data:`PEER_MASKS`) on a benchmark that runs the peer tools; read it with
    :func:`peer_mask`."""
    ap.add_argument("--peer-mask", choices=tuple(PEER_MASKS), default="tool",
                    help="the peer tools' (ants, greedy) moving-image mask: each tool's default (tool, the default), "
                         "the CBCT's field of view (fov) or none")


def peer_mask(args: argparse.Namespace) -> bool | None:
    """``use_mask`` of :func:`~monai_rigidreg.registration.peers.register_peer` for ``--peer-mask``."""
    return PEER_MASKS[args.peer_mask]


def peer_mask_line(args: argparse.Namespace, methods: list[str], out: Tee) -> None:
    """One line saying what each peer tool of ``methods`` gets as its moving-image mask (``--peer-mask``)."""
    from monai_rigidreg.registration.peers import PEER_METHODS, peer_uses_mask

    said = [f"{m} {'the CBCT field of view' if peer_uses_mask(m, peer_mask(args)) else 'none'}"
            for m in methods if m in PEER_METHODS]
    if said:
        out(f"peer tools' moving-image mask (--peer-mask {args.peer_mask}): {', '.join(said)}")


def checked_peers(methods: list[str], out: Tee) -> list[str]:
    """``methods`` less the peer tools (``ants``, ``greedy``) that are not installed or fail their convention check
    (:func:`monai_rigidreg.registration.peers.check_convention`: the known motion of a small pair recovered through
    the tool's own output): a peer's numbers count only after the check passes. Each check prints one line."""
    from monai_rigidreg.registration.peers import CONVENTION_TOLERANCE, PEER_METHODS, check_convention, peer_available

    kept = []
    for m in methods:
        if m not in PEER_METHODS:
            kept.append(m)
            continue
        if not peer_available(m):
            out(f"skipped method {m}: {'antspyx' if m == 'ants' else 'picsl-greedy'} is not installed "
                "(pip install 'monai-rigidreg[bench]')")
            continue
        from importlib.metadata import version

        dist = "antspyx" if m == "ants" else "picsl-greedy"
        t = time.perf_counter()
        check = check_convention(m)
        errors = " ".join(f"{e:.2f}" for e in check["errors"])
        verdict = "passed" if check["ok"] else "FAILED, the method is left out"
        out(f"convention check of {m} ({dist} {version(dist)}): known motion {signed(np.asarray(check['truth']))}, "
            f"errors {errors} (tolerance {CONVENTION_TOLERANCE[0]:g} mm / {CONVENTION_TOLERANCE[1]:g} degrees): "
            f"{verdict} ({time.perf_counter() - t:.1f} s)")
        if check["ok"]:
            kept.append(m)
    return kept


def median_time(fn: Callable[[], object], repeats: int, warm_up: bool = False) -> float:
    """Median wall seconds of ``repeats`` calls of ``fn`` (after one untimed call with ``warm_up``: the process's
    first-use costs)."""
    if warm_up:
        fn()
    times = []
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def start_run(out: Tee, module: str, threads: int, device: str, bundle: str) -> tuple[LoadMonitor, float]:
    """The head of a result file (the command as run, the date, the machine, the bundle, the load at the start) and
    the load monitor and start time of the run, for :func:`end_run`. ``module``: the script's ``__spec__.name``."""
    import platform
    import shlex

    import SimpleITK as sitk
    import torch

    monitor = LoadMonitor()
    monitor.start()
    t_start = time.perf_counter()
    for line in [
        f"command: python -m {shlex.join([module, *sys.argv[1:]])}",
        f"date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}",
        f"machine: {platform.node()} {platform.machine()}, {os.cpu_count()} CPU cores; threads {threads}; "
        f"torch {torch.__version__}, SimpleITK {sitk.Version.VersionString()}; device {device}",
        f"bundle: {bundle}",
        f"load average at start (1/5/15 min): {' '.join(f'{v:.2f}' for v in os.getloadavg())}",
    ]:
        out(line)
    return monitor, t_start


def end_run(out: Tee, monitor: LoadMonitor, t_start: float, results: Path | None, notes: list[str]) -> None:
    """The tail of a result file (a "Run" section: ``notes``, the wall time, the load during the run and at its
    end), and the file written to ``results`` when given."""
    monitor.stop()
    out("Run")
    out()
    for line in notes:
        out(f"- {line}")
    out(f"- total wall time {time.perf_counter() - t_start:.0f} s; 1-minute load average during the run: "
        f"{monitor.describe()}; at the end (1/5/15 min): {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    out(f"- timings are indicative only: the {os.cpu_count()} cores may have been shared with other jobs "
        "(see the load)")
    out.write(results)
    if results is not None:
        print(f"written {results}")


def pose_error(truth: object, truth_center: object, estimate: object, estimate_center: object,
               points: np.ndarray) -> tuple[np.ndarray, float]:
    """The error of an estimate against the truth (each six parameters, mm / degrees, about its centre): the residual
    motion ``truth^-1 estimate`` as six parameters about the truth's centre (its mean over cases is a bias), and the
    mean distance (mm) between the two transforms' images of ``points`` (``[n, 3]`` LPS mm, the TRE)."""
    from monai_rigidreg.core.geometry import invert_matrix, matrix_to_params, params_to_matrix

    t = params_to_matrix(truth, truth_center)
    e = params_to_matrix(estimate, estimate_center)
    moved = np.c_[points, np.ones(len(points))]
    tre = float(np.linalg.norm((moved @ (e - t).T)[:, :3], axis=1).mean())
    return matrix_to_params(invert_matrix(t) @ e, truth_center), tre


AXES = ("tx", "ty", "tz", "rx", "ry", "rz")
"""The six parameters' names (mm, degrees), as ``monai_rigidreg.PARAM_NAMES``."""


def signed(values: object) -> str:
    """``"tx +1.2 ty -0.3 ..."``: six parameters (mm, degrees) with their signs, for a case's error or motion."""
    return " ".join(f"{a} {v:+.1f}" for a, v in zip(AXES, values))


def script_parser(doc: str | None) -> argparse.ArgumentParser:
    """A benchmark's argument parser, its module docstring (method, usage) as the ``--help`` text, as written."""
    return argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)


def fine_stage_choice_summary(choices: list[dict[str, Any] | None]) -> str:
    """One line on the default path's fine-stage choice over a benchmark's cases (``details.fine_stage_choice`` of
    each, ``None`` where it was not recorded): how far the fine stage moved the regression's estimate, on how many
    cases the choice ran (a move beyond ``fine_stage_choice_mm``) and on how many the regression's end pose won."""
    got = [c for c in choices if c]
    if not got:
        return "fine-stage choice: not recorded"
    moves = np.asarray([c["move_mm"] for c in got], dtype=np.float64)
    ran = [c for c in got if "kept" in c]
    kept = sum(c["kept"] == "regression" for c in ran)
    return (f"fine-stage choice: the fine stage moved the regression's estimate median {np.median(moves):.2f} mm, "
            f"max {moves.max():.2f} mm over {len(got)} cases; the choice ran on {len(ran)}, the regression's end "
            f"pose kept on {kept}")
