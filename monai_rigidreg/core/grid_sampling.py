"""Physical resampling of tensors and SimpleITK images onto a :class:`~monai_rigidreg.core.geometry.Grid`, and the HU
normalization of the network's input, with torch and SimpleITK only.

The registration path (``monai-rigidreg register``, :class:`~monai_rigidreg.registration.RigidRegistrar`) uses these
functions directly; the MONAI transforms of :mod:`monai_rigidreg.transforms` (``ResampleToNetworkGrid``,
``NormalizeHU``) wrap the same functions for ``MetaTensor`` data. Keeping them out of the ``transforms`` package
keeps MONAI out of the register path: ``import monai`` costs about 6 s on 2 cores (its ``__init__`` imports every
submodule, ignite and ``torch.distributed`` with them; ``python -X importtime -c "import monai"``), four times the
whole registration's budget in the speed issue.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.core.geometry import Grid, transform_points
from monai_rigidreg.core.image_ops import gaussian_smooth
from monai_rigidreg.core.warp import warp_volume

__all__ = ["PaddingValue", "antialias_for_grid", "antialias_sigmas", "crop_to_grid", "normalize_hu",
           "resample_physical", "resample_to_grid", "sitk_on_grid", "sitk_tensor"]

PaddingValue = float | str | None
"""Value written where a resampled voxel falls outside the input: a number (e.g. ``-1000.0`` HU), ``"min"``
(per-channel minimum of the input) or ``None`` (use ``padding_mode`` of ``grid_sample`` as is)."""

def _check_image(img: torch.Tensor) -> None:
    if img.ndim != 4:
        raise ValueError(f"expected a channel-first 3D image [C, x, y, z], got shape {tuple(img.shape)}")


def resample_physical(
    img: torch.Tensor,
    matrix: Any,
    out_grid: Grid,
    in_grid: Grid,
    mode: str = "bilinear",
    padding_mode: str = "zeros",
    padding_value: PaddingValue = None,
) -> torch.Tensor:
    """Resample a channel-first image ``[C, x, y, z]`` on ``in_grid`` onto ``out_grid``.

    ``out(y) = img(matrix @ y)`` for every physical point ``y`` (LPS mm) of ``out_grid``: the semantics of
    ``sitk.Resample(img, out_grid, T)`` with ``T`` the 4x4 ``matrix`` (thin wrapper of
    :func:`monai_rigidreg.core.warp.warp_volume`).

    Args:
        img: plain tensor ``[C, x, y, z]`` (any dtype, any device).
        matrix: 4x4 physical transform (output -> input, LPS mm).
        out_grid: grid of the output.
        in_grid: grid of ``img``.
        mode: ``"bilinear"`` (trilinear) or ``"nearest"``.
        padding_mode: ``grid_sample`` padding mode, used when ``padding_value`` is ``None``.
        padding_value: constant written outside the input (see :data:`PaddingValue`); overrides ``padding_mode``.

    Returns:
        ``[C, *out_grid.size]`` tensor, same dtype and device as ``img`` (integer inputs are rounded back).
    """
    _check_image(img)
    orig_dtype = img.dtype
    cdtype = orig_dtype if orig_dtype in (torch.float32, torch.float64) else torch.float32
    x = img.to(cdtype)
    shift: torch.Tensor | float | None = None
    if padding_value is not None:
        if isinstance(padding_value, str):
            if padding_value != "min":
                raise ValueError(f"padding_value must be a number, 'min' or None, got {padding_value!r}")
            shift = x.amin(dim=(1, 2, 3), keepdim=True)
        else:
            shift = float(padding_value)
        # into a new C-contiguous tensor: the subtraction on a transposed view (sitk_tensor) would keep its strides
        # and grid_sample would copy it once more
        x = torch.sub(x, shift, out=torch.empty(x.shape, dtype=cdtype, device=x.device))
        padding_mode = "zeros"
    m = torch.as_tensor(np.asarray(matrix, dtype=np.float64), dtype=torch.float64, device=x.device).unsqueeze(0)
    out = warp_volume(x.unsqueeze(0), m, out_grid, in_grid, mode=mode, padding_mode=padding_mode)[0]
    if shift is not None:
        out = out + shift
    if not orig_dtype.is_floating_point:
        out = out.round()
    return out.to(orig_dtype)


def antialias_sigmas(in_grid: Grid, out_grid: Grid) -> list[float]:
    """Per index axis of ``in_grid``, the Gaussian sigma (voxels) of :func:`antialias_for_grid`:
    (ratio - 1) / 2 with ratio = min(out spacing) / in spacing, 0 where the input is not finer."""
    target = float(min(out_grid.spacing))
    return [max(0.0, (target / s - 1.0) / 2.0) for s in in_grid.spacing]


def antialias_for_grid(img: torch.Tensor, in_grid: Grid, out_grid: Grid) -> torch.Tensor:
    """Gaussian pre-filter of a ``[C, x, y, z]`` image on ``in_grid`` before sampling it onto a coarser
    ``out_grid`` (sigmas of :func:`antialias_sigmas`). Returns ``img`` itself when nothing needs smoothing."""
    sigmas = antialias_sigmas(in_grid, out_grid)
    if max(sigmas) < 0.25:
        return img
    x = img.as_tensor() if hasattr(img, "as_tensor") else img  # a MetaTensor's plain data
    return gaussian_smooth(x.float() if not x.is_floating_point() else x, sigmas).to(img.dtype)


def crop_to_grid(img: torch.Tensor, in_grid: Grid, out_grid: Grid, margin: int,
                 matrix: np.ndarray | None = None) -> tuple[torch.Tensor, Grid]:
    """The part of a ``[C, x, y, z]`` image on ``in_grid`` that ``out_grid`` can sample, plus ``margin`` voxels.

    ``matrix``: the 4x4 physical transform (``out_grid`` point -> ``in_grid`` point, LPS mm) the sampling goes
    through (default identity).

    Returns the cropped view and its grid (same spacing and direction, shifted origin); the image itself when the
    crop would keep (almost) everything. Sampling ``out_grid`` from the crop gives the same values as from the
    whole image wherever a filter of radius up to ``margin`` voxels was applied first.
    """
    corners = np.array([[i, j, k] for i in (0, out_grid.size[0] - 1) for j in (0, out_grid.size[1] - 1)
                        for k in (0, out_grid.size[2] - 1)], dtype=np.float64)
    phys = transform_points(out_grid.index_to_physical(), corners)
    if matrix is not None:
        phys = transform_points(np.asarray(matrix, dtype=np.float64), phys)
    idx = transform_points(np.linalg.inv(in_grid.index_to_physical()), phys)
    lo = np.maximum(np.floor(idx.min(0)).astype(int) - 1 - margin, 0)
    hi = np.minimum(np.ceil(idx.max(0)).astype(int) + 2 + margin, np.array(in_grid.size))
    if np.any(hi <= lo):  # no overlap: nothing to save, the caller pads
        return img, in_grid
    if np.prod(hi - lo) > 0.8 * np.prod(in_grid.size):
        return img, in_grid
    crop = img[:, lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    origin = tuple(float(v) for v in transform_points(in_grid.index_to_physical(), lo)[0])
    return crop, Grid(tuple(int(v) for v in hi - lo), in_grid.spacing, origin, in_grid.direction)


def resample_to_grid(
    img: torch.Tensor,
    in_grid: Grid,
    grid: Grid,
    mode: str = "bilinear",
    padding_mode: str = "zeros",
    padding_value: PaddingValue = -1000.0,
    antialias: bool = True,
    matrix: np.ndarray | None = None,
) -> torch.Tensor:
    """The resampling of :class:`ResampleToNetworkGrid` on a plain tensor: ``[C, x, y, z]`` on ``in_grid`` ->
    ``[C, *grid.size]`` (crop to what ``grid`` covers, anti-alias with ``"bilinear"``, sample physically).

    ``matrix``: optional 4x4 physical transform, ``grid`` point -> ``in_grid`` point (LPS mm; fixed -> moving when
    ``img`` is the moving image): ``out(y) = img(matrix @ y)``, one interpolation (default identity).
    ``img`` may be a non-contiguous view (e.g. a transposed ``SimpleITK`` array): only the cropped part is copied.
    """
    # only the part of the input the grid covers is filtered and sampled (a 256^3 CT for a 128 mm network grid:
    # about 8x less smoothing work); the margin covers the Gaussian's truncation radius (4 sigma)
    sample_grid = in_grid
    if antialias and mode == "bilinear":
        margin = int(np.ceil(4.0 * max(antialias_sigmas(in_grid, grid)))) + 1
        img, sample_grid = crop_to_grid(img, in_grid, grid, margin, matrix)
        img = antialias_for_grid(img, sample_grid, grid)
    return resample_physical(img, np.eye(4) if matrix is None else matrix, grid, sample_grid, mode, padding_mode,
                             padding_value)


def sitk_tensor(image: sitk.Image) -> tuple[torch.Tensor, Grid]:
    """``[1, x, y, z]`` float32 tensor of a SimpleITK image and its grid: the ``[z, y, x]`` array viewed as
    ``[x, y, z]`` without a copy, so :func:`resample_to_grid` transposes only the part a smaller grid covers."""
    if image.GetPixelID() != sitk.sitkFloat32:
        image = sitk.Cast(image, sitk.sitkFloat32)
    return torch.from_numpy(sitk.GetArrayFromImage(image)).permute(2, 1, 0)[None], Grid.from_sitk(image)


def sitk_on_grid(image: sitk.Image, grid: Grid, mode: str = "bilinear", padding_value: PaddingValue = -1000.0,
                 antialias: bool = True, matrix: np.ndarray | None = None) -> torch.Tensor:
    """``[1, *grid.size]`` float32 plain tensor of a SimpleITK image resampled onto ``grid`` by
    :func:`resample_to_grid` (anti-aliased only with ``"bilinear"``; ``matrix``: grid point -> image point, LPS mm)."""
    raw, in_grid = sitk_tensor(image)
    return resample_to_grid(raw, in_grid, grid, mode, "zeros", padding_value,
                            antialias=antialias and mode == "bilinear", matrix=matrix)


def normalize_hu(img: torch.Tensor, a_min: float = -1000.0, a_max: float = 2000.0, b_min: float = 0.0,
                 b_max: float = 1.0, clip: bool = True) -> torch.Tensor:
    """Linear map of ``[a_min, a_max]`` HU onto ``[b_min, b_max]`` (clipped by default), any shape, dtype kept:
    the arithmetic of MONAI's ``ScaleIntensityRange`` (:class:`~monai_rigidreg.transforms.NormalizeHU`), which
    ``tests/test_grid_sampling.py`` checks value for value.

    Raises:
        ValueError: when ``a_max == a_min``.
    """
    if a_max == a_min:
        raise ValueError(f"a_max must differ from a_min, got {a_min}")
    out = (img - a_min) / (a_max - a_min) * (b_max - b_min) + b_min
    return out.clamp(b_min, b_max) if clip else out
