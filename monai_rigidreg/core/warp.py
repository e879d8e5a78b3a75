"""Differentiable rigid resampling of volumes in physical space (the torch twin of ``SimpleITK.Resample``).

The normalized ``theta`` comes from :func:`monai_rigidreg.core.geometry.normalized_theta`; sampling is torch's
``affine_grid`` (as per-axis sums: :func:`affine_grid`) + ``grid_sample`` with ``align_corners=True``: what MONAI's
:class:`monai.networks.layers.AffineTransform` (``normalized=True``, ``reverse_indexing=False``) computes, called
directly so that the register path does not import MONAI (see :mod:`monai_rigidreg.core.grid_sampling`);
``tests/core/test_warp.py`` checks the two agree to float rounding.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F

from monai_rigidreg.core.geometry import Grid, index_to_normalized, normalized_theta, params_to_matrix_torch

__all__ = ["affine_grid", "normalized_points", "sample_normalized", "warp_points", "warp_volume", "warp_volume_many",
           "warp_volume_params"]

MODES = ("bilinear", "nearest")
PADDING_MODES = ("zeros", "border", "reflection")


def warp_volume(
    moving: torch.Tensor,
    matrix: torch.Tensor,
    fixed_grid: Grid,
    moving_grid: Grid,
    mode: str = "bilinear",
    padding_mode: str = "zeros",
    array_order: str = "xyz",
) -> torch.Tensor:
    """Resample ``moving`` onto ``fixed_grid`` under physical fixed->moving transforms (differentiable).

    Args:
        moving: ``[B, C, *spatial]`` volume on ``moving_grid`` (spatial axes in ``array_order``).
        matrix: ``[B, 4, 4]`` transforms (fixed -> moving, LPS mm).
        fixed_grid: output grid.
        moving_grid: grid of ``moving``.
        mode: ``"bilinear"`` (trilinear) or ``"nearest"``.
        padding_mode: ``"zeros"``, ``"border"`` or ``"reflection"`` for samples outside the moving volume.
        array_order: ``"xyz"`` (MONAI layout) or ``"zyx"`` (SimpleITK array layout).

    Returns:
        ``[B, C, *fixed spatial]`` tensor, dtype of ``moving``.
    """
    _check_batch(moving, matrix)
    sample_at = _sample_points(moving, matrix, fixed_grid, moving_grid, mode, padding_mode, array_order)
    return F.grid_sample(moving.contiguous(), sample_at, mode=mode, padding_mode=padding_mode, align_corners=True)


def _check_batch(moving: torch.Tensor, matrix: torch.Tensor) -> None:
    """``moving`` a ``[B, C, D, H, W]`` batch and ``matrix`` one transform per case."""
    if moving.ndim != 5:
        raise ValueError(f"moving must be [B, C, D, H, W], got shape {tuple(moving.shape)}")
    if matrix.shape[0] != moving.shape[0]:
        raise ValueError(f"batch of matrix ({matrix.shape[0]}) and moving ({moving.shape[0]}) differ")


def _check_moving(moving: torch.Tensor, moving_grid: Grid, mode: str, padding_mode: str, array_order: str) -> None:
    """``moving``'s spatial shape against its grid (in ``array_order``) and the sampling modes."""
    expected = tuple(moving_grid.size) if array_order == "xyz" else tuple(moving_grid.size)[::-1]
    if tuple(moving.shape[2:]) != expected:
        raise ValueError(f"moving spatial shape {tuple(moving.shape[2:])} does not match its grid {expected}")
    if mode not in MODES or padding_mode not in PADDING_MODES:
        raise ValueError(f"mode must be one of {MODES} and padding_mode one of {PADDING_MODES}, got {mode!r}, "
                         f"{padding_mode!r}")


