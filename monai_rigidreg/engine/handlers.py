"""Ignite handlers: per-epoch loss terms into the engine metrics, and the training-curve figure (paper Fig. 6)."""

from __future__ import annotations

import json
import logging
import math
import re
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

from ignite.engine import Events
from monai.handlers import CheckpointLoader, CheckpointSaver, TensorBoardStatsHandler

from monai_rigidreg.core.geometry import PARAM_NAMES

__all__ = [
    "load_matching_weights",
    "LossTermsHandler",
    "TrainingCurveHandler",
    "ResumeHandler",
    "TrainingCheckpointSaver",
    "OptionalTensorBoardStatsHandler",
    "plot_history",
]

logger = logging.getLogger(__name__)


class LossTermsHandler:
    """Average the criterion's per-term values over each epoch and publish them as ``engine.state.metrics``
    (``loss_ssim``, ``loss_ncc``, ... ``loss_sup``), where MONAI's stats and TensorBoard handlers pick them up.

    Args:
        criterion: a :class:`~monai_rigidreg.engine.RegistrationCriterion` (anything with ``last_terms``).
    """

    def __init__(self, criterion: Any) -> None:
        self.criterion = criterion
        self._sums: dict[str, float] = defaultdict(float)
        self._count = 0

    def attach(self, engine: Any) -> None:
        engine.add_event_handler(Events.EPOCH_STARTED, self._reset)
        engine.add_event_handler(Events.ITERATION_COMPLETED, self._accumulate)
        engine.add_event_handler(Events.EPOCH_COMPLETED, self._publish)

    def _reset(self, engine: Any) -> None:
        self._sums.clear()
        self._count = 0

    def _accumulate(self, engine: Any) -> None:
        for k, v in getattr(self.criterion, "last_terms", {}).items():
            self._sums[k] += float(v)
        self._count += 1

    def _publish(self, engine: Any) -> None:
        if self._count:
            for k, v in self._sums.items():
                engine.state.metrics[f"loss_{k}"] = v / self._count


class TrainingCurveHandler:
    """Record per-epoch training loss terms and validation errors; write ``history.json`` and ``curves.png``.

    The figure is the analog of the reference paper's Fig. 6: loss terms against epoch, and the validation
    per-axis translation (mm) and rotation (degrees) errors and TRE against epoch.

    Args:
        output_dir: where ``history.json`` and ``curves.png`` go.
        evaluator: the validation engine, whose ``state.metrics`` (``val_tx`` ... ``val_tre``) are read at each
            epoch end (attach this handler after the ``ValidationHandler`` so validation has run).
        every: write the figure every this many epochs (and at the end of training).
    """

    def __init__(self, output_dir: str | Path, evaluator: Any = None, every: int = 1) -> None:
        self.output_dir = Path(output_dir)
        self.evaluator = evaluator
        self.every = max(1, int(every))
        self.history: list[dict[str, float]] = []
        self._last_val_epoch = -1

    def attach(self, engine: Any) -> None:
        engine.add_event_handler(Events.STARTED, self._continue)
        engine.add_event_handler(Events.EPOCH_COMPLETED, self._record)
        engine.add_event_handler(Events.COMPLETED, self._write)

    def _continue(self, engine: Any) -> None:
        """A resumed run keeps the rows of the epochs its checkpoint had reached (attach after the resume)."""
        path = self.output_dir / "history.json"
        if engine.state.epoch > 0 and not self.history and path.is_file():
            try:
                rows = json.loads(path.read_text())
            except (OSError, ValueError):
                rows = []
            self.history = [r for r in rows if isinstance(r, dict) and r.get("epoch", 0) <= engine.state.epoch]

    def _record(self, engine: Any) -> None:
        row: dict[str, float] = {"epoch": float(engine.state.epoch)}
        row.update({k: float(v) for k, v in engine.state.metrics.items()
                    if k.startswith(("loss_", "train_")) and isinstance(v, (int, float))})
        if isinstance(engine.state.output, dict) and "loss" in engine.state.output:
            row["loss_last"] = float(engine.state.output["loss"])
        ev = self.evaluator
        if ev is not None and getattr(ev.state, "epoch", -1) != self._last_val_epoch and ev.state.metrics:
            self._last_val_epoch = ev.state.epoch
            row.update({k: float(v) for k, v in ev.state.metrics.items() if isinstance(v, (int, float))})
        self.history.append(row)
        if engine.state.epoch % self.every == 0:
            self._write(engine)

    def _write(self, engine: Any = None) -> None:
        self.output_dir.mkdir(parents=True, exist_ok=True)
        (self.output_dir / "history.json").write_text(json.dumps(self.history, indent=1))
        if self.history:
            plot_history(self.history, self.output_dir / "curves.png")


