"""The terms of one Gauss-Newton step of the fine stage (:mod:`monai_rigidreg.networks.gauss_newton`): how each of the
six parameters moves a voxel (:func:`parameter_flow`), the CT's Jacobian built from it (:func:`fixed_jacobian`), the
intensity-bias basis (:func:`polynomial_basis`) and flat voxel indices (:func:`voxel_indices`).

Parameters are ``(tx, ty, tz, rx, ry, rz)`` mm / degrees about the grid centre; the voxel displacement per parameter
comes from :func:`~monai_rigidreg.core.geometry.params_to_matrix` and the grid's index-to-physical matrix
(``docs/conventions.md``), so no convention is derived a second time here.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import torch

from monai_rigidreg.core.geometry import Grid, grid_points, params_to_matrix

__all__ = ["parameter_flow", "fixed_jacobian", "polynomial_basis", "voxel_indices"]


def parameter_flow(grid: Grid, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
                   ) -> torch.Tensor:
    """Physical displacement of every voxel centre per unit parameter at the identity: ``[6, 3, x, y, z]``.

    ``d W_p(x) / dp_k`` (mm per mm, mm per degree) for ``W_p`` of :func:`~monai_rigidreg.core.geometry.params_to_matrix`
    about ``grid.center()``, by central differences of that function (:func:`_parameter_derivative`; exact for
    translations, rotations to O(h^2) with h = 1e-3 degrees). The fine stage does not build it
    (:func:`fixed_jacobian` uses its affine coefficients); it is the reference the tests check them against.
    """
    deriv = torch.as_tensor(_parameter_derivative(grid), dtype=torch.float64, device=device)  # [6, 3, 4]
    # LPS mm of every voxel centre, in the xyz (index-major) order of the volume
    pts = torch.as_tensor(grid_points(grid, 1).T, dtype=torch.float64, device=device)  # [3, N]
    flow = deriv[:, :, :3] @ pts + deriv[:, :, 3:]  # [6, 3, N]
    return flow.reshape(6, 3, *grid.size).to(dtype)


def _parameter_derivative(grid: Grid) -> np.ndarray:
    """``d W_p / dp_k`` at ``p = 0`` as an affine map of physical points: ``[6, 3, 4]`` (``[:, :, :3]`` linear part,
    ``[:, :, 3]`` offset), from central differences of :func:`~monai_rigidreg.core.geometry.params_to_matrix` about
    ``grid.center()``. numpy, not torch: under ``torch.jit.trace`` a cached result (:func:`_flow_coefficients`) must
    not have recorded traced operations (the cache would make a second trace differ from the first)."""
    h = 1e-3
    center = grid.center()
    mats = np.stack([params_to_matrix(sign * h * row, center) for sign in (1.0, -1.0) for row in np.eye(6)])
    return (mats[:6] - mats[6:])[:, :3, :] / (2 * h)


def fixed_jacobian(fixed: torch.Tensor, grid: Grid, index: torch.Tensor | None = None,
                   points: torch.Tensor | None = None) -> torch.Tensor:
    """``d fixed(W_p(x)) / dp`` at ``p = 0``: ``[B, 6, C, x, y, z]`` (per mm and per degree); with ``index`` (``[K]``
    flat voxel indices of the grid) at those voxels only: ``[B, 6, C, K]`` (the gradients are taken over the whole
    grid, the rest is formed at the ``K`` voxels; ``points``: their voxel indices ``[K, 3]``, if at hand).

    Chain rule: the physical image gradient (central differences along the array axes, mapped through the
    grid's index-to-physical matrix) times :func:`parameter_flow`. ``fixed`` is in MONAI ``xyz`` layout on ``grid``.

    The flow is affine in the voxel index, ``flow_k(u) = K_k u + b_k`` with ``u`` the index about the grid centre, so
    ``J_k = sum_i (K_k^T A^-1 g)_i u_i + (b_k^T A^-1 g)`` is formed from the three index gradients ``g`` and three
    broadcast index ramps, never the ``[6, 3, N]`` flow itself (:func:`_flow_coefficients`; on the last level's
    ~1M-voxel grid, which changes with every case: 0.06 s instead of 0.23 s through the flow,
    ``benchmarks/speed/bench_network_paths.py``).
    """
    if tuple(fixed.shape[2:]) != tuple(grid.size):
        raise ValueError(f"fixed spatial shape {tuple(fixed.shape[2:])} does not match its grid {grid.size}")
    g_idx = torch.gradient(fixed, dim=(2, 3, 4))  # 3 x [B, C, x, y, z] per index step
    slope, offset = _flow_coefficients(grid)  # [6, 3 (index axis), 3 (gradient axis)], [6, 3 (gradient axis)]
    if index is None:
        ramps = [(torch.arange(n, dtype=fixed.dtype, device=fixed.device) - (n - 1) / 2.0).view(
            [n if a == i else 1 for a in range(3)]) for i, n in enumerate(grid.size)]
    else:
        g_idx = [g.flatten(2)[:, :, index] for g in g_idx]  # 3 x [B, C, K]
        at = voxel_indices(index, grid.size) if points is None else points.unbind(1)
        ramps = [u.to(fixed.dtype) - (n - 1) / 2.0 for u, n in zip(at, grid.size)]

    def combine(coefs: np.ndarray) -> torch.Tensor | None:
        terms = [float(c) * g for c, g in zip(coefs, g_idx) if c != 0.0]
        return sum(terms[1:], terms[0]) if terms else None

    out = []
    for k in range(6):
        jac = combine(offset[k])
        for i in range(3):
            part = combine(slope[k, i])
            if part is not None:
                jac = part * ramps[i] if jac is None else jac + part * ramps[i]
        out.append(torch.zeros_like(g_idx[0]) if jac is None else jac)
    return torch.stack(out, 1)


@functools.lru_cache(maxsize=64)
def _flow_coefficients(grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """The coefficients of :func:`fixed_jacobian` for ``grid``: ``slope[k, i, m]`` and ``offset[k, m]`` such that
    ``J_k = sum_m (sum_i slope[k, i, m] u_i + offset[k, m]) dI/du_m`` with ``u`` the voxel index about the grid
    centre and ``dI/du_m`` the image gradient per index step along array axis ``m``.

    From the derivative :func:`parameter_flow` is built from (:func:`_parameter_derivative`):
    ``flow_k(p) = D_k (p - c) + d_k`` (physical, mm), ``p - c = A u`` with ``A`` the grid's direction times spacing,
    and the physical gradient ``A^-T dI/du``."""
    center = grid.center()
    deriv = _parameter_derivative(grid)  # [6, 3, 4]
    lin = deriv[:, :, :3]  # D_k
    const = lin @ center + deriv[:, :, 3]  # d_k = flow at the centre
    a = grid.index_to_physical()[:3, :3]
    a_inv = np.linalg.inv(a)
    # flow . A^-T g = (A^-1 flow) . g: per index axis i the coefficients of g of the term in u_i
    slope = np.einsum("mp,kpq,qi->kim", a_inv, lin, a)  # [6, i, m]
    offset = np.einsum("mp,kp->km", a_inv, const)  # [6, m]
    return slope, offset


def voxel_indices(index: torch.Tensor, size: Sequence[int]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Flat indices ``[K]`` of a ``size`` ``(x, y, z)`` volume (row-major, the last axis fastest) -> the three voxel
    index tensors ``(i, j, k)``. Written out rather than ``torch.unravel_index``, whose first call imports sympy
    (0.35 s of a command-line registration, measured with cProfile)."""
    ny, nz = int(size[1]), int(size[2])
    return index // (ny * nz), (index // nz) % ny, index % nz


def polynomial_basis(grid: Grid, degree: int, dtype: torch.dtype = torch.float32,
                     device: torch.device | str | None = None) -> torch.Tensor:
    """Monomials of total degree <= ``degree`` in the grid's index coordinates scaled to [-1, 1]: ``[k, x, y, z]``.

    Degree 0: the constant (k = 1); 1: plus x, y, z (k = 4); 2: plus the six quadratic terms (k = 10); and so on.
    Smooth intensity fields such as CBCT cupping and scatter shading are close to this span over a network grid.
    Cached like :func:`parameter_flow` (shared tensor: do not modify it in place).
    """
    dev = str(torch.device(device) if device is not None else torch.device("cpu"))
    if torch.jit.is_tracing():
        return _polynomial_basis.__wrapped__(tuple(grid.size), int(degree), dtype, dev)
    return _polynomial_basis(tuple(grid.size), int(degree), dtype, dev)


@functools.lru_cache(maxsize=8)
def _polynomial_basis(size: tuple[int, ...], degree: int, dtype: torch.dtype, device: str) -> torch.Tensor:
    axes = [torch.linspace(-1.0, 1.0, n, dtype=torch.float64, device=device) if n > 1
            else torch.zeros(1, dtype=torch.float64, device=device) for n in size]
    x, y, z = torch.meshgrid(*axes, indexing="ij")
    terms = [x**i * y**j * z**m for total in range(degree + 1) for i in range(total, -1, -1)
             for j in range(total - i, -1, -1) for m in [total - i - j]]
    return torch.stack(terms).to(dtype)