def _sample_points(moving: torch.Tensor, matrices: torch.Tensor, fixed_grid: Grid, moving_grid: Grid, mode: str,
                   padding_mode: str, array_order: str) -> torch.Tensor:
    """The checks :func:`warp_volume` and :func:`warp_volume_many` share (``moving``'s spatial shape against its
    grid, the modes) and ``grid_sample``'s sampling points of the ``K`` fixed -> moving ``matrices``:
    ``[K, *fixed spatial, 3]`` in ``moving``'s dtype."""
    _check_moving(moving, moving_grid, mode, padding_mode, array_order)
    theta = normalized_theta(matrices.to(torch.float64), fixed_grid, moving_grid, array_order).to(moving.dtype)
    out_size = tuple(fixed_grid.size) if array_order == "xyz" else tuple(fixed_grid.size)[::-1]
    return affine_grid(theta[:, :3], out_size)


def affine_grid(theta: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """``F.affine_grid(theta, [B, C, *size], align_corners=True)`` as a sum of three per-axis terms.

    Torch forms every point as ``[x, y, z, 1] @ theta^T``, a batched matrix product with an inner size of 4 that
    runs on a slow path on the CPU: 21.5 ms for a ``102^3`` grid where the per-axis sum takes 4.1 ms, 6.0 -> 1.2 ms
    at ``64^3`` (2 cores, torch 2.13, ``benchmarks/speed/bench_network_paths.py``). The same points to float rounding
    and the same gradients with respect to ``theta`` (``tests/core/test_warp.py``).

    Args:
        theta: ``[B, 3, 4]`` normalized affine matrices (:func:`~monai_rigidreg.core.geometry.normalized_theta`).
        size: the output's spatial size ``(D, H, W)``; ``x`` runs along ``W``, ``z`` along ``D``.

    Returns:
        ``[B, D, H, W, 3]`` sampling points for ``grid_sample``, in ``theta``'s dtype.

    Example:
        >>> theta = torch.tensor([[[1.0, 0.0, 0.0, 0.5], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]])
        >>> [round(v, 4) for v in affine_grid(theta, (2, 3, 4))[0, 0, 0, :, 0].tolist()]  # x shifted by 0.5
        [-0.5, 0.1667, 0.8333, 1.5]
    """
    if theta.ndim != 3 or tuple(theta.shape[1:]) != (3, 4):
        raise ValueError(f"theta must be [B, 3, 4], got shape {tuple(theta.shape)}")
    d, h, w = (int(n) for n in size)

    def base(n: int) -> torch.Tensor:  # affine_grid's coordinates: -1..1, a one-voxel axis at 0
        if n <= 1:
            return torch.zeros(n, dtype=theta.dtype, device=theta.device)
        return torch.linspace(-1.0, 1.0, n, dtype=theta.dtype, device=theta.device)

    th = theta[:, None, None, None]  # [B, 1, 1, 1, 3, 4]
    along_w = base(w).view(1, 1, 1, w, 1) * th[..., 0] + th[..., 3]  # [B, 1, 1, W, 3]
    along_h = base(h).view(1, 1, h, 1, 1) * th[..., 1]
    along_d = base(d).view(1, d, 1, 1, 1) * th[..., 2]
    return along_d + (along_h + along_w)  # one full-size sum


def warp_points(moving: torch.Tensor, matrix: torch.Tensor, points: torch.Tensor, fixed_grid: Grid, moving_grid: Grid,
                mode: str = "bilinear", padding_mode: str = "zeros") -> torch.Tensor:
    """:func:`warp_volume` at some voxels of ``fixed_grid`` only: ``[B, C, x, y, z]`` (``xyz`` layout on
    ``moving_grid``), ``[B, 4, 4]`` fixed -> moving matrices (LPS mm) and ``points`` ``[K, 3]``, fixed-grid voxel
    indices ``(i, j, k)`` (float, may be fractional) -> ``[B, C, K]``, the values :func:`warp_volume` has there
    (the same sampling, ``grid_sample`` with ``align_corners=True``, on a ``[B, 1, 1, K, 3]`` grid of points), on
    grids of at least two voxels along each axis (``affine_grid`` puts a one-voxel axis at the normalized
    coordinate 0, half a voxel off its centre; here it is the voxel's centre).

    The cost is that of ``K`` output voxels: the last level's Gauss-Newton steps sample only the voxels that can
    carry weight (:func:`~monai_rigidreg.networks.gauss_newton.gauss_newton_align`, ``candidates``).
    """
    _check_batch(moving, matrix)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be [K, 3] voxel indices, got shape {tuple(points.shape)}")
    _check_moving(moving, moving_grid, mode, padding_mode, "xyz")
    return sample_normalized(moving, matrix, normalized_points(points, fixed_grid, moving.dtype), fixed_grid,
                              moving_grid, mode, padding_mode)


def normalized_points(points: torch.Tensor, grid: Grid, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Voxel indices ``[K, 3]`` ``(i, j, k)`` of ``grid`` -> ``grid_sample``'s normalized coordinates ``[K, 3]``
    (``align_corners=True``; component ``g`` addresses index axis ``2 - g``, as ``affine_grid`` lays them out;
    :func:`~monai_rigidreg.core.geometry.index_to_normalized`)."""
    m = torch.as_tensor(index_to_normalized(grid.size, "xyz"), dtype=dtype, device=points.device)
    return torch.addmm(m[:3, 3], points.to(dtype), m[:3, :3].T)


def sample_normalized(moving: torch.Tensor, matrix: torch.Tensor, normalized: torch.Tensor, fixed_grid: Grid,
                       moving_grid: Grid, mode: str = "bilinear", padding_mode: str = "zeros") -> torch.Tensor:
    """:func:`warp_points` from the points' :func:`normalized_points` (computed once by a caller that samples the
    same points under many matrices): ``[B, C, K]``."""
    theta = normalized_theta(matrix.to(torch.float64), fixed_grid, moving_grid, "xyz").to(moving.dtype)  # [B, 3, 4]
    sample_at = torch.baddbmm(theta[:, None, :, 3], normalized.expand(theta.shape[0], -1, -1),
                              theta[:, :, :3].transpose(1, 2))  # [B, K, 3]
    out = F.grid_sample(moving.contiguous(), sample_at[:, None, None], mode=mode, padding_mode=padding_mode,
                        align_corners=True)  # [B, C, 1, 1, K]
    return out[:, :, 0, 0]


def warp_volume_many(moving: torch.Tensor, matrices: torch.Tensor, fixed_grid: Grid, moving_grid: Grid,
                     mode: str = "bilinear", padding_mode: str = "zeros") -> torch.Tensor:
    """One volume under ``K`` transforms: ``[1, C, x, y, z]`` (``xyz`` layout on ``moving_grid``) and ``[K, 4, 4]``
    fixed -> moving matrices (LPS mm) -> ``[K, C, *fixed_grid.size]``, as :func:`warp_volume` of ``K`` copies.

    The ``K`` sampling grids are stacked along the first output axis of a single ``grid_sample`` call, so the volume
    is read in place instead of being copied ``K`` times (``grid_sample`` makes a batch of ``expand``-ed views
    contiguous: 27 copies of a 128^3 CBCT and of its field of view for the global search's rotations).
    """
    if moving.ndim != 5 or moving.shape[0] != 1:
        raise ValueError(f"moving must be one volume [1, C, x, y, z], got shape {tuple(moving.shape)}")
    k, c = matrices.shape[0], moving.shape[1]
    size = tuple(fixed_grid.size)
    sample_at = _sample_points(moving, matrices, fixed_grid, moving_grid, mode, padding_mode, "xyz")
    out = F.grid_sample(moving.contiguous(), sample_at.reshape(1, k * size[0], *size[1:], 3), mode=mode,
                        padding_mode=padding_mode, align_corners=True)  # [1, C, K * x, y, z]
    return out.reshape(c, k, *size).transpose(0, 1)


def warp_volume_params(
    moving: torch.Tensor,
    params: torch.Tensor,
    fixed_grid: Grid,
    moving_grid: Grid | None = None,
    center: Any = None,
    **kwargs: Any,
) -> torch.Tensor:
    """:func:`warp_volume` from ``[B, 6]`` parameters (mm / degrees) about ``center`` (default fixed centre)."""
    moving_grid = fixed_grid if moving_grid is None else moving_grid
    c = fixed_grid.center() if center is None else center
    matrix = params_to_matrix_torch(params.to(torch.float64), c)
    return warp_volume(moving, matrix, fixed_grid, moving_grid, **kwargs)
