"""General image operations used by several packages (transforms, simulation, losses, networks, registration).

One Gaussian kernel builder (:func:`gaussian_kernel_1d`), one separable filter over the last axes of any tensor
(:func:`separable_filter`) and the Gaussian smoothing built on them (:func:`gaussian_smooth`), the normalized
convolution :func:`local_mean`, the box erosion :func:`erode`, :func:`gradient_magnitude`, the average-pooling
:func:`pyramid` and the masked global correlation :func:`masked_ncc`.

This module depends on torch, numpy and :mod:`monai_rigidreg.core.geometry` only: never on the networks, the losses or
the registrar, so any of those can use it, and not on MONAI, because the register path imports it (see
:mod:`monai_rigidreg.core.grid_sampling`). Every operation is differentiable with respect to its image
inputs; kernels follow the dtype and device of the input (the speed measurements are CPU ones).

Sizes and units: sigmas and radii are in voxels (pixels) of the axis they act on; shapes are given per function.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F

from monai_rigidreg.core.geometry import Grid

__all__ = [
    "SHIFTED_SUM_MAX_TAPS",
    "broadcast_mask",
    "erode",
    "gaussian_kernel_1d",
    "gaussian_smooth",
    "gradient_magnitude",
    "local_mean",
    "masked_ncc",
    "pyramid",
    "separable_filter",
    "subvoxel_peaks",
]

Padding = Literal["zeros", "replicate", "valid"]
Method = Literal["auto", "shifted", "conv", "matrix"]

SHIFTED_SUM_MAX_TAPS: int = 301
"""Longest kernel (taps) that :func:`separable_filter` applies as a weighted sum of shifted views when
``method="auto"``; longer kernels are applied by a 1-D convolution.

