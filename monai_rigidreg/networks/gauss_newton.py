"""The weight-free fine stage: differentiable Gauss-Newton rigid alignment of two feature maps.

:class:`GaussNewtonStage` refines a start estimate (the learned regression's, see
:class:`~monai_rigidreg.networks.TwoStageRigidNet`) by coarse-to-fine inverse-compositional Lucas-Kanade steps on
fixed, contrast-robust feature maps (:func:`alignment_features`). It has no trainable weights. A regression alone
cannot reach sub-voxel accuracy cheaply (it has to learn the mm scale of every displacement from data); a
Gauss-Newton step computes the displacement from image gradients, so the learned part only has to bring the start
into the basin.

Conventions are those of :mod:`monai_rigidreg.core.geometry`: ``T`` maps fixed points to moving points (LPS mm), the
estimate is a ``[B, 4, 4]`` matrix, parameters are ``(tx, ty, tz, rx, ry, rz)`` mm / degrees about the grid
centre. The Jacobian combines the image gradient with the voxel displacement per parameter computed from
:func:`~monai_rigidreg.core.geometry.params_to_matrix` and the grid's index-to-physical matrix, so no convention
is derived a second time here (tests compare it with finite differences of
:func:`~monai_rigidreg.core.warp.warp_volume`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from monai_rigidreg.core.geometry import (
    Grid,
    matrix_to_params_torch,
    params_to_matrix_torch,
)
from monai_rigidreg.core.image_ops import erode, pyramid
from monai_rigidreg.core.warp import normalized_points, sample_normalized, warp_volume
from monai_rigidreg.networks.alignment_features import alignment_features
from monai_rigidreg.networks.gauss_newton_terms import (
    fixed_jacobian,
    parameter_flow,
    polynomial_basis,
    voxel_indices,
)

__all__ = [
    "GaussNewtonStage",
    "JACOBIANS",
    "alignment_features",
    "fixed_jacobian",
    "gauss_newton_align",
    "parameter_flow",
    "polynomial_basis",
]

JACOBIANS: tuple[str, ...] = ("fixed", "moving", "symmetric")
"""Where the Gauss-Newton steps take their image gradients from (see :func:`gauss_newton_align`)."""


def gauss_newton_align(
    moving: torch.Tensor,
    fixed: torch.Tensor,
    grid: Grid,
    init: torch.Tensor,
    iterations: int = 5,
    weight: torch.Tensor | None = None,
    moving_support: torch.Tensor | None = None,
    damping: float = 1e-3,
    max_step: tuple[float, float] = (10.0, 5.0),
    min_voxels: int = 100,
    robust_scale: float | None = None,
    return_residual: bool = False,
    bias_degree: int = -1,
    jacobian: str = "fixed",
    tolerance: Sequence[float] | None = None,
    secant: bool = False,
    candidates: torch.Tensor | None = None,
    reach_mm: float = 0.0,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Refine a fixed->moving rigid matrix so that ``moving(T(x)) ~ fixed(x)`` in least squares.

    Inverse compositional update: with ``J = d fixed(W_d(x))/dd`` (constant) and residual
    ``r = moving(T(x)) - fixed(x)``, ``d = (J^T w J + damping * diag(J^T w J))^-1 J^T w r`` and
    ``T <- T o W_d^-1``. Differentiable with respect to both feature maps and ``init``.

    Args:
        moving: ``[B, C, x, y, z]`` moving features on ``grid`` (the *unwarped* moving volume).
        fixed: ``[B, C, x, y, z]`` fixed features on ``grid``.
        grid: the network grid.
        init: ``[B, 4, 4]`` starting estimate (float64 preferred).
        iterations: number of Gauss-Newton steps.
        weight: optional ``[B, 1, x, y, z]`` voxel weights (e.g. a field-of-view mask); voxels that the warped
            moving volume does not cover are always excluded.
        moving_support: optional ``[B, 1, x, y, z]`` mask of where the moving volume has data (e.g. the CBCT
            field of view), in moving space; warped with the estimate and thresholded.
        damping: Levenberg-Marquardt damping relative to the diagonal.
        max_step: trust region of one step, ``(mm, degrees)``: a step whose largest translation or rotation
            component exceeds it is scaled down (an ill-conditioned system, e.g. a nearly empty overlap, would
            otherwise jump by metres).
        min_voxels: cases whose overlap has fewer weighted voxels than this keep their estimate (no step).
        return_residual: also return the final weighted mean squared residual (without bias terms) and the
            overlap per case.
        robust_scale: if set, Geman-McClure weights ``s^2 / (s^2 + r^2)`` on the per-voxel squared residual
            (downweights CBCT truncation and artefacts).
        bias_degree: if >= 0, a smooth intensity bias per channel, a polynomial of this degree in the grid
            coordinates (:func:`polynomial_basis`), is estimated jointly with the pose at every step and discarded
            (linear appearance variation in the sense of Baker and Matthews): the CBCT's cupping and scatter
            shading no longer pull the pose. -1: none.
        jacobian: where the image gradients come from: ``"fixed"`` (inverse compositional, computed once),
            ``"moving"`` (the warped moving features at every step, forward compositional) or ``"symmetric"``
            (their mean, as in efficient second-order minimisation). With images of equal appearance all three
            converge to the same pose; where the CBCT's features differ from the CT's, their fixed points differ
            (``benchmarks/ablation/bench_gauss_newton_variants.py``).
        tolerance: ``(mm, degrees)``: stop before ``iterations`` once the step of every case is below both (its
            largest translation and rotation component); ``None``: always ``iterations`` steps (training keeps the
            number of steps fixed).
        secant: scale each step by ``1 / a``, where ``a`` (per case, in [0.25, 1]) is the secant estimate of how
            much of a step the next residual actually takes back: ``a = (d_k - d_{k+1}) . s_k / |s_k|^2`` with ``d``
            the Gauss-Newton steps and ``s`` the applied ones. Where the CBCT's features have less contrast than
            the CT's (blur, noise), ``J^T J`` from the CT over-estimates the curvature and every step covers only a
            fraction ``a`` of the remaining error: the iteration contracts linearly by
            ``1 - a`` per step. The scaled steps keep the same fixed point and reach it in fewer steps.
        candidates: optional ``[1, 1, x, y, z]`` boolean mask (one case, ``jacobian="fixed"``) holding every voxel
            that can carry weight while the estimate moves every point of the grid less than ``reach_mm`` from
            where ``init`` puts it: where ``weight`` is positive and the warped ``moving_support`` can cover
            (:func:`~monai_rigidreg.registration.last_level.support_reach`). The steps are computed over these voxels
            only (:func:`~monai_rigidreg.core.warp.warp_points`), the same sums as over the whole grid, the other
            voxels' weights being zero; once the estimate has moved a corner of the grid ``reach_mm`` or more from
            ``init``'s, the remaining steps use the whole grid. The last level's grid covers the CBCT's box, about
            a third of it outside its cylindrical field of view (``benchmarks/speed/bench_network_paths.py``).
        reach_mm: see ``candidates``.

    Returns:
        ``[B, 4, 4]`` float64 refined matrices; with ``return_residual`` also two ``[B]`` tensors at the returned
        estimate: the weighted mean squared residual (lower is a better fit) and the overlap, the fraction of the
        grid that the warped ``moving_support`` covers.
    """
    if moving.shape != fixed.shape or moving.ndim != 5:
        raise ValueError(f"moving {tuple(moving.shape)} and fixed {tuple(fixed.shape)} must be equal [B,C,x,y,z]")
    # the Jacobian is treated as a constant in backpropagation (as the inverse-compositional scheme treats it in
    # the forward pass); gradients reach both feature maps through the residual
    if jacobian not in JACOBIANS:
        raise ValueError(f"jacobian must be 'fixed', 'moving' or 'symmetric', got {jacobian!r}")
    subset = None if candidates is None else _Subset(candidates, grid, init, reach_mm, fixed, weight, jacobian,
                                                     robust_scale)
    # (products in the feature dtype, the 6x6 solve in float64)
    jac_fixed = None if jacobian == "moving" or subset is not None else fixed_jacobian(fixed.detach(), grid).flatten(2)
    n_ch, n_vox = moving.shape[1], moving[0, 0].numel()
    basis = None if bias_degree < 0 else polynomial_basis(grid, bias_degree, moving.dtype, moving.device).flatten(1)
    center = grid.center()
    total = init.to(torch.float64)
    support = torch.ones_like(moving[:, :1]) if moving_support is None else moving_support.to(moving.dtype)
    # the support rides along as one more channel: one sampling grid and one grid_sample per step
    stacked = torch.cat([moving, support], 1)
    gain = torch.ones(moving.shape[0], dtype=torch.float64, device=moving.device)
    raw_prev = applied_prev = None
    for _ in range(iterations):
        if subset is not None and not subset.within_reach(total):
            # the estimate left the reach the candidates were chosen for: the whole grid from here
            subset = None
            jac_fixed = fixed_jacobian(fixed.detach(), grid).flatten(2)
        if subset is not None:
            both = sample_normalized(stacked, total, subset.normalized, grid, grid)  # [1, C + 1, K]
            warped, cover = both[:, :n_ch], both[:, n_ch:]
            w = (cover > 0.999).to(moving.dtype)
            if subset.weight is not None:
                w = w * subset.weight
            r = warped - subset.fixed  # [1, C, K]
            d = _solve_step(subset.jacobian, w, r, None if basis is None else basis[:, subset.index], n_ch,
                            subset.count, damping)
        else:
            d, w = _dense_step(stacked, total, grid, fixed, weight, jac_fixed, jacobian, robust_scale, basis, n_ch,
                               n_vox, damping)
        if secant:
            raw = d.detach()
            if applied_prev is not None:
                ss = (applied_prev * applied_prev).sum(1)
                est = ((raw_prev - raw) * applied_prev).sum(1) / ss.clamp_min(1e-12)
                # a step too small to measure the gain (below 0.01 mm / degrees) keeps the previous estimate
                gain = torch.where(ss > 1e-4, est.clamp(0.25, 1.0), gain)
            d = d / gain[:, None]
            raw_prev = raw
        scale = torch.maximum(d[:, :3].abs().amax(1) / max_step[0], d[:, 3:].abs().amax(1) / max_step[1])
        enough = w.flatten(1).sum(1).to(torch.float64) >= min_voxels
        d = torch.where(enough[:, None], d / scale.clamp_min(1.0)[:, None], torch.zeros_like(d))
        if secant:
            applied_prev = d.detach()
        step = params_to_matrix_torch(d, center)
        total = total @ torch.linalg.inv(step)
        if tolerance is not None and bool((d[:, :3].abs().amax(1) < tolerance[0]).all()) and bool(
                (d[:, 3:].abs().amax(1) < tolerance[1]).all()):
            break
    if not return_residual:
        return total
    both = warp_volume(stacked, total, grid, grid)
    warped, covered = both[:, :n_ch], (both[:, n_ch:] > 0.999).to(moving.dtype)
    overlap = covered.flatten(1).mean(1)
    w = covered if weight is None else covered * weight
    res = (w * (warped - fixed) ** 2).sum(dim=(1, 2, 3, 4)) / (w.sum(dim=(1, 2, 3, 4)) * moving.shape[1] + 1e-6)
    return total, res, overlap


