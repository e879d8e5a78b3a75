"""Composite loss of the reference paper (SSIM, NCC, MI, grid gradient, L2) plus an optional supervised TRE term.

``L = w_ssim (1 - SSIM) + w_ncc (-NCC) + w_mi (-MI) + w_grad L_grad + w_reg ||p||^2 + w_sup TRE``

Image terms compare the warped moving volume (CBCT resampled by the predicted transform onto the network grid)
with the fixed volume (Sim-CT), both normalized to about [0, 1], optionally restricted to the CBCT field-of-view
mask. MONAI's :class:`~monai.losses.SSIMLoss` and :class:`~monai.losses.GlobalMutualInformationLoss` do not take
masks, so masked versions are written here (they reduce to MONAI's value for an all-ones mask; tested).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch
from monai.losses import GlobalMutualInformationLoss, SSIMLoss
from torch import nn

from monai_rigidreg.core.geometry import Grid, grid_points, params_to_matrix_torch, point_distances_torch
from monai_rigidreg.core.image_ops import broadcast_mask, gaussian_kernel_1d, masked_ncc, separable_filter

__all__ = [
    "RigidRegistrationLoss",
    "LossTerms",
    "masked_ncc",
    "masked_ssim",
    "masked_mutual_information",
    "grid_gradient_penalty",
    "image_gradient_difference",
    "supervised_point_distance",
]


class LossTerms(NamedTuple):
    """Output of :class:`RigidRegistrationLoss`: the weighted total and the *unweighted* terms (0-d tensors).

    ``ssim`` is ``1 - SSIM``, ``ncc`` is ``-NCC``, ``mi`` is ``-MI`` (nats), ``grad`` the grid-gradient term,
    ``reg`` ``||params||^2`` (mm^2 + deg^2), ``sup`` the supervised point distance (mm). Terms whose weight is 0 are
    not computed and read 0.
    """

    total: torch.Tensor
    ssim: torch.Tensor
    ncc: torch.Tensor
    mi: torch.Tensor
    grad: torch.Tensor
    reg: torch.Tensor
    sup: torch.Tensor

    def as_dict(self) -> dict[str, float]:
        """Python floats of every field, for logging."""
        return {k: float(v.detach()) for k, v in self._asdict().items()}


def masked_ssim(
    x: torch.Tensor,
    y: torch.Tensor,
    mask: torch.Tensor,
    win_size: int = 7,
    sigma: float = 1.5,
    data_range: float = 1.0,
    k1: float = 0.01,
    k2: float = 0.03,
) -> torch.Tensor:
    """SSIM (paper Eq. 2) restricted to a mask, by normalized convolution.

    Local Gaussian-weighted means/variances/covariance use only voxels inside the mask (the Gaussian weights
    are renormalised by the blurred mask), and the SSIM map is averaged over window centres inside the mask.
    Voxels outside the mask therefore never contribute. With an all-ones mask this equals
    :class:`monai.losses.SSIMLoss`'s SSIM (``valid`` windows, Gaussian kernel ``win_size``/``sigma``).

    Args:
        x, y: ``[B, C, x, y, z]`` intensities in ``[0, data_range]``.
        mask: ``[B, 1, x, y, z]``, non-zero inside the field of view.

    Returns:
        ``[B]`` mean SSIM (dimensionless, 1 for identical images).
    """
    dt = torch.promote_types(x.dtype, torch.float32)
    x, y = x.to(dt), y.to(dt)
    m = broadcast_mask(mask, x)
    assert m is not None
    g = gaussian_kernel_1d(sigma, approx="sampled", normalize=True, size=win_size, dtype=dt, device=x.device)

    def blur(img: torch.Tensor) -> torch.Tensor:  # ``valid`` windows, like MONAI's SSIM metric
        return separable_filter(img, [g, g, g], padding="valid")

    wsum = blur(m)
    safe = wsum.clamp_min(1e-6)
    mu_x = blur(m * x) / safe
    mu_y = blur(m * y) / safe
    s_xx = blur(m * x * x) / safe - mu_x * mu_x
    s_yy = blur(m * y * y) / safe - mu_y * mu_y
    s_xy = blur(m * x * y) / safe - mu_x * mu_y
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * s_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (s_xx + s_yy + c2))
    h = win_size // 2
    sl = [slice(h, s - (win_size - 1 - h)) for s in m.shape[2:]]
    centre = m[:, :, sl[0], sl[1], sl[2]] * (wsum > 1e-6).to(dt)
    n = centre.flatten(1).sum(1)
    val = (ssim_map * centre).flatten(1).sum(1) / n.clamp_min(1.0)
    return torch.where(n > 0, val, torch.ones_like(val))


def masked_mutual_information(
    x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor, parzen: GlobalMutualInformationLoss
) -> torch.Tensor:
    """Mutual information (nats, paper Eq. 4) over the voxels of ``mask``, Gaussian Parzen windows.

    Uses MONAI's ``parzen_windowing_gaussian`` (bins on [0, 1]) for the per-voxel bin weights and forms the
    mask-weighted joint histogram here (MONAI's loss has no mask argument). Call in float32.

    Returns:
        ``[B]`` MI (>= 0; larger is more similar).
    """
    m = broadcast_mask(mask, x)
    assert m is not None
    wx, _ = parzen.parzen_windowing_gaussian(x)  # [B, N, bins]
    wy, _ = parzen.parzen_windowing_gaussian(y)
    mv = m.reshape(m.shape[0], -1, 1)
    n = mv.sum(1, keepdim=True).clamp_min(1.0)  # [B, 1, 1]
    px = (wx * mv).sum(1, keepdim=True) / n  # [B, 1, bins]
    py = (wy * mv).sum(1, keepdim=True) / n
    pxy = torch.bmm((wx * mv).transpose(1, 2), wy) / n  # [B, bins, bins]
    pxpy = torch.bmm(px.transpose(1, 2), py)
    nr, dr = parzen.smooth_nr, parzen.smooth_dr
    return torch.sum(pxy * torch.log((pxy + nr) / (pxpy + dr)), dim=(1, 2))


def grid_gradient_penalty(matrix: torch.Tensor) -> torch.Tensor:
    """The paper's gradient regularisation of the sampling grid, for a rigid grid.

    The sampling grid maps fixed point ``x`` to ``T(x)``; its displacement field ``u(x) = T(x) - x`` has the
    spatial Jacobian ``du/dx = R - I`` everywhere (the same value any finite-difference scheme on any grid gives,
    since ``u`` is affine). The term is the mean squared Frobenius norm of that gradient,
    ``||R - I||_F^2 = 4 (1 - cos(theta))`` (~ ``theta^2`` for a total rotation angle ``theta`` in radians):
    dimensionless ((mm/mm)^2). For a rigid grid it is a smooth rotation-magnitude prior; translations do not
    enter it.

    Args:
        matrix: ``[B, 4, 4]`` fixed->moving matrices.

    Returns:
        ``[B]`` penalty.
    """
    eye = torch.eye(3, dtype=matrix.dtype, device=matrix.device)
    return ((matrix[:, :3, :3] - eye) ** 2).sum(dim=(1, 2))


def image_gradient_difference(
    x: torch.Tensor, y: torch.Tensor, spacing: Any = (1.0, 1.0, 1.0), mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean squared difference of the spatial gradients of ``x`` and ``y`` (forward differences / spacing).

    ``mean |grad x - grad y|^2`` over voxels whose forward-difference stencil lies inside ``mask``; unit
    (intensity / mm)^2. An edge-alignment alternative to :func:`grid_gradient_penalty` (``grad_term="image"``).

    Returns:
        ``[B]``.
    """
    dt = torch.promote_types(x.dtype, torch.float32)
    d = x.to(dt) - y.to(dt)
    m = broadcast_mask(mask, d)
    sp = [float(s) for s in np.broadcast_to(np.asarray(spacing, dtype=np.float64), (3,))]
    total = torch.zeros(d.shape[0], dtype=dt, device=d.device)
    count = torch.zeros_like(total)
    for ax in range(3):
        dim = ax + 2
        n = d.shape[dim]
        if n < 2:
            continue
        g = (d.narrow(dim, 1, n - 1) - d.narrow(dim, 0, n - 1)) / sp[ax]
        w = torch.ones_like(g) if m is None else m.narrow(dim, 1, n - 1) * m.narrow(dim, 0, n - 1)
        total = total + (w * g * g).flatten(1).sum(1)
        count = count + w.flatten(1).sum(1)
    return total / count.clamp_min(1.0)


def supervised_point_distance(
    params_pred: torch.Tensor,
    params_true: torch.Tensor,
    points: torch.Tensor,
    center: Any,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean distance (mm) between points mapped by the predicted and by the true transform (a differentiable TRE,
    :func:`~monai_rigidreg.core.geometry.point_distances_torch` averaged with optional weights).

    Args:
        params_pred, params_true: ``[B, 6]`` (mm, degrees) about ``center``.
        points: ``[N, 3]`` LPS points (mm).
        center: ``[3]`` or ``[B, 3]`` rotation centre (mm).
        weights: optional ``[B, N]`` non-negative point weights (e.g. a field-of-view mask at the points); a batch
            item whose weights sum to 0 falls back to all points.

    Returns:
        ``[B]`` mean ``|T_pred(x) - T_true(x)|`` in mm; exactly 0 (with zero gradient) when the transforms agree.
    """
    dist = point_distances_torch(params_pred, params_true, points, center)  # [B, N]
    if weights is None:
        return dist.mean(1)
    w = weights.to(dist.dtype)
    ws = w.sum(1)
    return torch.where(ws > 0, (w * dist).sum(1) / ws.clamp_min(1e-12), dist.mean(1))


class RigidRegistrationLoss(nn.Module):
    """Composite rigid-registration loss of the reference paper (Eq. 1) plus an optional supervised term.

    ``total = w_ssim (1 - SSIM) + w_ncc (-NCC) + w_mi (-MI) + w_grad L_grad + w_reg ||p||^2 + w_sup TRE``,
    each term averaged over the batch.

    * SSIM: Gaussian window ``ssim_win_size``/``ssim_sigma`` voxels, data range 1 (MONAI ``SSIMLoss`` when no
      mask is given; :func:`masked_ssim` otherwise).
    * NCC: global (Pearson) correlation, paper Eq. 3 (:func:`masked_ncc`).
    * MI: Gaussian-Parzen mutual information with ``mi_bins`` bins on [0, 1] (MONAI
      ``GlobalMutualInformationLoss`` / :func:`masked_mutual_information`), always in float32 with autocast off.
    * ``L_grad``: ``grad_term="grid"`` (default): :func:`grid_gradient_penalty`, squared spatial gradient of the
      rigid sampling grid's displacement field, dimensionless; ``grad_term="image"``:
      :func:`image_gradient_difference` of warped and fixed, (intensity/mm)^2 (needs ``grid`` for the spacing).
    * ``reg``: ``||params||^2`` summed over the six parameters, mm^2 + deg^2 (weak: default weight 1e-4).
    * ``sup``: :func:`supervised_point_distance` in mm between ``params_pred`` and ``params_true`` on every
      ``sup_step``-th voxel of ``grid`` (only those inside ``mask`` when a mask is given).

    Image intensities are clamped to [0, 1] (the range SSIM's ``data_range`` and MI's bins assume; the network
    grid preprocessing maps HU -1000..2000 there). Every image term is restricted to ``mask`` (``[B, 1, x, y, z]``,
    the CBCT field of view) when one is given. Terms with weight 0 are skipped and reported as 0.

    Returns a :class:`LossTerms` named tuple. With MONAI's ``SupervisedTrainer`` (which expects a scalar from
    ``loss_function``) use the ``total`` field and log the rest, e.g. a custom ``iteration_update`` that warps
    the moving image with :class:`~monai_rigidreg.networks.RigidTransformer` and calls
    ``terms = loss(warped, fixed, params_pred, params_true, mask, grid)``, ``terms.total.backward()``, and
    returns ``terms.as_dict()`` in the engine output for the handlers.

    Args:
        w_ssim, w_ncc, w_mi, w_grad, w_reg, w_sup: term weights (paper: 1.0, 0.1, 0.1, 0.1; weak L2; sup off).
        mi_bins: histogram bins of MI.
        mi_sigma_ratio: Parzen window width as a fraction of the bin spacing (MONAI's ``sigma_ratio``).
        ssim_win_size, ssim_sigma: SSIM Gaussian window (voxels).
        grad_term: ``"grid"`` or ``"image"`` (see above).
        sup_step: voxel stride of the supervised point grid.
    """

    def __init__(
        self,
        w_ssim: float = 1.0,
        w_ncc: float = 0.1,
        w_mi: float = 0.1,
        w_grad: float = 0.1,
        w_reg: float = 1e-4,
        w_sup: float = 0.0,
        mi_bins: int = 32,
        mi_sigma_ratio: float = 0.5,
        ssim_win_size: int = 7,
        ssim_sigma: float = 1.5,
        grad_term: str = "grid",
        sup_step: int = 4,
    ) -> None:
        super().__init__()
        if grad_term not in ("grid", "image"):
            raise ValueError(f"grad_term must be 'grid' or 'image', got {grad_term!r}")
        self.w_ssim, self.w_ncc, self.w_mi = float(w_ssim), float(w_ncc), float(w_mi)
        self.w_grad, self.w_reg, self.w_sup = float(w_grad), float(w_reg), float(w_sup)
        self.grad_term = grad_term
        self.sup_step = int(sup_step)
        self.ssim_win_size, self.ssim_sigma = int(ssim_win_size), float(ssim_sigma)
        self.ssim_loss = SSIMLoss(spatial_dims=3, data_range=1.0, win_size=self.ssim_win_size, kernel_sigma=ssim_sigma)
        self.mi_loss = GlobalMutualInformationLoss(kernel_type="gaussian", num_bins=mi_bins, sigma_ratio=mi_sigma_ratio)
        self._points: dict[tuple, torch.Tensor] = {}

    # -- individual terms (unweighted, batch-averaged) ---------------------------------------------------------
    def ssim_term(self, warped: torch.Tensor, fixed: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """``1 - SSIM`` (0 for identical images)."""
        if mask is None:
            return self.ssim_loss(warped.float(), fixed.float())
        s = masked_ssim(warped, fixed, mask, self.ssim_win_size, self.ssim_sigma)
        return (1.0 - s).mean()

    def ncc_term(self, warped: torch.Tensor, fixed: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """``-NCC`` (-1 for identical non-constant images)."""
        return -masked_ncc(warped, fixed, mask).mean()

    def mi_term(self, warped: torch.Tensor, fixed: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """``-MI`` in nats (float32, autocast disabled: MI is unstable in fp16)."""
        with torch.autocast(device_type=warped.device.type, enabled=False):
            w, f = warped.float(), fixed.float()
            if mask is None:
                return self.mi_loss(w, f)
            return -masked_mutual_information(w, f, mask.float(), self.mi_loss).mean()

    def sup_term(
        self, params_pred: torch.Tensor, params_true: torch.Tensor, grid: Grid, mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Mean point distance (mm) on every ``sup_step``-th voxel of ``grid`` (inside ``mask`` if given)."""
        key = (grid, self.sup_step)
        if key not in self._points:
            self._points[key] = torch.as_tensor(grid_points(grid, self.sup_step), dtype=torch.float64)
        pts = self._points[key]
        weights = None
        if mask is not None:
            s = self.sup_step
            # grid_points enumerates x-major, then y, then z: the same order as flattening [x, y, z]
            weights = (mask[:, 0, ::s, ::s, ::s] > 0).flatten(1)
        return supervised_point_distance(params_pred, params_true, pts, grid.center(), weights).mean()

    def forward(
        self,
        warped: torch.Tensor,
        fixed: torch.Tensor,
        params_pred: torch.Tensor,
        params_true: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        grid: Grid | None = None,
    ) -> LossTerms:
        """Compute all terms.

        Args:
            warped: ``[B, 1, x, y, z]`` moving volume warped onto the network grid by ``params_pred``, ~[0, 1].
            fixed: ``[B, 1, x, y, z]`` fixed volume on the same grid, ~[0, 1].
            params_pred: ``[B, 6]`` predicted ``(tx, ty, tz, rx, ry, rz)`` (mm, degrees) about the grid centre.
            params_true: ``[B, 6]`` ground truth, required when ``w_sup > 0``.
            mask: optional ``[B, 1, x, y, z]`` field-of-view mask (non-zero = inside).
            grid: the network grid; required for ``w_sup > 0`` and ``grad_term="image"``; it also provides the
                rotation centre of the grid term (else the centre is irrelevant: ``R - I`` does not depend on it).

        Returns:
            :class:`LossTerms` (``total`` is the scalar to back-propagate).
        """
        if warped.shape != fixed.shape or warped.ndim != 5:
            raise ValueError(f"warped {tuple(warped.shape)} and fixed {tuple(fixed.shape)} must match, [B, C, x, y, z]")
        warped = warped.clamp(0.0, 1.0)
        fixed = fixed.clamp(0.0, 1.0)
        dt = torch.promote_types(warped.dtype, torch.float32)
        zero = torch.zeros((), dtype=dt, device=warped.device)
        ssim = self.ssim_term(warped, fixed, mask) if self.w_ssim != 0 else zero
        ncc = self.ncc_term(warped, fixed, mask) if self.w_ncc != 0 else zero
        mi = self.mi_term(warped, fixed, mask) if self.w_mi != 0 else zero
        grad = zero
        if self.w_grad != 0:
            if self.grad_term == "grid":
                center = None if grid is None else grid.center()
                grad = grid_gradient_penalty(params_to_matrix_torch(params_pred.to(dt), center)).mean()
            else:
                if grid is None:
                    raise ValueError("grad_term='image' needs the network grid (for its spacing)")
                grad = image_gradient_difference(warped, fixed, grid.spacing, mask).mean()
        reg = (params_pred.to(dt) ** 2).sum(1).mean() if self.w_reg != 0 else zero
        sup = zero
        if self.w_sup != 0:
            if params_true is None or grid is None:
                raise ValueError("the supervised term (w_sup > 0) needs params_true and grid")
            sup = self.sup_term(params_pred, params_true, grid, mask)
        total = (
            self.w_ssim * ssim
            + self.w_ncc * ncc
            + self.w_mi * mi
            + self.w_grad * grad
            + self.w_reg * reg
            + self.w_sup * sup.to(dt)
        )
        return LossTerms(total, ssim, ncc, mi, grad, reg, sup.to(dt))