Measured by ``benchmarks/speed/bench_gaussian.py`` (2 CPU threads, quiet machine; ms, shifted / conv):
``[1, 136, 136, 136]`` zero padding, three axes: 6 / 137 at 3 taps, 23 / 154 at 17, 228 / 296 at 181, 318 / 359
at 257, 467 / 385 at 361; ``[360, 128, 128]`` replicate padding, two axes: 23 / 230 at 3 taps, 400 / 494 at 181 (the
CBCT scatter kernel), 568 / 587 at 257, 774 / 732 at 361. The convolution's fixed cost (about 0.13-0.23 s here) only
pays off beyond about 300 taps; with backward (the SSIM loss, 7 taps) the shifted sum is 7x faster too. On an
oversubscribed CPU (more runnable processes than cores) the shifted sum's many short multi-threaded operations
suffer most and the convolution can win from about 30 taps: the benchmark prints the load average.
"""

_MODES = ("zeros", "replicate", "valid")


def _erf_taps(sigma32: torch.Tensor, tail: int) -> torch.Tensor:
    """``[2 * tail + 1]`` float32 Gaussian mass of the unit intervals about the integer offsets ``-tail..tail``:
    the arithmetic of MONAI's ``gaussian_1d(approx="erf")`` (checked value for value in ``tests/test_image_ops.py``),
    written here so that the register path does not import MONAI (see :mod:`monai_rigidreg.core.grid_sampling`)."""
    x = torch.arange(-tail, tail + 1, dtype=torch.float32)
    t = 0.70710678 / torch.abs(sigma32)
    return (0.5 * ((t * (x + 0.5)).erf() - (t * (x - 0.5)).erf())).clamp(min=0)


def gaussian_kernel_1d(
    sigma: float,
    truncated: float = 4.0,
    approx: Literal["erf", "sampled"] = "erf",
    normalize: bool = False,
    size: int | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """A 1-D Gaussian kernel of standard deviation ``sigma`` (voxels), centred, ``[size]``.

    Args:
        sigma: standard deviation in voxels (> 0).
        truncated: half-width in sigmas when ``size`` is not given: ``tail = round(max(sigma * truncated, 0.5))``
            taps each side (MONAI's rule), so ``2 * tail + 1`` taps.
        approx: ``"erf"``: MONAI's ``monai.networks.layers.convutils.gaussian_1d(approx="erf")`` (the Gaussian
            mass of each unit interval, computed in float32 then cast to ``dtype``), what MONAI's
            ``GaussianFilter`` / ``GaussianSmooth`` use; ``"sampled"``: ``exp(-x^2 / (2 sigma^2))`` at the tap
            offsets, computed in ``dtype`` (divided by ``sqrt(2 pi) sigma`` unless normalized), as MONAI's SSIM.
        normalize: divide by the sum (the kernel then keeps the mean of the signal).
        size: number of taps, overriding ``truncated``; the taps sit at offsets ``i - (size - 1) / 2``, so an even
            size (``"sampled"`` only) has half-integer offsets (a ``padding="valid"`` window like MONAI's SSIM).
        dtype, device: of the returned kernel.

    Returns:
        ``[size]`` (``[2 * tail + 1]``) kernel weights (dimensionless).
    """
    sigma = float(sigma)
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    if size is not None and int(size) < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    if approx == "erf":
        sigma32 = torch.tensor(sigma, dtype=torch.float32)
        if size is None:
            if not truncated > 0:
                raise ValueError(f"truncated must be > 0, got {truncated}")
            kernel = _erf_taps(sigma32, int(max(float(sigma32) * truncated, 0.5) + 0.5))
            kernel = kernel / kernel.sum() if normalize else kernel
        elif int(size) % 2 == 0:
            raise ValueError(f"an 'erf' kernel has an odd size, got {size}")
        else:
            # MONAI's tail is round(sigma * truncated): ask for the radius we want (at least 1, see below)
            radius = max(1, (int(size) - 1) // 2)
            kernel = _erf_taps(sigma32, radius)
            if int(size) == 1:  # the central tap only
                kernel = kernel[1:2]
            kernel = kernel / kernel.sum() if normalize else kernel
        return kernel.to(dtype=dtype, device=device)
    if approx != "sampled":
        raise ValueError(f"approx must be 'erf' or 'sampled', got {approx!r}")
    n = 2 * int(max(sigma * truncated, 0.5) + 0.5) + 1 if size is None else int(size)
    dist = torch.arange(n, dtype=dtype, device=device) - (n - 1) / 2.0
    kernel = torch.exp(-0.5 * (dist / sigma) ** 2)
    return kernel / kernel.sum() if normalize else kernel / (math.sqrt(2.0 * math.pi) * sigma)


def _as_3d(x: torch.Tensor, dim: int) -> torch.Tensor:
    """``x`` as ``[before, n, after]`` with ``dim`` in the middle (a view when the layout allows)."""
    return x.reshape(math.prod(x.shape[:dim]), x.shape[dim], math.prod(x.shape[dim + 1 :]))


def _pad_3d(x3: torch.Tensor, before: int, after: int, padding: str) -> torch.Tensor:
    """Pad the middle axis of ``[P, n, Q]``."""
    if padding == "valid" or before == after == 0:
        return x3
    if padding == "zeros":
        return F.pad(x3, (0, 0, before, after))
    return F.pad(x3[:, None], (0, 0, before, after), mode="replicate")[:, 0]


def _filter_axis_shifted(x3: torch.Tensor, kernel: torch.Tensor, padding: str) -> torch.Tensor:
    """Correlate the middle axis of ``[P, n, Q]`` with ``kernel``: a weighted sum of shifted views."""
    k = kernel.numel()
    r = (k - 1) // 2
    padded = _pad_3d(x3, r, k - 1 - r, padding)
    n = padded.shape[1] - k + 1
    out = padded.narrow(1, 0, n) * kernel[0]
    for i in range(1, k):
        out.addcmul_(padded.narrow(1, i, n), kernel[i])
    return out


def _filter_axis_conv(x3: torch.Tensor, kernel: torch.Tensor, padding: str) -> torch.Tensor:
    """Correlate the middle axis of ``[P, n, Q]`` with ``kernel``: one single-channel ``conv1d`` / ``conv2d``."""
    k = kernel.numel()
    r = (k - 1) // 2
    pad = r if padding == "zeros" else 0
    if padding == "replicate":
        x3 = _pad_3d(x3, r, k - 1 - r, padding)
    if x3.shape[2] == 1:  # the last axis: a batch of 1-D signals
        return F.conv1d(x3.reshape(x3.shape[0], 1, x3.shape[1]), kernel.view(1, 1, k), padding=pad)[:, 0, :, None]
    return F.conv2d(x3[:, None], kernel.view(1, 1, k, 1), padding=(pad, 0))[:, 0]


def _filter_axis_matrix(x3: torch.Tensor, kernel: torch.Tensor, padding: str) -> torch.Tensor:
    """Correlate the middle axis of ``[P, n, Q]`` with ``kernel``: one matrix product with the dense ``[n_out, n]``
    filter matrix (the padding folded into it: a replicated edge adds its taps to the edge column)."""
    k, n = kernel.numel(), x3.shape[1]
    r = 0 if padding == "valid" else (k - 1) // 2
    n_out = n - k + 1 if padding == "valid" else n
    rows = torch.arange(n_out, device=x3.device)[:, None].expand(n_out, k)
    cols = rows + torch.arange(k, device=x3.device)[None, :] - r
    taps = kernel[None, :].expand(n_out, k)
    if padding == "replicate":
        cols = cols.clamp(0, n - 1)
    else:  # zeros (valid never leaves the axis)
        inside = (cols >= 0) & (cols < n)
        rows, cols, taps = rows[inside], cols[inside], taps[inside]
    mat = torch.zeros(n_out, n, dtype=x3.dtype, device=x3.device)
    mat.index_put_((rows.reshape(-1), cols.reshape(-1)), taps.reshape(-1), accumulate=True)
    if x3.shape[2] == 1:  # the last axis: rows of x times the transposed matrix
        return (x3[:, :, 0] @ mat.T)[:, :, None]
    return torch.matmul(mat, x3)


def separable_filter(
    x: torch.Tensor,
    kernels: Sequence[torch.Tensor | None],
    padding: Padding = "zeros",
    method: Method = "auto",
) -> torch.Tensor:
    """Correlate the last ``len(kernels)`` axes of ``x`` with one 1-D kernel each (a separable filter).

    ``kernels[i]`` acts on axis ``x.ndim - len(kernels) + i`` (``None`` leaves that axis alone); the axes are
    filtered in order. Correlation, as MONAI's ``separable_filtering`` (the same as convolution for the symmetric
    Gaussians).

    Args:
        x: ``[..., n_1, ..., n_k]`` floating tensor, any leading axes (batch, channels), any layout.
        kernels: ``k`` 1-D kernels (cast to the dtype and device of ``x``) or ``None``.
        padding: ``"zeros"`` (outside is 0, MONAI's default), ``"replicate"`` (edge values continue) or
            ``"valid"`` (no padding: each filtered axis shrinks by ``len(kernel) - 1``, as ``conv`` without
            padding). ``"zeros"`` and ``"replicate"`` keep the shape and need odd kernels (centred).
        method: ``"shifted"``: a weighted sum of shifted views of the padded tensor (one memory pass per tap, no
            convolution set-up: fast for short kernels); ``"conv"``: a single-channel ``conv1d``/``conv2d`` of the
            axis; ``"matrix"``: one product with the dense ``[n, n]`` filter matrix of the axis (``n^2`` multiply-adds
            per line whatever the kernel's length: for kernels nearly as long as the axis, e.g. the CBCT scatter
            kernel); ``"auto"``: ``"shifted"`` up to :data:`SHIFTED_SUM_MAX_TAPS` taps, else ``"conv"`` (the
            crossover measured by ``benchmarks/speed/bench_gaussian.py``, forward and backward). All give the same
            result up to floating-point rounding.

    Returns:
        the filtered tensor, ``x``'s shape (``"valid"``: shrunk), dtype and device; ``x`` itself when every kernel
        is ``None``. Differentiable with respect to ``x`` (and the kernels).
    """
    if padding not in _MODES:
        raise ValueError(f"padding must be one of {_MODES}, got {padding!r}")
    if method not in ("auto", "shifted", "conv", "matrix"):
        raise ValueError(f"method must be 'auto', 'shifted', 'conv' or 'matrix', got {method!r}")
    if len(kernels) > x.ndim:
        raise ValueError(f"{len(kernels)} kernels for a {x.ndim}-d tensor")
    first = x.ndim - len(kernels)
    out = x
    for i, kernel in enumerate(kernels):
        if kernel is None:
            continue
        dim = first + i
        if kernel.ndim != 1 or kernel.numel() < 1:
            raise ValueError(f"kernel {i} must be a non-empty 1-D tensor, got shape {tuple(kernel.shape)}")
        k = kernel.numel()
        if padding != "valid" and k % 2 == 0:
            raise ValueError(f"padding={padding!r} needs odd (centred) kernels, kernel {i} has {k} taps")
        if padding == "valid" and k > out.shape[dim]:
            raise ValueError(f"kernel {i} ({k} taps) is longer than axis {dim} ({out.shape[dim]}) for 'valid'")
        kernel = kernel.to(dtype=out.dtype, device=out.device)
        use_conv = method == "conv" or (method == "auto" and k > SHIFTED_SUM_MAX_TAPS)
        filt = _filter_axis_matrix if method == "matrix" else _filter_axis_conv if use_conv else _filter_axis_shifted
        y3 = filt(_as_3d(out, dim), kernel, padding)
        out = y3.reshape(*out.shape[:dim], y3.shape[1], *out.shape[dim + 1 :])
    return out


def gaussian_smooth(
    x: torch.Tensor,
    sigmas: Sequence[float],
    truncated: float = 4.0,
    padding: Padding = "zeros",
    approx: Literal["erf", "sampled"] = "erf",
    normalize: bool = False,
    method: Method = "auto",
) -> torch.Tensor:
    """Separable Gaussian filter of the last ``len(sigmas)`` axes of ``x``, sigma in voxels per axis.

    With the defaults it is MONAI's ``GaussianSmooth(sigma)`` / ``GaussianFilter`` (the ``erf`` kernel of
    ``monai.networks.layers.convutils.gaussian_1d``, truncated at 4 sigma, not renormalized, zero padding), computed
    by :func:`separable_filter`: for the few-tap kernels of the network-grid anti-aliasing the shifted-view sum is
    more than 10x faster than MONAI's three single-channel ``conv3d`` passes on CPU
    (``benchmarks/speed/bench_gaussian.py``; ``benchmarks/speed/bench_inference_speed.py``: 0.004 s instead of 0.055 s
    on the 136^3 crop of a 1 mm CT, 2 cores).

    Args:
        x: ``[..., n_1, ..., n_k]`` floating tensor (e.g. ``[C, x, y, z]`` or ``[B, C, x, y, z]``).
        sigmas: ``k`` standard deviations in voxels; an axis with sigma <= 0 is left alone.
        truncated, approx, normalize: the kernel, see :func:`gaussian_kernel_1d`.
        padding, method: see :func:`separable_filter`.

    Returns:
        the smoothed tensor (``x``'s shape unless ``padding="valid"``); ``x`` itself when every sigma is <= 0.
    """
    kernels = [
        gaussian_kernel_1d(s, truncated, approx, normalize, dtype=x.dtype, device=x.device) if s > 0 else None
        for s in (float(v) for v in sigmas)
    ]
    return separable_filter(x, kernels, padding, method)


def local_mean(volume: torch.Tensor, mask: torch.Tensor, sigma_vox: Sequence[float]) -> torch.Tensor:
    """Gaussian-weighted mean of ``volume`` over ``mask`` (normalized convolution), sigma in voxels.

    ``G * (volume * mask) / max(G * mask, 1e-3)`` with ``G`` MONAI's ``GaussianFilter`` kernel (``erf``, truncated
    at 4 sigma, zero padding: :func:`gaussian_smooth`'s defaults). A smooth quantity, so it is computed on a grid
    average-pooled by up to 4 (``min(sigma_vox) // 2``, sigma >= 2 voxels there) and upsampled trilinearly: the
    filter then runs on up to 64x fewer voxels with a 4x shorter kernel.

    Args:
        volume: ``[N, C, x, y, z]``.
        mask: ``[N, 1 or C, x, y, z]`` weights in [0, 1] (1 where the volume holds data).
        sigma_vox: the three Gaussian sigmas (voxels of ``volume``).

    Returns:
        ``[N, C, x, y, z]`` local mean (``volume``'s units).
    """
    factor = max(1, min(4, int(min(sigma_vox) // 2)))
    num, den = volume * mask, mask
    if factor > 1:
        num, den = F.avg_pool3d(num, factor, ceil_mode=True), F.avg_pool3d(den, factor, ceil_mode=True)
    sigmas = [float(s) / factor for s in sigma_vox]
    mean = gaussian_smooth(num, sigmas) / gaussian_smooth(den, sigmas).clamp_min(1e-3)
    if factor > 1:
        mean = F.interpolate(mean, size=volume.shape[2:], mode="trilinear", align_corners=False)
    return mean


def erode(mask: torch.Tensor, radius: Sequence[int]) -> torch.Tensor:
    """Erosion of ``[B, C, x, y, z]`` masks (values in [0, 1]) by a box of half-widths ``radius`` voxels per axis.

    Separable 1-D min-filters; voxels outside the volume do not count (the border itself is not eroded). Each is
    the minimum over a sliding window (``unfold`` of the padded volume, a view, then ``amin``), faster than
    ``max_pool3d``, which computes argmax indices on the CPU (``benchmarks/speed/bench_network_paths.py``'s erosion
    row).
    """
    for axis, r in enumerate(radius):
        if r > 0:
            r = int(r)
            dim = 2 + axis
            # the volume's own edge planes repeated: they are in every border window, so the minimum is that of the
            # voxels inside (any dtype; a constant pad value goes through a float and wraps for int64)
            n = mask.shape[dim]
            first = mask.narrow(dim, 0, 1).expand(*mask.shape[:dim], r, *mask.shape[dim + 1:])
            last = mask.narrow(dim, n - 1, 1).expand(*mask.shape[:dim], r, *mask.shape[dim + 1:])
            mask = torch.cat([first, mask, last], dim).unfold(dim, 2 * r + 1, 1).amin(-1)
    return mask


def gradient_magnitude(volume: torch.Tensor, eps: float = 0.0) -> torch.Tensor:
    """Magnitude of the central-difference gradient over the last three axes (per voxel step).

    ``sqrt(sum_i g_i^2 + eps)``: with ``eps > 0`` it is differentiable at flat regions too.
    """
    grads = torch.gradient(volume, dim=(-3, -2, -1))
    return torch.sqrt(sum(g * g for g in grads) + eps)


def pyramid(volume: torch.Tensor, grid: Grid, factor: int) -> tuple[torch.Tensor, Grid]:
    """Average-pool ``volume`` by ``factor`` and return it with its grid (same centre)."""
    if factor == 1:
        return volume, grid
    pooled = F.avg_pool3d(volume, factor)
    g = Grid.centered(pooled.shape[2:], [s * factor for s in grid.spacing], grid.center())
    return pooled, g


def broadcast_mask(mask: torch.Tensor | None, ref: torch.Tensor) -> torch.Tensor | None:
    """A ``[B, 1 or C, x, y, z]`` mask as 0/1 weights (``mask > 0``) of ``ref``'s dtype, expanded to ``ref``'s
    ``[B, C, x, y, z]``; ``None`` stays ``None``. Raises ``ValueError`` when the shapes do not match."""
    if mask is None:
        return None
    if mask.shape[0] != ref.shape[0] or mask.shape[2:] != ref.shape[2:] or mask.shape[1] not in (1, ref.shape[1]):
        raise ValueError(f"mask {tuple(mask.shape)} does not match image {tuple(ref.shape)} (want [B, 1, x, y, z])")
    return (mask > 0).to(ref.dtype).expand_as(ref)


def masked_ncc(x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor | None = None, eps: float = 1e-8) -> torch.Tensor:
    """Global normalized cross-correlation (paper Eq. 3, Pearson correlation) over the voxels of ``mask``.

    Args:
        x, y: ``[B, C, x, y, z]``.
        mask: optional ``[B, 1, x, y, z]``; voxels where ``mask <= 0`` are ignored.

    Returns:
        ``[B]`` NCC in [-1, 1] (dimensionless), computed in float32 or wider.
    """
    dt = torch.promote_types(x.dtype, torch.float32)
    x, y = x.to(dt), y.to(dt)
    m = broadcast_mask(mask, x)
    w = torch.ones_like(x) if m is None else m
    n = w.flatten(1).sum(1).clamp_min(1.0)
    mx = (w * x).flatten(1).sum(1) / n
    my = (w * y).flatten(1).sum(1) / n
    dx = (x - mx.view(-1, 1, 1, 1, 1)) * w
    dy = (y - my.view(-1, 1, 1, 1, 1)) * w
    num = (dx * dy).flatten(1).sum(1)
    den = torch.sqrt((dx * dx).flatten(1).sum(1) * (dy * dy).flatten(1).sum(1) + eps)
    return num / den


def subvoxel_peaks(ncc: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The maximum of each of ``B`` score maps ``[B, X, Y, Z]`` (one per template: the global search's
    ``masked_ncc_map``, the region check's blocks) refined per axis by the vertex of the parabola through it and its
    two neighbours (offset clamped to half a sample; none at the map's border or where the three samples are not
    concave). Returns the refined indices ``[B, 3]`` (float64, index units of the map) and the maxima ``[B]``
    (float64), as numpy."""
    b, shape = ncc.shape[0], tuple(ncc.shape[1:])
    arg = ncc.reshape(b, -1).argmax(1)  # the first maximum of each map
    # the index by arithmetic: torch.unravel_index's argument check imports torch.fx's symbolic shapes and sympy
    # (0.24 s of a command's start-up, python -X importtime)
    idx = torch.stack([arg // (shape[1] * shape[2]), (arg // shape[2]) % shape[1], arg % shape[2]], 1)  # [B, 3]
    rows = torch.arange(b, device=ncc.device)
    peak = ncc[rows, idx[:, 0], idx[:, 1], idx[:, 2]].double()
    sub = idx.double()
    for ax in range(3):
        lo, hi = idx.clone(), idx.clone()
        lo[:, ax] = (idx[:, ax] - 1).clamp(0, shape[ax] - 1)
        hi[:, ax] = (idx[:, ax] + 1).clamp(0, shape[ax] - 1)
        cm = ncc[rows, lo[:, 0], lo[:, 1], lo[:, 2]].double()
        cp = ncc[rows, hi[:, 0], hi[:, 1], hi[:, 2]].double()
        den = cm - 2.0 * peak + cp
        use = (idx[:, ax] > 0) & (idx[:, ax] < shape[ax] - 1) & (den < -1e-9)
        off = (0.5 * (cm - cp) / torch.where(use, den, torch.full_like(den, -1.0))).clamp(-0.5, 0.5)
        sub[:, ax] += torch.where(use, off, torch.zeros_like(off))
    return sub.cpu().numpy(), peak.cpu().numpy()
