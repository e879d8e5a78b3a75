"""Analytic reconstruction: FDK for the cone beam (CBCT) and slice-by-slice fan-beam FBP (the planning CT).

Both follow Kak & Slaney (Principles of Computerized Tomographic Imaging, ch. 3) for a flat detector, with the
detector rescaled to the isocentre (pitch ``du * sod / sdd``):

1. cosine weights ``sdd / sqrt(sdd^2 + u^2 + v^2)`` (``v = 0`` for the fan beam);
2. a ramp filter along the detector rows built from the *spatial* Ram-Lak kernel ``h[0] = 1 / (4 tau^2)``,
   ``h[n odd] = -1 / (pi n tau)^2``, ``h[n even] = 0`` with zero padding to at least twice the row length
   (no DC bias, no wrap-around), optionally apodized by a window;
3. back projection with the distance weight ``(sod / U)^2`` and the scaling ``pi / N`` (``delta beta / 2``
   for a full 360 degree scan of ``N`` views).

The result is the linear attenuation coefficient in 1/mm.
"""

from __future__ import annotations

import math

import torch

from monai_rigidreg.core.device import resolve_device
from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.simulation.projector import cone_backproject, fan_backproject
from monai_rigidreg.simulation.scanner import ConeBeamGeometry, FanBeamGeometry

__all__ = ["FILTERS", "padded_length", "ramp_filter_response", "ramp_filter", "fdk", "fbp_fan"]

FILTERS: tuple[str, ...] = ("ram-lak", "shepp-logan", "cosine", "hann", "hamming")
"""Names of the filter windows (``"ramp"`` is an alias of ``"ram-lak"``)."""


def padded_length(num_pixels: int) -> int:
    """Length of the zero-padded rows for the FFT: the smallest ``P >= 2 nu`` with no prime factor above 5.

    ``P >= 2 nu`` (``P`` even) keeps every tap ``|n| < nu`` of the spatial kernel that a row of ``nu`` pixels
    uses, so the circular convolution equals the linear one on the row for any such ``P``; a 5-smooth length is as
    fast for the FFT as a power of two and often much shorter (280 pixels: 576 instead of 1024).
    """
    p = max(2 * int(num_pixels), 2)
    while True:
        m = p
        for f in (2, 3, 5):
            while m % f == 0:
                m //= f
        if m == 1:
            return p
        p += 2


