"""What one registration call carries from stage to stage: its options (:class:`RegistrationOptions`), what the
stages have found so far (:class:`RegistrationState`) and its worker threads (:class:`Background`).

:meth:`~monai_rigidreg.registration.RigidRegistrar.__call__` makes one state and hands it to the stage methods in
call order (``RigidRegistrar._register``); nothing else keeps it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.core.geometry import Grid, params_to_matrix
from monai_rigidreg.registration.inputs import Inputs

__all__ = ["Background", "NetworkRun", "RegistrationOptions", "RegistrationState"]


@dataclass(frozen=True)
class RegistrationOptions:
    """A call's options (:func:`~monai_rigidreg.registration.register`), ``roi`` parsed and ``global_init``,
    ``keep_couch`` and ``thorough`` (the full path instead of the network-led one) resolved against the registrar's
    settings and ``fine_stage``."""

    refine: bool
    cascade_steps: int | None
    resample_moving: bool
    moving_fov: sitk.Image | None
    assess: bool
    global_init: bool
    roi: Any
    match: str
    keep_couch: bool
    allow_swapped: bool = False
    thorough: bool = False


@dataclass
class NetworkRun:
    """One network run from a start (``RigidRegistrar._run_from``): its grid and ``[1, x, y, z]`` tensors, the
    start and the residual (mm/deg about the grid centre) and the total fixed -> moving matrix (LPS mm);
    ``regression``: the learned regression's residual before the fine stage (mm/deg about the grid centre; ``None``
    where no fine stage ran, or in a cascade, ``cascade_steps > 1``, whose fine stage runs once per step)."""

    grid: Grid
    fixed_t: torch.Tensor
    moving_t: torch.Tensor
    start: np.ndarray
    residual: np.ndarray
    total: np.ndarray
    regression: np.ndarray | None = None

    @property
    def regression_total(self) -> np.ndarray | None:
        """The fixed -> moving matrix (LPS mm) of the regression's estimate before the fine stage, ``start o
        regression``, in the frame of :attr:`total` (``None`` where :attr:`regression` is)."""
        if self.regression is None:
            return None
        return self.start @ params_to_matrix(self.regression, self.grid.center())

    @property
    def sampling(self) -> np.ndarray | None:
        """The matrix the CBCT was sampled through onto ``grid`` (``None`` for the identity start)."""
        return None if np.allclose(self.start, np.eye(4)) else self.start


@dataclass
class RegistrationState:
    """What the stages of one call have found, in the order they find it.

    Attributes:
        options: the call's options.
        inputs: both images, their grids and the warnings about them (stage 1).
        weight_img: the match region's weight on the CT (``None``: the whole field of view).
        staged: the network's fine stage runs (``False``: the learned network alone).
        native: the last level runs (``native_level`` and ``staged``).
        fov_img: the CBCT's field of view on its grid (``None`` where nothing needs it).
        body: the CT's coarse body mask (``None``: couches kept, or nothing is body).
        weights: CT-frame images whose product is the match weight of the last level and the checks.
        pose_weights: those the network's runs and the choice between starts use (the region only weights the
            last level when ``region_last``).
        region_last: a match region applies to the last level (not to the search for the pose).
        run: the network's run from the winning start.
        params: the estimate (mm/deg about ``run.grid``'s centre until the result re-expresses it).
        net_params: the network's estimate (after the last level), before the refinement.
        fov_t: the field of view on ``run.grid``.
        early_swap: the swapped-input estimate started beside the last level.
        fov_sample: the CBCT's field of view sampled at 4 mm (:func:`~monai_rigidreg.registration.overlap.fov_sample`;
            ``None`` where there is no field of view).
        domain: the CT's box as a match weight (:func:`~monai_rigidreg.registration.overlap.ct_domain_weight`), where
            the CT does not cover the CBCT's tissue (``None``: it does, and nothing is restricted).
        other_runs: the network's runs from the other starts, best image match first (where the search ran them).
        region_blocks: the ROI's block check per estimate (its parameters' bytes), computed once per call (the
            network-led path's check and the confidence judge the same estimate).
        details, timings: what goes into the result's ``details`` and ``timings``.
    """

    options: RegistrationOptions
    inputs: Inputs
    t_start: float
    timings: dict[str, float] = field(default_factory=dict)
    details: dict[str, Any] = field(default_factory=dict)
    weight_img: sitk.Image | None = None
    staged: bool = True
    native: bool = True
    fov_img: sitk.Image | None = None
    body: sitk.Image | None = None
    body_cached: bool = False
    weights: list[sitk.Image] = field(default_factory=list)
    pose_weights: list[sitk.Image] = field(default_factory=list)
    region_last: bool = False
    run: NetworkRun | None = None
    params: np.ndarray | None = None
    net_params: np.ndarray | None = None
    fov_t: torch.Tensor | None = None
    early_swap: Background | None = None
    fov_sample: Any = None
    domain: sitk.Image | None = None
    other_runs: list[NetworkRun] = field(default_factory=list)
    region_blocks: dict[bytes, Any] = field(default_factory=dict)
    confidence: float = float("nan")
    flagged: bool = False


class Background:
    """``fn(*args, **kwargs)`` in a worker thread; :meth:`result` waits for it and returns its value or raises its
    exception. PyTorch and SimpleITK release the GIL in their kernels, so the global search's FFTs and sampling run
    while the main thread runs the network from the identity, and the confidence check's swapped-input network run
    beside the last level (``docs/results.md``, "Threads"). torch's intra-op thread count carries over to the worker
    thread."""

    def __init__(self, fn: Callable[..., Any], *args: Any, thread_name: str = "monai-rigidreg-worker",
                 **kwargs: Any) -> None:
        self._value: Any = None
        self._error: BaseException | None = None
        self.seconds = 0.0  # how long fn ran

        def run() -> None:
            t = time.perf_counter()
            try:
                self._value = fn(*args, **kwargs)
            except BaseException as exc:  # noqa: BLE001 - handed to the caller by result()
                self._error = exc
            self.seconds = time.perf_counter() - t

        self._thread = threading.Thread(target=run, name=thread_name, daemon=True)
        self._thread.start()

    def result(self) -> Any:
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value

    def wait(self) -> None:
        """Wait for the worker to finish, its result or error dropped (the caller is raising its own)."""
        self._thread.join()
