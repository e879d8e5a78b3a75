"""Tiny synthetic registration pairs for tests, smoke training and the network benchmark (not a simulator:
no projection or reconstruction; :mod:`monai_rigidreg.simulation` has the CT/CBCT simulator next to it).

A phantom is an analytic function of LPS position: a soft ellipsoidal "body" plus random Gaussian blobs, values
in [0, 1]. The fixed volume samples it on the grid, ``F(x) = P(x)``; the moving volume samples it displaced,
``M(y) = P(T^{-1}(y))``, so that ``M(T(x)) = F(x)`` exactly: ``T`` (fixed -> moving, the project convention) is
the registration ground truth and no interpolation or padding enters the pair.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.core.geometry import Grid, grid_points, params_to_matrix_torch

__all__ = ["random_phantom", "phantom_pair_batch", "random_params", "blob_ct"]


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


def blob_ct(n: int = 48, spacing: float = 2.0) -> sitk.Image:
    """A smooth CT-like test object in HU (float32 ``SimpleITK.Image``, ``n`` voxels of ``spacing`` mm a side, centred
    on the origin, identity direction): an ellipsoidal soft-tissue body (0 HU) in air (-1000 HU) holding four
    distinct blobs (-500 to 1200 HU), smoothed by a 2 mm Gaussian. The documentation's examples register it with a
    shifted copy of itself.

    >>> ct = blob_ct()
    >>> ct.GetSize(), ct.GetSpacing(), ct.GetOrigin()
    ((48, 48, 48), (2.0, 2.0, 2.0), (-47.0, -47.0, -47.0))
    """
    c = (n - 1) / 2.0
    z, y, x = (a - c for a in np.mgrid[0:n, 0:n, 0:n].astype(np.float32))
    arr = np.full((n, n, n), -1000.0, np.float32)
    arr[(x / 20) ** 2 + (y / 16) ** 2 + (z / 18) ** 2 <= 1] = 0.0
    for bx, by, bz, r, hu in [(-8, -4, 3, 5, 900), (7, 5, -6, 4, 500), (2, -9, -8, 3, -500), (-3, 8, 9, 4, 1200)]:
        arr[(x - bx) ** 2 + (y - by) ** 2 + (z - bz) ** 2 <= r * r] = hu
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing((spacing,) * 3)
    img.SetOrigin((-c * spacing,) * 3)
    return sitk.SmoothingRecursiveGaussian(img, 2.0)
