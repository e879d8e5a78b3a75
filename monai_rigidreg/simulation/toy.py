"""Tiny synthetic registration pairs for tests, smoke training and the network benchmark (not a simulator:
no projection or reconstruction; :mod:`monai_rigidreg.simulation` has the CT/CBCT simulator next to it).

A phantom is an analytic function of LPS position: a soft ellipsoidal "body" plus random Gaussian blobs, values
in [0, 1]. The fixed volume samples it on the grid, ``F(x) = P(x)``; the moving volume samples it displaced,
``M(y) = P(T^{-1}(y))``, so that ``M(T(x)) = F(x)`` exactly: ``T`` (fixed -> moving, the project convention) is
the registration ground truth and no interpolation or padding enters the pair.
"""

from __future__ import annotations

import torch

from monai_rigidreg.geometry import Grid, grid_points, params_to_matrix_torch

__all__ = ["random_phantom", "phantom_pair_batch", "random_params"]


def random_phantom(generator: torch.Generator, n_blobs: int = 10, radius: float = 40.0) -> dict[str, torch.Tensor]:
    """Random phantom description (blob centres ``[K, 3]`` mm, widths ``[K]`` mm, amplitudes ``[K]``, body axes)."""
    g = generator
    centres = (torch.rand(n_blobs, 3, generator=g, dtype=torch.float64) * 2 - 1) * radius * 0.6
    sigmas = 5.0 + torch.rand(n_blobs, generator=g, dtype=torch.float64) * 0.12 * radius
    amps = 0.3 + 0.5 * torch.rand(n_blobs, generator=g, dtype=torch.float64)
    axes = radius * (0.7 + 0.3 * torch.rand(3, generator=g, dtype=torch.float64))
    return {"centres": centres, "sigmas": sigmas, "amps": amps, "axes": axes}


def _evaluate(ph: dict[str, torch.Tensor], pts: torch.Tensor, center: torch.Tensor) -> torch.Tensor:
    rel = pts - center
    r = torch.sqrt(((rel / ph["axes"]) ** 2).sum(-1))
    body = 0.25 * torch.sigmoid((1.0 - r) * 8.0)
    d2 = ((rel[:, None, :] - ph["centres"][None]) ** 2).sum(-1)
    blobs = (ph["amps"] * torch.exp(-0.5 * d2 / ph["sigmas"] ** 2)).sum(-1)
    return (body + blobs).clamp(0.0, 1.0)


def phantom_pair_batch(
    grid: Grid, params: torch.Tensor, generator: torch.Generator, n_blobs: int = 10
) -> tuple[torch.Tensor, torch.Tensor]:
    """A batch of (moving, fixed) pairs with ground truth ``params``.

    Args:
        grid: network grid.
        params: ``[B, 6]`` ground-truth ``(tx, ty, tz, rx, ry, rz)`` (mm, degrees) about ``grid.center()``.
        generator: torch RNG for the phantoms.
        n_blobs: blobs per phantom.

    Returns:
        ``moving, fixed``: ``[B, 1, *grid.size]`` float32 each, with ``moving(T(x)) = fixed(x)``.
    """
    pts = torch.as_tensor(grid_points(grid, step=1), dtype=torch.float64)
    center = torch.as_tensor(grid.center(), dtype=torch.float64)
    radius = 0.5 * min(s * n for s, n in zip(grid.spacing, grid.size))
    inv = torch.linalg.inv(params_to_matrix_torch(params.to(torch.float64), center))
    moving, fixed = [], []
    for b in range(params.shape[0]):
        ph = random_phantom(generator, n_blobs, radius)
        fixed.append(_evaluate(ph, pts, center))
        moving.append(_evaluate(ph, pts @ inv[b, :3, :3].T + inv[b, :3, 3], center))
    shape = (params.shape[0], 1, *grid.size)
    return torch.stack(moving).view(shape).float(), torch.stack(fixed).view(shape).float()


def random_params(
    n: int, generator: torch.Generator, max_translation: float = 10.0, max_rotation: float = 10.0
) -> torch.Tensor:
    """``[n, 6]`` uniform random parameters in ``+-max_translation`` mm and ``+-max_rotation`` degrees."""
    u = torch.rand(n, 6, generator=generator, dtype=torch.float64) * 2 - 1
    return u * torch.tensor([max_translation] * 3 + [max_rotation] * 3, dtype=torch.float64)