def ramp_filter_response(
    num_pixels: int, spacing: float, window: str = "ram-lak", device: str | torch.device | None = "cpu"
) -> tuple[torch.Tensor, int]:
    """Frequency response of the apodized ramp filter for ``torch.fft.rfft`` of zero-padded rows.

    Args:
        num_pixels: row length ``nu``.
        spacing: detector pitch at the isocentre ``tau`` (mm).
        window: one of :data:`FILTERS`.
        device: torch device.

    Returns:
        ``(response [P // 2 + 1] float32, P)``, ``P`` the padded length (:func:`padded_length`); the response
        includes the factor ``tau`` of the discrete convolution, so filtered rows are in 1/mm per unit input.
    """
    name = "ram-lak" if window == "ramp" else str(window).lower()
    if name not in FILTERS:
        raise ValueError(f"unknown filter window {window!r}; choose one of {FILTERS}")
    p = padded_length(num_pixels)
    n = torch.arange(p, dtype=torch.float64, device=device)
    n = torch.where(n < p // 2, n, n - p)
    h = torch.zeros(p, dtype=torch.float64, device=device)
    h[n == 0] = 1.0 / (4.0 * spacing**2)
    odd = n.remainder(2) == 1
    h[odd] = -1.0 / (math.pi * n[odd] * spacing) ** 2
    resp = torch.fft.rfft(h).real * spacing
    fn = torch.fft.rfftfreq(p, device=device, dtype=torch.float64) / 0.5  # frequency / Nyquist in [0, 1]
    if name == "shepp-logan":
        resp = resp * torch.sinc(fn / 2)
    elif name == "cosine":
        resp = resp * torch.cos(math.pi * fn / 2)
    elif name == "hann":
        resp = resp * (0.5 + 0.5 * torch.cos(math.pi * fn))
    elif name == "hamming":
        resp = resp * (0.54 + 0.46 * torch.cos(math.pi * fn))
    return resp.to(torch.float32), p


def ramp_filter(rows: torch.Tensor, spacing: float, window: str = "ram-lak") -> torch.Tensor:
    """Ramp-filter ``rows`` (``[..., nu]``) along the last axis (pitch ``spacing`` mm at the isocentre)."""
    nu = rows.shape[-1]
    resp, p = ramp_filter_response(nu, spacing, window, rows.device)
    spec = torch.fft.rfft(rows.to(torch.float32), n=p, dim=-1) * resp
    return torch.fft.irfft(spec, n=p, dim=-1)[..., :nu]


def _check_full_scan(arc: float) -> None:
    if abs(arc - 360.0) > 1e-6:
        raise NotImplementedError(
            f"reconstruction needs a full 360 degree scan (short-scan weights are not implemented), got arc={arc}"
        )


def fdk(
    projections: torch.Tensor,
    geometry: ConeBeamGeometry,
    grid: Grid,
    window: str = "ram-lak",
    device: str | torch.device | None = "auto",
    columns: torch.Tensor | None = None,
) -> torch.Tensor:
    """Feldkamp-Davis-Kress reconstruction of cone-beam line integrals.

    Args:
        projections: ``[num_views, nv, nu]`` line integrals (unitless).
        geometry: the complete :class:`ConeBeamGeometry` they were acquired with (full 360 degree arc).
        grid: output grid (axis-aligned, LPS mm, centred anywhere).
        window: filter window, one of :data:`FILTERS`.
        device: ``"cpu"``, ``"cuda"`` or ``"auto"``.
        columns: ``[nx, ny]`` bool, the voxel columns to reconstruct (``None``: all; the others are 0), e.g.
            ``fov_mask(...).any(2)`` when the result is masked to the field of view anyway
            (:func:`~monai_rigidreg.simulation.projector.cone_backproject`).

    Returns:
        ``[nx, ny, nz]`` float32 linear attenuation (1/mm) on ``device``.
    """
    _check_full_scan(geometry.arc)
    dev = resolve_device(device)
    u = geometry.u_coords(dev)[None, :]
    v = geometry.v_coords(dev)[:, None]
    cosw = (geometry.sdd / torch.sqrt(geometry.sdd**2 + u**2 + v**2)).to(torch.float32)
    iso_pitch = geometry.pixel_pitch[0] / geometry.magnification  # type: ignore[index]
    filtered = ramp_filter(projections.to(dev) * cosw, iso_pitch, window)
    return cone_backproject(filtered, grid, geometry, dev, columns=columns) * (math.pi / geometry.num_views)


def fbp_fan(
    sinogram: torch.Tensor,
    geometry: FanBeamGeometry,
    grid: Grid,
    window: str = "ram-lak",
    device: str | torch.device | None = "auto",
    fov_only: bool = True,
) -> torch.Tensor:
    """Slice-by-slice fan-beam filtered back projection (flat detector).

    Args:
        sinogram: ``[num_views, nz, nu]`` line integrals, detector row ``k`` belonging to slice ``k`` of ``grid``.
        geometry: the complete :class:`FanBeamGeometry` (full 360 degree arc).
        grid: output grid.
        window: filter window, one of :data:`FILTERS`.
        device: ``"cpu"``, ``"cuda"`` or ``"auto"``.
        fov_only: reconstruct only inside the field of view every view sees (:meth:`FanBeamGeometry.fov_radius`;
            :meth:`FanBeamGeometry.fitted` sizes it to hold the object) and leave 0 outside (``False``:
            the incomplete-data values there).

    Returns:
        ``[nx, ny, nz]`` float32 linear attenuation (1/mm).
    """
    _check_full_scan(geometry.arc)
    dev = resolve_device(device)
    u = geometry.u_coords(dev)[None, None, :]
    cosw = (geometry.sdd / torch.sqrt(geometry.sdd**2 + u**2)).to(torch.float32)
    iso_pitch = float(geometry.pixel_pitch) / geometry.magnification  # type: ignore[arg-type]
    filtered = ramp_filter(sinogram.to(dev) * cosw, iso_pitch, window)
    return fan_backproject(filtered, grid, geometry, dev, fov_only=fov_only) * (math.pi / geometry.num_views)