def plot_history(history: list[dict[str, float]], path: str | Path) -> Path:
    """Draw loss terms (log scale) and validation errors against epoch into ``path`` (PNG)."""
    # imported on use: the Agg backend must be chosen before pyplot is first imported, and a caller that never
    # plots does not pay for matplotlib (about 0.3-0.5 s: python -c "import matplotlib.pyplot")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs = [h["epoch"] for h in history]
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    for k in sorted({k for h in history for k in h if k.startswith("loss_") and k != "loss_last"}):
        vals = [abs(h.get(k, math.nan)) for h in history]
        if any(v > 0 for v in vals if not math.isnan(v)):
            axes[0].plot(epochs, vals, label=k[5:])
    axes[0].set_yscale("log")
    axes[0].set_title("training loss terms (|value|, epoch mean)")
    for ax, names, unit in ((axes[1], PARAM_NAMES[:3], "mm"), (axes[2], PARAM_NAMES[3:], "degrees")):
        for n in names:
            pts = [(h["epoch"], h[f"val_{n}"]) for h in history if f"val_{n}" in h]
            if pts:
                ax.plot(*zip(*pts), marker="o", ms=3, label=f"|Δ{n}|")
        ax.set_ylabel(unit)
        ax.set_title(f"validation absolute error ({unit})")
    pts = [(h["epoch"], h["val_tre"]) for h in history if "val_tre" in h]
    if pts:
        axes[1].plot(*zip(*pts), "k--", label="TRE")
    for ax in axes:
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    logger.info("training curves written to %s", path)
    return Path(path)


class TrainingProgressHandler:
    """Samples seen, wall time and where the time of an iteration goes (waiting for data vs the network step).

    Each epoch end puts ``train_samples`` (all samples since the run began, resumed runs included),
    ``train_wall_time_s`` (likewise), ``train_samples_per_s``, ``train_data_wait_s`` and ``train_step_s`` (mean per
    iteration over the epoch) into the engine's metrics (so :class:`TrainingCurveHandler` records them) and logs
    them in one line. Its totals are saved with the checkpoints (``state_dict``; put it in the saver's and the
    resume handler's dictionaries). At the start it tells a dataset with ``set_epoch`` (an endless sampler such as
    :class:`~monai_rigidreg.engine.sampler.RigidPairSampler`) the epoch it starts at, so a resumed run draws a new
    stream rather than the first run's again. Given the network, each epoch also records ``train_bfloat16`` (1.0
    where a submodule trains under bfloat16 autocast, its ``train_autocast``, else 0.0; the config chooses it by the
    machine, so a run resumed on other machines says per epoch which precision its encoders trained in), logged at
    the start.

    Args:
        batch_size: samples per iteration (per process).
        dataset: the training dataset (``set_epoch`` is called where it has one).
        world_size: processes training together.
        network: the network being trained (optional), for ``train_bfloat16``.
    """

    def __init__(self, batch_size: int, dataset: Any = None, world_size: int = 1, network: Any = None) -> None:
        self.batch_size = int(batch_size)
        self.dataset = dataset
        self.world_size = int(world_size)
        self.network = network
        self.samples = 0
        self.wall_time_s = 0.0
        self._reset()

    def _reset(self) -> None:
        self._wait = self._step = 0.0
        self._count = 0
        self._t_get = self._t_got = None

    def state_dict(self) -> dict[str, float]:
        return {"samples": self.samples, "wall_time_s": self.wall_time_s}

    def load_state_dict(self, state: dict[str, float]) -> None:
        self.samples = int(state.get("samples", 0))
        self.wall_time_s = float(state.get("wall_time_s", 0.0))

    def attach(self, engine: Any) -> None:
        engine.add_event_handler(Events.STARTED, self._started)
        engine.add_event_handler(Events.GET_BATCH_STARTED, self._get_started)
        engine.add_event_handler(Events.GET_BATCH_COMPLETED, self._get_completed)
        engine.add_event_handler(Events.ITERATION_COMPLETED, self._iteration_completed)
        engine.add_event_handler(Events.EPOCH_COMPLETED, self._epoch_completed)

    def _bfloat16(self) -> float | None:
        """1.0 where a submodule of the network trains under bfloat16 autocast, 0.0 where none does, None without
        the network."""
        if self.network is None:
            return None
        return float(any(getattr(m, "train_autocast", None) == "bfloat16" for m in self.network.modules()))

    def _started(self, engine: Any) -> None:
        if self.dataset is not None and hasattr(self.dataset, "set_epoch"):
            self.dataset.set_epoch(engine.state.epoch)
        bfloat16 = self._bfloat16()
        if bfloat16 is not None:
            logger.info("training precision of the encoders: %s", "bfloat16 autocast" if bfloat16 else "float32")
        self._last = time.perf_counter()
        self._epoch_start = self._last
        self._samples_at_epoch = self.samples
        self._reset()

    def _get_started(self, engine: Any) -> None:
        self._t_get = time.perf_counter()

    def _get_completed(self, engine: Any) -> None:
        self._t_got = time.perf_counter()
        if self._t_get is not None:
            self._wait += self._t_got - self._t_get

    def _iteration_completed(self, engine: Any) -> None:
        now = time.perf_counter()
        if self._t_got is not None:
            self._step += now - self._t_got
        self._count += 1
        self.samples += self.batch_size * self.world_size
        self.wall_time_s += now - self._last
        self._last = now

    def _epoch_completed(self, engine: Any) -> None:
        now = time.perf_counter()
        self.wall_time_s += now - self._last  # handlers after the last iteration (validation, checkpoints)
        self._last = now
        elapsed = max(now - self._epoch_start, 1e-9)
        n = max(self._count, 1)
        stats = {"train_samples": float(self.samples), "train_wall_time_s": self.wall_time_s,
                 "train_samples_per_s": (self.samples - self._samples_at_epoch) / elapsed,
                 "train_data_wait_s": self._wait / n, "train_step_s": self._step / n}
        bfloat16 = self._bfloat16()
        if bfloat16 is not None:
            stats["train_bfloat16"] = bfloat16
        engine.state.metrics.update(stats)
        logger.info("epoch %d: %d samples seen, %.1f h of training, %.2f samples/s this epoch; per iteration "
                    "%.3f s waiting for data, %.3f s in the network step", engine.state.epoch, self.samples,
                    self.wall_time_s / 3600, stats["train_samples_per_s"], stats["train_data_wait_s"],
                    stats["train_step_s"])
        self._epoch_start = now
        self._samples_at_epoch = self.samples
        self._reset()


