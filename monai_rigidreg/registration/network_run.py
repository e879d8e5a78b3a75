"""Stage 3 of a registration: the network run from a start.

:class:`NetworkRuns` is the part of :class:`~monai_rigidreg.registration.RigidRegistrar` that puts images on the
network grid (the training preprocessing, without MONAI) and runs the network from one or several starts in one
batch; a start is a 4x4 fixed -> moving matrix (LPS mm), the network estimates the residual about its grid's
centre, and the run's total is ``start o residual`` (:class:`~monai_rigidreg.registration.state.NetworkRun`).
"""

from __future__ import annotations

import contextlib
import functools
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch
from torch import nn

from monai_rigidreg.core.geometry import Grid, invert_matrix, params_to_matrix, transform_points
from monai_rigidreg.core.grid_sampling import normalize_hu, sitk_on_grid
from monai_rigidreg.core.network_grid import NetworkGridSpec
from monai_rigidreg.networks import cascade_register
from monai_rigidreg.registration.body import without_couch
from monai_rigidreg.registration.inputs import check_cascade_steps
from monai_rigidreg.registration.match_region import weight_on_grid
from monai_rigidreg.registration.state import NetworkRun

__all__ = ["NetworkRuns"]


class NetworkRuns:
    """Preprocessing onto the network grid and network runs from starts, for a class that sets ``grid_spec``
    (:class:`~monai_rigidreg.core.network_grid.NetworkGridSpec`), ``network``, ``device``, ``hu_range``,
    ``cascade_steps``, ``inferer``, ``accepts_weight`` and ``antialias`` (:class:`~monai_rigidreg.registration.
    RigidRegistrar` does)."""

    grid_spec: NetworkGridSpec
    context_grid_spec: NetworkGridSpec | None  # the CT context's grid, for a regression that takes one
    network: nn.Module
    device: torch.device
    hu_range: tuple[float, float]
    cascade_steps: int
    inferer: Callable[..., torch.Tensor] | None
    accepts_weight: bool
    antialias: bool

    def network_grid(self, fixed: sitk.Image, moving: sitk.Image | None = None) -> Grid:
        """The inference placement of the network grid: centred on the CBCT (moving) centre
        (:meth:`~monai_rigidreg.core.network_grid.NetworkGridSpec.on_moving`), or on the fixed image without a CBCT.

        Estimates on this grid are about its centre; the registrar re-expresses them about the fixed image centre.
        """
        return self.grid_spec.on_moving(moving) if moving is not None else self.grid_spec.on_fixed(fixed)

    def preprocess(self, image: sitk.Image, grid: Grid, matrix: np.ndarray | None = None) -> torch.Tensor:
        """``[1, x, y, z]`` normalized plain tensor of ``image`` on the network grid (the training preprocessing:
        :class:`~monai_rigidreg.transforms.ResampleToNetworkGrid` then :class:`~monai_rigidreg.transforms.NormalizeHU`,
        through their MONAI-free functions in :mod:`~monai_rigidreg.core.grid_sampling`);
        ``matrix``: sample ``image`` through this 4x4 grid -> image transform (LPS mm; a start estimate)."""
        out = self._on_grid(image, grid, "bilinear", self.hu_range[0], matrix)
        return normalize_hu(out, self.hu_range[0], self.hu_range[1]).float()

    def _on_grid(self, image: sitk.Image, grid: Grid, mode: str, padding_value: float,
                 matrix: np.ndarray | None = None) -> torch.Tensor:
        """``[1, x, y, z]`` float32 plain tensor of ``image`` resampled onto ``grid`` (no normalization).

        The ``[z, y, x]`` array is viewed as ``[x, y, z]`` without a copy, so for a CT much larger than the grid only
        the part the grid covers is transposed, and plain tensors skip ``MetaTensor`` bookkeeping in the network.
        """
        return sitk_on_grid(image, grid, mode, padding_value, antialias=self.antialias, matrix=matrix)

    def estimate(self, moving_t: torch.Tensor, fixed_t: torch.Tensor, grid: Grid, steps: int | None = None,
                 fixed_weight: torch.Tensor | None = None) -> np.ndarray:
        """Network (+ cascade) estimate ``[6]`` (numpy, mm/deg about the grid centre) from preprocessed
        ``[1, x, y, z]`` tensors on ``grid``; ``fixed_weight``: optional ``[1, x, y, z]`` match-region weights
        on the grid (passed to the network as ``fixed_weight``)."""
        return self.estimate_batch(moving_t[None], fixed_t[None], grid, steps,
                                   None if fixed_weight is None else fixed_weight[None])[0]

    @torch.no_grad()
    def estimate_batch(self, moving_t: torch.Tensor, fixed_t: torch.Tensor, grid: Grid, steps: int | None = None,
                       fixed_weight: torch.Tensor | None = None) -> np.ndarray:
        """:meth:`estimate` for a batch: ``[B, 1, x, y, z]`` tensors on grids of ``grid``'s size and spacing ->
        ``[B, 6]`` (numpy, mm/deg about each case's grid centre)."""
        k = self.cascade_steps if steps is None else check_cascade_steps(steps)
        m = moving_t.to(self.device)
        f = fixed_t.to(self.device)
        kwargs = {}
        if fixed_weight is not None and self.accepts_weight:
            kwargs["fixed_weight"] = fixed_weight.to(self.device)
        if self.inferer is None:
            net = functools.partial(self.network, **kwargs) if kwargs else self.network
        else:
            net = functools.partial(self.inferer, network=self.network, **kwargs)
        params = cascade_register(net, m, f, grid, steps=k)
        return params.double().cpu().numpy()

    def _start_tensors(self, fixed_img: sitk.Image, moving_img: sitk.Image, start: np.ndarray,
                       body: sitk.Image | None = None) -> tuple[Grid, torch.Tensor, torch.Tensor]:
        """The network grid for a start (4x4 fixed -> moving, LPS mm), centred on the CT point the start maps to the
        CBCT centre, and ``[1, x, y, z]`` normalized CT and CBCT on it: the CBCT sampled through the start (one
        interpolation), the CT with its tissue-like voxels outside ``body`` (the couch) set to air."""
        sampling = None if np.allclose(start, np.eye(4)) else start
        center = Grid.from_sitk(moving_img).center()
        if sampling is not None:
            center = transform_points(invert_matrix(sampling), center[None])[0]
        grid = self.grid_spec.centered(center)
        fixed_t = self.preprocess(fixed_img, grid)
        moving_t = self.preprocess(moving_img, grid, sampling)
        if body is not None:
            fixed_t = without_couch(fixed_t, self._on_grid(body, grid, "bilinear", 0.0), self.hu_range)
        return grid, fixed_t, moving_t

    def _context(self, fixed_img: sitk.Image, grid: Grid, body: sitk.Image | None) -> torch.Tensor:
        """``[1, *context size]`` normalized CT on the context grid centred as ``grid`` (a regression that takes a
        CT context: same centre, ``context_factor`` times the spacing), the couch removed as on the network grid."""
        ctx_grid = self.context_grid_spec.centered(grid.center())
        ctx = self.preprocess(fixed_img, ctx_grid)
        if body is not None:
            ctx = without_couch(ctx, self._on_grid(body, ctx_grid, "bilinear", 0.0), self.hu_range)
        return ctx

    def _run_from(self, fixed_img: sitk.Image, moving_img: sitk.Image, start: np.ndarray, steps: int | None,
                  weights: Sequence[sitk.Image], timings: dict[str, float], body: sitk.Image | None = None
                  ) -> NetworkRun:
        """The network from a start (4x4 fixed -> moving, LPS mm) on :meth:`_start_tensors`' grid and tensors: the
        network estimates the residual and the total is ``start o residual``. ``weights``: CT-frame images whose
        product on the grid is the match weight; ``body``: the CT's body (tissue-like voxels outside it, the couch,
        become air). Adds to ``timings["preprocess"]`` and ``["network"]``."""
        return self._runs_from(fixed_img, moving_img, [start], steps, weights, timings, body)[0]

    def _runs_from(self, fixed_img: sitk.Image, moving_img: sitk.Image, starts: Sequence[np.ndarray],
                   steps: int | None, weights: Sequence[sitk.Image], timings: dict[str, float],
                   body: sitk.Image | None = None) -> list[NetworkRun]:
        """:meth:`_run_from` for several starts in one batch of the network (the global search's candidates):
        each start has its own grid and tensors, the network sees them as one ``[B, 1, x, y, z]`` batch. Every
        operation of the network and its fine stage is per case, so a case's estimate is the one it gets alone, but
        for the fine stage's early stop, which waits for the slowest case of the batch (a few more steps of the
        same iteration)."""
        t = time.perf_counter()
        prepared = [self._start_tensors(fixed_img, moving_img, start, body) for start in starts]
        weight_ts = [weight_on_grid(weights, grid) for grid, _, _ in prepared]
        fixed_in = [f for _, f, _ in prepared]
        if self.context_grid_spec is not None:  # the CT context rides along as a second channel of the fixed input
            fixed_in = [torch.cat([f, self._context(fixed_img, grid, body)], 0) for (grid, _, _), f in
                        zip(prepared, fixed_in)]
        timings["preprocess"] = timings.get("preprocess", 0.0) + time.perf_counter() - t
        t = time.perf_counter()
        # the network works about its grid's centre: a grid of the same size and spacing stands for all of them
        canonical = self.grid_spec.canonical()
        with _regression_estimates(self.network, steps or self.cascade_steps, len(starts)) as regressions:
            residuals = self.estimate_batch(torch.stack([m for _, _, m in prepared]),
                                            torch.stack(fixed_in), canonical, steps,
                                            None if weight_ts[0] is None else torch.stack(weight_ts))
        timings["network"] = timings.get("network", 0.0) + time.perf_counter() - t
        runs = []
        for k, ((grid, fixed_t, moving_t), start, residual) in enumerate(zip(prepared, starts, residuals)):
            total = start @ params_to_matrix(residual, grid.center())
            runs.append(NetworkRun(grid, fixed_t, moving_t, start, residual, total,
                                   None if regressions is None or len(regressions) != 1 else regressions[0][k]))
        return runs


@contextlib.contextmanager
def _regression_estimates(network: nn.Module, steps: int, batch: int) -> Iterator[list[np.ndarray] | None]:
    """While the block runs, the learned regression's estimates that ``network``'s fine stage receives (``[batch,
    6]`` numpy, mm/deg about the grid centre), caught by a forward pre-hook on the fine stage in this thread only
    (the swapped-input estimate may run the same network in a worker thread). Yields the list they are appended to,
    one entry per fine-stage call; ``None`` where there is nothing to catch: no fine stage, the fine stage off, or
    a cascade (``steps > 1``: the fine stage runs once per step)."""
    fine = getattr(network, "fine_stage", None)
    if fine is None or not getattr(network, "fine_stage_enabled", True) or steps != 1:
        yield None
        return
    caught: list[np.ndarray] = []
    thread = threading.get_ident()

    def catch(_module: nn.Module, args: tuple[Any, ...]) -> None:
        if threading.get_ident() == thread and len(args) >= 3 and args[2].shape[0] == batch:
            caught.append(args[2].detach().double().cpu().numpy())

    handle = fine.register_forward_pre_hook(catch)
    try:
        yield caught
    finally:
        handle.remove()