def _solve_step(jf: torch.Tensor, w: torch.Tensor, r: torch.Tensor, basis: torch.Tensor | None, n_ch: int,
                n_vox: int, damping: float) -> torch.Tensor:
    """The Levenberg-Marquardt step ``[B, 6]`` from the Jacobian ``jf`` ``[B, 6, C*N]``, the voxel weights ``w``
    ``[B, 1, ...]`` and residuals ``r`` ``[B, C, ...]`` of ``N`` voxels (the whole grid or the candidates), with the
    bias terms of ``basis`` ``[k, N]`` solved for and dropped. Products in the feature dtype, the solve in
    float64."""
    wj = jf * w.expand_as(r).flatten(1).unsqueeze(1)  # [B, 6, C*N]
    h = (wj @ jf.transpose(1, 2)).to(torch.float64)  # [B, 6, 6]
    g = (wj @ r.flatten(1).unsqueeze(-1)).to(torch.float64)  # [B, 6, 1]
    if basis is not None:
        h, g = _with_bias_terms(h, g, wj, w, r, basis, n_ch, n_vox)
    diag = torch.diagonal(h, dim1=1, dim2=2)
    h = h + torch.diag_embed(damping * diag + 1e-9)
    return torch.linalg.solve(h, g).squeeze(-1)[:, :6]