def load_matching_weights(network: Any, state: dict[str, Any]) -> tuple[list[str], list[str], list[str]]:
    """Load into ``network`` the tensors of ``state`` (a state dict, or a training checkpoint with ``"network"``)
    whose names and shapes it has; the others keep their values.

    Returns ``(taken, fresh, unused)``: the names loaded, the network's names not loaded, the state's names not used
    (each sorted). Raises ``ValueError`` when nothing matches."""
    if isinstance(state.get("network"), dict):
        state = state["network"]
    own = network.state_dict()
    taken = {k: v for k, v in state.items() if k in own and tuple(own[k].shape) == tuple(v.shape)}
    if not taken:
        raise ValueError("no tensor matches the network's names and shapes")
    network.load_state_dict(taken, strict=False)
    return sorted(taken), sorted(k for k in own if k not in taken), sorted(k for k in state if k not in taken)


class ResumeHandler:
    """Resume training from the newest ``checkpoint_epoch=N.pt`` in ``ckpt_dir`` (written by MONAI's
    ``CheckpointSaver`` with ``save_interval``), when ``resume`` is true and one exists; otherwise start from
    ``init_weights`` (network weights only: a fine-tuning run) where given, or from scratch.

    Args:
        ckpt_dir: checkpoint directory.
        load_dict: objects to restore, e.g. ``{"network": net, "optimizer": opt}``; the engine this handler is
            attached to is restored too (as ``"trainer"``), so that the epoch count resumes.
        resume: switch (a config override: ``--resume true``).
        map_location: device to load tensors onto.
        init_weights: a network state dict file (e.g. the shipped ``models/model.pt``) loaded into
            ``load_dict["network"]`` when training does not resume from a checkpoint; the optimizer, the learning
            rate schedule and the epoch count start afresh. A resumed run ignores it (the checkpoint holds the
            network it had reached). It may also be a training checkpoint (its ``"network"`` is taken).
        init_partial: load only the tensors of ``init_weights`` whose names and shapes the network has, and log
            the rest (a new design that keeps part of an earlier one, e.g. new coarse-level layers beside trained
            local levels); it stops with an error when nothing matches. Default: every tensor must match.
    """

    def __init__(self, ckpt_dir: str | Path, load_dict: dict[str, Any], resume: bool = True,
                 map_location: Any = None, init_weights: str | Path | None = None, init_partial: bool = False
                 ) -> None:
        self.ckpt_dir = Path(ckpt_dir)
        self.load_dict = load_dict
        self.resume = bool(resume)
        self.map_location = map_location
        self.init_weights = Path(init_weights) if init_weights else None
        self.init_partial = bool(init_partial)
        if self.init_weights is not None and not self.init_weights.is_file():
            raise FileNotFoundError(f"init_weights: no such file: {self.init_weights}")

    def _start_from_weights(self) -> None:
        if self.init_weights is None:
            return
        import torch  # only when fine-tuning

        state = torch.load(self.init_weights, map_location=self.map_location, weights_only=True)
        if isinstance(state.get("network"), dict):
            state = state["network"]
        network = self.load_dict["network"]
        if not self.init_partial:
            network.load_state_dict(state)
            logger.info("network initialised from %s (optimizer and schedule start afresh)", self.init_weights)
            return
        try:
            taken, fresh, unused = load_matching_weights(network, state)
        except ValueError as exc:
            raise ValueError(f"init_weights {self.init_weights}: {exc}") from None
        logger.info("network initialised in part from %s: %d of %d tensors taken; freshly initialised: %s; "
                    "not used: %s (optimizer and schedule start afresh)", self.init_weights, len(taken),
                    len(taken) + len(fresh), ", ".join(fresh) or "none", ", ".join(unused) or "none")

    def latest(self) -> Path | None:
        """The newest epoch checkpoint, or ``None``."""
        found = []
        for p in self.ckpt_dir.glob("*checkpoint*epoch=*.pt"):
            m = re.search(r"epoch=(\d+)", p.name)
            if m:
                found.append((int(m.group(1)), p))
        return max(found)[1] if found else None

    def attach(self, engine: Any) -> None:
        if not self.resume:
            self._start_from_weights()
            return
        path = self.latest()
        if path is None:
            logger.info("no checkpoint in %s: training starts from %s", self.ckpt_dir,
                        self.init_weights or "scratch")
            self._start_from_weights()
            return
        logger.info("resuming from %s", path)
        load_dict = {**self.load_dict, "trainer": engine}
        CheckpointLoader(str(path), load_dict, map_location=self.map_location).attach(engine)


