"""How precisely the last level's images determine the pose: an expected TRE from the Gauss-Newton normal equations.

At the last level's final estimate the weighted least-squares problem it solved has a normal matrix ``H = J^T W J``
(six pose parameters plus the smooth intensity-bias terms, which are marginalised out) and a residual variance
``s^2``. Were the residuals independent noise, ``s^2 H^-1`` would be the covariance of the pose; the features are
smooth over several millimetres, so the voxel count overstates the independent samples: the covariance is scaled by
the voxels per ``cell_mm`` cube (:data:`CELL_MM`). The number that comes out is a relative measure (a pair with
little structure in view, or a large residual, reads higher), fed to the calibrated confidence as a feature; its
scale is not a promise about millimetres.

Frames: parameters ``(tx, ty, tz, rx, ry, rz)`` mm / degrees about the grid centre, the grid in the CT frame.
"""

from __future__ import annotations

import numpy as np
import torch

from monai_rigidreg.core.geometry import Grid, grid_points, params_to_matrix, transform_points
from monai_rigidreg.core.image_ops import pyramid
from monai_rigidreg.core.warp import warp_volume
from monai_rigidreg.networks.gauss_newton import fixed_jacobian, polynomial_basis

__all__ = ["CELL_MM", "pose_covariance", "expected_tre_mm"]

CELL_MM = 4.0
"""The residuals are taken as independent per cube of this edge (mm): about the scale of the local-contrast feature's
smoothing and of the edge test's pooling (:data:`~monai_rigidreg.registration.confidence.EDGE_SPACING_MM`)."""


def pose_covariance(moving: torch.Tensor, fixed: torch.Tensor, grid: Grid, matrix: torch.Tensor,
                    weight: torch.Tensor | None = None, moving_support: torch.Tensor | None = None,
                    bias_degree: int = -1, cell_mm: float = CELL_MM) -> tuple[np.ndarray, float, float]:
    """The pose covariance at ``matrix`` of the least-squares match of ``moving`` to ``fixed``.

    Args:
        moving, fixed: ``[1, C, x, y, z]`` features on ``grid`` (``moving`` unwarped, as
            :func:`~monai_rigidreg.networks.gauss_newton.gauss_newton_align` takes it).
        grid: their grid (CT frame).
        matrix: ``[1, 4, 4]`` the estimate (fixed -> moving, of ``moving``'s frame).
        weight, moving_support: as for ``gauss_newton_align``.
        bias_degree: the intensity-bias polynomial estimated with the pose (-1: none); marginalised out.
        cell_mm: see :data:`CELL_MM`.

    Returns:
        ``(cov, s2, count)``: the ``[6, 6]`` covariance (mm / degrees), the residual variance, and the voxels that
        carry weight on the pooled grid; the covariance is infinite where fewer than 100 do, or where a direction of
        the pose is not constrained by the images (a singular normal matrix).
    """
    with torch.no_grad():
        n_ch = moving.shape[1]
        # on the grid pooled to about cell_mm: an eighth of the voxels of a 2 mm grid, where the samples are
        # nearer to independent anyway (the covariance is scaled to the cell below)
        factor = max(1, round(cell_mm / min(grid.spacing)))
        support = torch.ones_like(moving[:, :1]) if moving_support is None else moving_support.to(moving.dtype)
        fixed = pyramid(fixed, grid, factor)[0]
        if weight is not None:
            weight = (pyramid(weight.to(moving.dtype), grid, factor)[0] > 0.5).to(moving.dtype)
        stacked, grid = pyramid(torch.cat([moving, support], 1), grid, factor)
        both = warp_volume(stacked, matrix.to(torch.float64), grid, grid)
        w = (both[:, n_ch:] > 0.999).to(moving.dtype)
        if weight is not None:
            w = w * weight
        count = float(w.sum())
        if count < 100:
            return np.full((6, 6), np.inf), float("nan"), count
        r = (both[:, :n_ch] - fixed).flatten(2)  # [1, C, N]
        jac = fixed_jacobian(fixed, grid).flatten(3)  # [1, 6, C, N]
        wf = w.flatten(2)  # [1, 1, N]
        wj = (jac * wf.unsqueeze(1)).flatten(2)  # [1, 6, C*N]
        h = (wj @ jac.flatten(2).transpose(1, 2)).to(torch.float64)[0]  # [6, 6]
        sigma2 = float((wf * r**2).sum() / (wf.sum() * n_ch))
        if bias_degree >= 0:  # the pose block of the inverse: the bias terms marginalised (Schur complement)
            basis = polynomial_basis(grid, bias_degree, moving.dtype, moving.device).flatten(1)  # [k, N]
            wa = basis * wf[0]  # [k, N]
            h_aa = (wa @ basis.t()).to(torch.float64)
            for c in range(n_ch):
                h_pa = (wj[0, :, c * r.shape[2]:(c + 1) * r.shape[2]] @ basis.t()).to(torch.float64)  # [6, k]
                h = h - h_pa @ torch.linalg.solve(h_aa + 1e-9 * torch.eye(len(h_aa), dtype=h_aa.dtype), h_pa.t())
        voxel_mm3 = float(np.prod(grid.spacing))
        scale = sigma2 * max(1.0, cell_mm**3 / voxel_mm3)
        h_np = h.cpu().numpy()
        eig = np.linalg.eigvalsh(h_np)
        if not eig[0] > 1e-9 * max(eig[-1], 1e-30):  # a direction the images do not constrain
            return np.full((6, 6), np.inf), sigma2, count
        cov = scale * np.linalg.inv(h_np)
    return cov, sigma2, count


def expected_tre_mm(cov: np.ndarray, grid: Grid, step: int = 8) -> float:
    """The root-mean-square displacement (mm) over ``grid``'s points (every ``step``-th) of a pose error with
    covariance ``cov`` (``[6, 6]``, mm / degrees about ``grid``'s centre): ``sqrt(mean_x trace(A(x) cov A(x)^T))``
    with ``A(x)`` the displacement of ``x`` per parameter."""
    if not np.all(np.isfinite(cov)):
        return float("inf")
    pts = grid_points(grid, step)  # [N, 3]
    h, center = 1e-3, grid.center()
    # displacement of each point per unit parameter (central differences of the one conversion module's matrices)
    flow = np.stack([(transform_points(params_to_matrix(h * row, center), pts)
                      - transform_points(params_to_matrix(-h * row, center), pts)) / (2 * h)
                     for row in np.eye(6)], 1)  # [N, 6, 3]
    m = np.einsum("nki,nli->kl", flow, flow) / len(pts)
    return float(np.sqrt(max(0.0, float(np.trace(cov @ m)))))