def _dense_step(stacked: torch.Tensor, total: torch.Tensor, grid: Grid, fixed: torch.Tensor,
                weight: torch.Tensor | None, jac_fixed: torch.Tensor | None, jacobian: str,
                robust_scale: float | None, basis: torch.Tensor | None, n_ch: int, n_vox: int,
                damping: float) -> tuple[torch.Tensor, torch.Tensor]:
    """One step of :func:`gauss_newton_align` over the whole grid: ``stacked`` ``[B, C + 1, x, y, z]`` (the moving
    features and their support), the estimate ``total`` ``[B, 4, 4]`` -> the step ``[B, 6]`` and the voxel weights
    ``[B, 1, x, y, z]`` it was computed with."""
    both = warp_volume(stacked, total, grid, grid)
    warped, cover = both[:, :n_ch], both[:, n_ch:]
    w = (cover > 0.999).to(stacked.dtype)
    if weight is not None:
        w = w * weight
    r = warped - fixed  # [B, C, ...]
    jf = jac_fixed
    if jacobian != "fixed":  # the step is still composed as T o W_d^-1 (W_d^-1 = W_-d to first order)
        jac_moving = fixed_jacobian(warped.detach(), grid).flatten(2)
        jf = jac_moving if jac_fixed is None else 0.5 * (jac_fixed + jac_moving)
    if robust_scale is not None:
        sq = (r.detach() ** 2).sum(1, keepdim=True)
        w = w * (robust_scale**2 / (robust_scale**2 + sq))
    return _solve_step(jf, w, r, basis, n_ch, n_vox, damping), w