class TrainingCheckpointSaver:
    """MONAI ``CheckpointSaver`` of ``save_dict`` plus the engine it is attached to (as ``"trainer"``), every
    ``save_interval`` epochs, keeping ``n_saved`` files ``checkpoint_epoch=N.pt``: what :class:`ResumeHandler`
    resumes from. (A bundle config cannot reference the trainer inside the trainer's own handler list.)

    Args:
        save_dir: checkpoint directory.
        save_dict: objects to save besides the trainer, e.g. ``{"network": net, "optimizer": opt}``.
        save_interval: epochs between checkpoints.
        n_saved: checkpoints kept.
    """

    def __init__(self, save_dir: str | Path, save_dict: dict[str, Any], save_interval: int = 1,
                 n_saved: int = 1) -> None:
        self.save_dir = str(save_dir)
        self.save_dict = save_dict
        self.save_interval = int(save_interval)
        self.n_saved = int(n_saved)

    def attach(self, engine: Any) -> None:
        CheckpointSaver(self.save_dir, {**self.save_dict, "trainer": engine}, file_prefix="checkpoint",
                        save_interval=self.save_interval, n_saved=self.n_saved, epoch_level=True).attach(engine)


class OptionalTensorBoardStatsHandler:
    """MONAI's ``TensorBoardStatsHandler`` where TensorBoard is installed; elsewhere a warning and no TensorBoard
    logs (TensorBoard is the ``tensorboard`` extra, not a dependency: training must run without it).

    Args:
        kwargs: ``TensorBoardStatsHandler`` arguments (``log_dir``, ``tag_name``, ``output_transform``, ...).
    """

    _warned = False  # one warning per process, not one per handler

    def __init__(self, **kwargs: Any) -> None:
        self.kwargs = kwargs

    def attach(self, engine: Any) -> None:
        try:  # an optional extra: imported where it is used
            from torch.utils.tensorboard import SummaryWriter  # noqa: F401
        except ImportError as exc:
            if not OptionalTensorBoardStatsHandler._warned:
                logger.warning("TensorBoard is not installed (%s): training runs without TensorBoard logs; the "
                               "history (history.json) and curves.png are still written. pip install tensorboard "
                               "to get them", str(exc).splitlines()[0])
                OptionalTensorBoardStatsHandler._warned = True
            return
        TensorBoardStatsHandler(**self.kwargs).attach(engine)