class _Subset:
    """The candidate voxels of :func:`gauss_newton_align` (one case) and what a step needs at them: ``index`` ``[K]``
    flat voxel indices, ``normalized`` ``[K, 3]`` their sampling coordinates, ``fixed`` ``[1, C, K]``, ``jacobian``
    ``[1, 6, C*K]`` (:func:`fixed_jacobian` there), ``weight`` ``[1, 1, K]`` (or ``None``); :meth:`within_reach`
    tells whether an estimate moves every grid point less than ``reach_mm`` from where ``init`` puts it."""

    def __init__(self, candidates: torch.Tensor, grid: Grid, init: torch.Tensor, reach_mm: float,
                 fixed: torch.Tensor, weight: torch.Tensor | None, jacobian: str, robust_scale: float | None) -> None:
        if fixed.shape[0] != 1 or init.shape[0] != 1:
            raise ValueError(f"candidates are for one case, got a batch of {fixed.shape[0]}")
        if tuple(candidates.shape) != (1, 1, *fixed.shape[2:]):
            raise ValueError(f"candidates must be [1, 1, x, y, z] like the features, got {tuple(candidates.shape)}")
        if jacobian != "fixed":
            raise ValueError("candidates need jacobian='fixed' (the moving Jacobian is computed over the whole grid)")
        if robust_scale is not None:
            raise ValueError("candidates are not combined with robust_scale")
        if reach_mm < 0:
            raise ValueError(f"reach_mm must be >= 0, got {reach_mm}")
        n_ch, n_vox = fixed.shape[1], fixed[0, 0].numel()
        self.index = candidates.to(fixed.device).reshape(-1).nonzero().squeeze(1)
        self.count = int(self.index.numel())
        points = torch.stack(voxel_indices(self.index, grid.size), 1).to(fixed.dtype)
        self.normalized = normalized_points(points, grid, fixed.dtype)  # sampled under every step's estimate
        self.fixed = fixed.reshape(1, n_ch, n_vox)[:, :, self.index]
        self.jacobian = fixed_jacobian(fixed.detach(), grid, self.index, points).reshape(1, 6, n_ch * self.count)
        self.weight = None if weight is None else weight.reshape(1, 1, n_vox)[:, :, self.index]
        corners = np.concatenate([grid.corners(), np.ones((8, 1))], 1)  # [8, 4] homogeneous LPS mm
        self._corners = torch.as_tensor(corners, dtype=torch.float64, device=init.device)
        self._start = self._corners @ init[0].detach().to(torch.float64).T
        self._reach = float(reach_mm)

    def within_reach(self, total: torch.Tensor) -> bool:
        """Whether ``total`` ``[1, 4, 4]`` moves every grid point less than ``reach_mm`` from ``init``'s image of it
        (the displacement between two affine maps is largest at a corner of the grid's box)."""
        moved = self._corners @ total[0].detach().to(torch.float64).T - self._start
        return bool(moved[:, :3].norm(dim=1).amax() < self._reach)


def _with_bias_terms(h: torch.Tensor, g: torch.Tensor, wj: torch.Tensor, w: torch.Tensor, r: torch.Tensor,
                     basis: torch.Tensor, n_ch: int, n_vox: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Extend the pose normal equations ``h [B, 6, 6]``, ``g [B, 6, 1]`` by ``k`` bias coefficients per channel.

    The bias columns of the Jacobian are the basis functions ``[k, N]`` on one channel each, so every block is a
    small product over ``N`` voxels (never a ``[6 + C k, C N]`` matrix): pose-bias ``(w J_c) A^T``, bias-bias
    ``(w A) A^T`` (the same for every channel, the weights being shared) and ``(w A) r_c``.
    """
    b, k = h.shape[0], basis.shape[0]
    wa = basis.unsqueeze(0) * w.flatten(1).unsqueeze(1)  # [B, k, N]
    h_aa = (wa @ basis.t()).to(torch.float64)  # [B, k, k]
    size = 6 + n_ch * k
    big_h = torch.zeros(b, size, size, dtype=torch.float64, device=h.device)
    big_g = torch.zeros(b, size, 1, dtype=torch.float64, device=h.device)
    big_h[:, :6, :6] = h
    big_g[:, :6] = g
    for c in range(n_ch):
        sl = slice(6 + c * k, 6 + (c + 1) * k)
        h_pa = (wj[:, :, c * n_vox:(c + 1) * n_vox] @ basis.t()).to(torch.float64)  # [B, 6, k]
        big_h[:, :6, sl] = h_pa
        big_h[:, sl, :6] = h_pa.transpose(1, 2)
        big_h[:, sl, sl] = h_aa
        big_g[:, sl] = (wa @ r[:, c].reshape(b, n_vox, 1)).to(torch.float64)
    return big_h, big_g


class GaussNewtonStage(nn.Module):
    """The fine stage: coarse-to-fine Gauss-Newton alignment of contrast-robust features, from two starts.

    ``forward(moving, fixed, start)`` refines ``start`` (the regression's estimate): the feature maps of both
    volumes (:func:`alignment_features`: intensity and local contrast) are aligned on an average-pooled pyramid of
    the network grid (``levels``, coarse to fine, ``iterations`` steps each) by :func:`gauss_newton_align`,
    restricted to the moving image's support (voxels above ``support_threshold``, eroded by
    ``support_erosion_mm``: the CBCT field of view minus air), so a truncated CBCT is not pulled towards the CT's
    anatomy outside its field of view. The first level runs from two starts, ``start`` and the identity; per case
    the better fit (lower residual, keeping at least half the identity's overlap) goes on, so the regression can
    only widen the capture range, never spoil a case the Gauss-Newton steps capture on their own.

    No trainable weights. Differentiable with respect to the images; the start is detached (measured: letting the
    loss on the final estimate reach the regression through these steps made CPU training diverge within two
    epochs, the regression saturating at its tanh bounds), so the regression learns from its own supervised term.
    Fixed rather than learned features: learned channels trained through the (detached-Jacobian) steps degraded
    the validation TRE from 2.6 mm to 15 mm within one CPU epoch, while these reach about 0.4 mm
    (``benchmarks/ablation/bench_alignment_features.py``).

    Args:
        grid_spacing: network-grid spacing in mm (the bundle's ``network_spacing``; the steps work in physical
            units, so this must be the spacing the volumes are on).
        iterations: Gauss-Newton steps per pyramid level (empty or all zero: the start is returned).
        levels: pooling factor of each level, coarse to fine (same length as ``iterations``).
        highpass_sigma_mm, highpass_weight, gradient_weight, contrast_norm_sigma_mm, intensity_weight: the feature
            maps, see :func:`alignment_features` (highpass and gradient weights 0: align intensities alone). The last
            level (:mod:`~monai_rigidreg.registration.last_level`) uses the same settings.
        support_erosion_mm: erosion of the moving support before it weights the residuals (mm, at least a voxel).
            More than a voxel: near the CBCT field-of-view edge the local contrast of the CT (which has data
            beyond it) and of the CBCT differ (``bench_alignment_features.py``: 8 mm takes the validation TRE
            from 0.63 mm with one voxel to 0.42 mm).
        bias_degree: degree of the smooth intensity bias per feature channel estimated jointly with the pose and
            discarded (-1: none; see :func:`gauss_newton_align`). Used from the second level on: on the coarsest
            level, where large motions are captured, a smooth field can stand in for a shift of broad structures
            (``benchmarks/accuracy/bench_capture_range.py`` with the terms on every level captured fewer large motions).
        jacobian: ``"fixed"`` (inverse compositional, the default), ``"moving"`` or ``"symmetric"``; one for all
            levels or one per level.
        robust_scale: optional Geman-McClure scale of the residuals (None: plain least squares).
        support_threshold: normalized intensity above which a moving voxel counts as data.
        tolerance: ``(mm, degrees)``: at inference (gradients off) a level stops once its steps fall below both
            (:func:`gauss_newton_align`); with gradients on, every level takes its ``iterations`` steps. ``None``:
            always all steps. The bundle uses ``(0.03, 0.03)`` (``benchmarks/speed/bench_bundle_ab.py`` measures the
            time saved and the change of the estimates against another setting).
        secant: at inference (gradients off), secant-scaled steps (:func:`gauss_newton_align`); training keeps
            plain steps.

    Shapes:
        ``forward``: ``moving, fixed`` ``[B, C, x, y, z]`` on the network grid (intensities ~[0, 1]), ``start``
        ``[B, 6]`` (mm, degrees about the grid centre) -> ``(params [B, 6] in the dtype of start,
        from_start [B] bool: True where the refined ``start`` beat the identity start)``.
    """

    def __init__(
        self,
        grid_spacing: Sequence[float],
        iterations: Sequence[int] = (12, 8, 4),
        levels: Sequence[int] = (4, 2, 1),
        highpass_sigma_mm: float = 16.0,
        highpass_weight: float = 3.0,
        gradient_weight: float = 0.0,
        support_erosion_mm: float = 8.0,
        bias_degree: int = -1,
        jacobian: str | Sequence[str] = "fixed",
        robust_scale: float | None = None,
        support_threshold: float = 1e-3,
        tolerance: Sequence[float] | None = None,
        secant: bool = False,
        contrast_norm_sigma_mm: float | None = None,
        intensity_weight: float = 1.0,
    ) -> None:
        super().__init__()
        if contrast_norm_sigma_mm is not None and not float(contrast_norm_sigma_mm) > 0:
            raise ValueError(f"contrast_norm_sigma_mm must be > 0 mm (or None), got {contrast_norm_sigma_mm}")
        if not float(intensity_weight) >= 0:
            raise ValueError(f"intensity_weight must be >= 0, got {intensity_weight}")
        self.contrast_norm_sigma_mm = None if contrast_norm_sigma_mm is None else float(contrast_norm_sigma_mm)
        self.intensity_weight = float(intensity_weight)
        self.secant = bool(secant)
        if tolerance is not None and (len(tolerance) != 2 or min(float(v) for v in tolerance) <= 0):
            raise ValueError(f"tolerance must be (mm, degrees) > 0, got {tolerance}")
        self.tolerance = None if tolerance is None else (float(tolerance[0]), float(tolerance[1]))
        self.iterations = tuple(int(i) for i in iterations)
        self.levels = tuple(int(v) for v in levels)
        if len(self.iterations) != len(self.levels):
            raise ValueError(f"iterations {self.iterations} and levels {self.levels} differ in length")
        self.jacobian = jacobian if isinstance(jacobian, str) else tuple(jacobian)
        jacobians = [self.jacobian] if isinstance(self.jacobian, str) else list(self.jacobian)
        if not isinstance(self.jacobian, str) and len(self.jacobian) != len(self.levels):
            raise ValueError(f"jacobian {self.jacobian} needs one entry per level {self.levels}")
        if any(j not in JACOBIANS for j in jacobians):
            raise ValueError(f"jacobian must be one of {JACOBIANS} (or one per level), got {self.jacobian!r}")
        self.grid_spacing = tuple(float(v) for v in grid_spacing)
        if len(self.grid_spacing) != 3 or min(self.grid_spacing) <= 0:
            raise ValueError(f"grid_spacing must be three positive mm values, got {grid_spacing}")
        self.highpass_sigma_mm = float(highpass_sigma_mm)
        self.highpass_weight = float(highpass_weight)
        self.gradient_weight = float(gradient_weight)
        self.support_erosion_mm = float(support_erosion_mm)
        self.bias_degree = int(bias_degree)
        self.robust_scale = robust_scale
        self.support_threshold = float(support_threshold)

    def features(self, volumes: torch.Tensor) -> torch.Tensor:
        """The maps the stage aligns, ``[N, C, x, y, z]`` -> ``[N, C * k, x, y, z]`` (:func:`alignment_features`)."""
        return alignment_features(volumes, self.grid_spacing, self.support_threshold, self.highpass_sigma_mm,
                                  self.highpass_weight, self.gradient_weight, self.contrast_norm_sigma_mm,
                                  self.intensity_weight)

    def forward(self, moving: torch.Tensor, fixed: torch.Tensor, start: torch.Tensor,
                fixed_weight: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``fixed_weight``: optional ``[B, 1, x, y, z]`` voxel weights in [0, 1] on the fixed grid (the match
        region); the residuals of each level are weighted by it (average-pooled to the level)."""
        if moving.shape != fixed.shape or moving.ndim != 5:
            raise ValueError(f"moving {tuple(moving.shape)} and fixed {tuple(fixed.shape)} must be equal [B,C,x,y,z]")
        b = moving.shape[0]
        feat = self.features(torch.cat([moving, fixed], dim=0))
        feat_m, feat_f = feat[:b], feat[b:]
        support = (moving > self.support_threshold).to(moving.dtype)
        support = erode(support, [max(1, round(self.support_erosion_mm / s)) for s in self.grid_spacing])
        grid = Grid.centered(tuple(moving.shape[2:]), self.grid_spacing, (0.0, 0.0, 0.0))
        starts = torch.cat([params_to_matrix_torch(start.detach().to(torch.float64), grid.center()),
                            torch.eye(4, dtype=torch.float64, device=start.device).expand(b, 4, 4)], 0)
        total = starts[:b]
        from_start = torch.ones(b, dtype=torch.bool, device=start.device)
        first = True
        tol = None if torch.is_grad_enabled() else self.tolerance
        sec = self.secant and not torch.is_grad_enabled()
        jacobians = [self.jacobian] * len(self.levels) if isinstance(self.jacobian, str) else list(self.jacobian)
        for level, iters, jacobian in zip(self.levels, self.iterations, jacobians):
            if iters <= 0:
                continue
            fm, g = pyramid(feat_m, grid, level)
            ff, _ = pyramid(feat_f, grid, level)
            sup = support if level == 1 else (F.avg_pool3d(support, level) > 0.999).to(support.dtype)
            wgt = None
            if fixed_weight is not None:
                wgt = fixed_weight.to(fm.dtype) if level == 1 else F.avg_pool3d(fixed_weight.to(fm.dtype), level)
            if first:
                both, res, cover = gauss_newton_align(
                    fm.repeat(2, 1, 1, 1, 1), ff.repeat(2, 1, 1, 1, 1), g, starts, iterations=iters,
                    weight=None if wgt is None else wgt.repeat(2, 1, 1, 1, 1),
                    moving_support=sup.repeat(2, 1, 1, 1, 1), robust_scale=self.robust_scale, return_residual=True,
                    jacobian=jacobian, tolerance=tol, secant=sec)
                # a start that leaves little overlap can show a low mean residual: it must keep at least half the
                # overlap of the identity start to be preferred
                from_start = (res[:b] <= res[b:]) & (cover[:b] >= 0.5 * cover[b:])
                total = torch.where(from_start.view(b, 1, 1), both[:b], both[b:])
                first = False
                continue
            total = gauss_newton_align(fm, ff, g, total, iterations=iters, weight=wgt, moving_support=sup,
                                       robust_scale=self.robust_scale, bias_degree=self.bias_degree,
                                       jacobian=jacobian, tolerance=tol, secant=sec)
        return matrix_to_params_torch(total, grid.center()).to(start.dtype), from_start

    def extra_repr(self) -> str:
        return (f"grid_spacing={self.grid_spacing}, iterations={self.iterations}, levels={self.levels}, "
                f"bias_degree={self.bias_degree}, jacobian={self.jacobian!r}, tolerance={self.tolerance}, "
                f"secant={self.secant}")
