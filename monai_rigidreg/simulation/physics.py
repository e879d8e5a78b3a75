"""CBCT physics in the projection domain: beam hardening, scatter, quantum and electronic noise, truncation.

The chain applied by :func:`apply_cbct_physics` to ideal (monochromatic) line integrals ``p``:

1. beam hardening: ``p_bh = p - beam_hardening * p^2`` (a one-term polynomial of the polychromatic
   log signal, as a water correction that leaves bone uncorrected would give); cupping, dark streaks;
2. primary signal ``I_p = I0 exp(-p_bh)`` photons per detector pixel (``I0`` raised for a thick patient where the
   automatic exposure control is on: :func:`effective_photons`);
3. scatter ``I_s``: the primary signal blurred by a wide Gaussian (``scatter_sigma_mm`` on the detector),
   scaled so that the scatter-to-primary ratio behind the object centre is ``scatter_to_primary``
   (low frequency; lowers contrast and adds cupping since the scanner does not subtract it);
4. quantum noise ``Poisson(I_p + I_s)`` and electronic noise ``Normal(0, electronic_noise)`` photons;
5. log transform ``-log(max(I, 1) / I0)``;
6. truncation: detector columns outside ``detector_fraction`` of the width are cut (set to zero, a hard
   transaxial truncation) if asked.

A smaller reconstructed field of view (``fov_diameter_mm``) is applied in the image domain (the
reconstruction is masked to a cylinder; :func:`fov_mask` gives the mask).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import torch

from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.core.image_ops import gaussian_kernel_1d, separable_filter
from monai_rigidreg.simulation.projector import grid_axes
from monai_rigidreg.simulation.scanner import ConeBeamGeometry

__all__ = ["CBCTPhysics", "apply_cbct_physics", "centre_line_integral", "effective_photons", "fov_mask"]


@dataclass(frozen=True)
class CBCTPhysics:
    """Degradations of the CBCT, in physical units with realistic defaults (an on-board kV imager).

    Args:
        photons: unattenuated photon count per detector pixel ``I0`` (photons / pixel / view); ``0`` or
            ``None`` disables quantum noise. Default ``1e5``.
        electronic_noise: standard deviation of the additive electronic noise in photon equivalents per pixel
            (default 10).
        scatter_to_primary: scatter-to-primary ratio behind the object centre (unitless; 0 disables scatter;
            default 0.3, a CBCT with an anti-scatter grid).
        scatter_sigma_mm: width (Gaussian standard deviation) of the scatter kernel on the detector, mm
            (default 60 mm: scatter is low frequency).
        beam_hardening: coefficient ``b`` of ``p - b p^2`` (unitless per unit line integral; 0 disables;
            default 0.01, about 6 % signal loss through 30 cm of water).
        detector_fraction: fraction of the detector width kept around its centre (1 = no truncation);
            less truncates the projections on purpose.
        fov_diameter_mm: diameter of the reconstructed cylindrical field of view, mm (``None``: what the
            detector sees); voxels outside are set to air.
        exposure_reference: automatic exposure control (``None``: off, the default). The line integral through the
            isocentre (median over the views of the detector's centre pixel) above which the exposure is raised:
            ``I0 = photons * exp(max(0, p_centre - exposure_reference))``, so that a patient thicker than the
            reference keeps the reference's primary signal behind the isocentre, as a clinic's pelvis protocol
            gives a large patient more dose (6.5 is about 325 mm of water). Never lowered below ``photons``.
    """

    photons: float | None = 1e5
    electronic_noise: float = 10.0
    scatter_to_primary: float = 0.3
    scatter_sigma_mm: float = 60.0
    beam_hardening: float = 0.01
    detector_fraction: float = 1.0
    fov_diameter_mm: float | None = None
    exposure_reference: float | None = None

    def __post_init__(self) -> None:
        if self.photons is not None and self.photons < 0:
            raise ValueError(f"photons must be >= 0, got {self.photons}")
        for name in ("electronic_noise", "scatter_to_primary", "beam_hardening"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.scatter_sigma_mm <= 0:
            raise ValueError(f"scatter_sigma_mm must be > 0, got {self.scatter_sigma_mm}")
        if not (0 < self.detector_fraction <= 1):
            raise ValueError(f"detector_fraction must be in (0, 1], got {self.detector_fraction}")
        if self.fov_diameter_mm is not None and self.fov_diameter_mm <= 0:
            raise ValueError(f"fov_diameter_mm must be > 0, got {self.fov_diameter_mm}")
        if self.exposure_reference is not None and self.exposure_reference < 0:
            raise ValueError(f"exposure_reference must be >= 0, got {self.exposure_reference}")

    @classmethod
    def ideal(cls) -> CBCTPhysics:
        """No degradation at all (noise-free monochromatic projections)."""
        return cls(photons=None, electronic_noise=0.0, scatter_to_primary=0.0, beam_hardening=0.0)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (for JSON)."""
        return asdict(self)


def apply_cbct_physics(
    line_integrals: torch.Tensor,
    geometry: ConeBeamGeometry,
    physics: CBCTPhysics,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Degrade ideal cone-beam line integrals as the scanner would measure them.

    Args:
        line_integrals: ``[num_views, nv, nu]`` ideal line integrals (unitless).
        geometry: the complete acquisition geometry (for the pixel pitch of the scatter kernel).
        physics: the degradations.
        generator: random generator on the device of ``line_integrals`` (reproducible noise).

    Returns:
        ``[num_views, nv, nu]`` float32 measured line integrals ``-log(I / I0)``.
    """
    p = line_integrals.to(torch.float32)
    i0 = effective_photons(p, physics)
    if physics.beam_hardening > 0:
        p = p - physics.beam_hardening * p * p
    nu = p.shape[-1]
    if physics.photons or physics.scatter_to_primary > 0 or physics.electronic_noise > 0:
        primary = i0 * torch.exp(-p)
        total = primary
        if physics.scatter_to_primary > 0:
            du, dv = geometry.pixel_pitch  # type: ignore[misc]
            # separable sampled Gaussian (radius ceil(3 sigma) pixels, normalized), edges replicated: the detector
            # signal continues smoothly. As dense matrix products: the kernel (~120 taps) is nearly as long as the
            # detector axes (benchmarks/speed/bench_gaussian.py, the [360, 128, 128] replicate table's matrix column)
            kernels = [
                gaussian_kernel_1d(s, approx="sampled", normalize=True, size=2 * math.ceil(3 * s) + 1,
                                   dtype=primary.dtype, device=primary.device)
                for s in (physics.scatter_sigma_mm / dv, physics.scatter_sigma_mm / du)
            ]
            blurred = separable_filter(primary, kernels, padding="replicate", method="matrix")
            nv = p.shape[1]
            cv, cu = (
                slice(nv // 2 - nv // 16, nv // 2 + nv // 16 + 1),
                slice(nu // 2 - nu // 16, nu // 2 + nu // 16 + 1),
            )
            # scale per view so that scatter / primary = SPR at the centre of the object shadow
            ratio = blurred[:, cv, cu].mean((1, 2)) / primary[:, cv, cu].mean((1, 2)).clamp_min(1e-6)
            scale = physics.scatter_to_primary / ratio.clamp_min(1e-6)
            total = primary + blurred * scale.view(-1, 1, 1)
        if physics.photons:
            total = torch.poisson(total, generator=generator)
        if physics.electronic_noise > 0:
            noise = torch.randn(total.shape, generator=generator, device=total.device, dtype=total.dtype)
            total = total + physics.electronic_noise * noise
        p = -torch.log(total.clamp_min(1.0) / i0)
    if physics.detector_fraction < 1:
        keep = max(2, int(round(nu * physics.detector_fraction)))
        lo = (nu - keep) // 2
        mask = torch.zeros(nu, dtype=p.dtype, device=p.device)
        mask[lo : lo + keep] = 1
        p = p * mask
    return p


def effective_photons(line_integrals: torch.Tensor, physics: CBCTPhysics) -> float:
    """The unattenuated photon count per pixel and view that :func:`apply_cbct_physics` uses for these projections:
    ``physics.photons`` (``1e5`` where it is ``None`` or 0: the scale of scatter and electronic noise), raised by the
    automatic exposure control where ``physics.exposure_reference`` is set (see :class:`CBCTPhysics`).

    Args:
        line_integrals: ``[num_views, nv, nu]`` ideal line integrals (unitless; the detector's centre pixel sees
            the ray through the isocentre).

    >>> import torch
    >>> p = torch.full((4, 3, 3), 8.5)
    >>> round(effective_photons(p, CBCTPhysics(photons=1e4, exposure_reference=6.5)))
    73891
    >>> effective_photons(p, CBCTPhysics(photons=1e4))
    10000.0
    """
    i0 = float(physics.photons) if physics.photons else 1e5
    if physics.exposure_reference is not None and physics.photons:
        i0 *= math.exp(max(0.0, centre_line_integral(line_integrals) - float(physics.exposure_reference)))
    return i0


def centre_line_integral(line_integrals: torch.Tensor) -> float:
    """The median over the views of the detector's centre pixel, ``[num_views, nv, nu]`` -> unitless: how thick the
    patient is along the ray through the isocentre (about 0.02 per mm of water)."""
    nv, nu = line_integrals.shape[-2:]
    return float(line_integrals[:, nv // 2, nu // 2].float().median())


def fov_mask(
    grid: Grid, geometry: ConeBeamGeometry, physics: CBCTPhysics | None = None, device: str | torch.device = "cpu"
) -> torch.Tensor:
    """Field of view of a CBCT reconstruction: voxels every view sees, inside ``fov_diameter_mm``.

    Transaxially a cylinder of radius ``geometry.fov_radius()`` (reduced by ``detector_fraction`` and by
    ``fov_diameter_mm``); axially, ``|z| <= v_max (sod - rho) / sdd`` at distance ``rho`` from the axis (the
    cone covers less near the source).

    Returns:
        ``[nx, ny, nz]`` bool tensor.
    """
    xs, ys, zs = grid_axes(grid, device)
    u = geometry.u_coords()
    v = geometry.v_coords()
    du = geometry.pixel_pitch[0]  # type: ignore[index]
    half_u = float(min(-u[0], u[-1])) + du / 2
    if physics is not None and physics.detector_fraction < 1:
        nu = u.numel()
        keep = max(2, int(round(nu * physics.detector_fraction)))
        half_u = min(half_u, keep * du / 2 - abs(geometry.detector_offset[0]))
    radius = geometry.radius_seen(half_u)
    if physics is not None and physics.fov_diameter_mm is not None:
        radius = min(radius, physics.fov_diameter_mm / 2)
    half_v = float(min(-v[0], v[-1])) + geometry.pixel_pitch[1] / 2  # type: ignore[index]
    rho = torch.sqrt(xs[:, None] ** 2 + ys[None, :] ** 2)  # [nx, ny]
    zmax = half_v * (geometry.sod - rho) / geometry.sdd
    inside = (rho <= radius)[:, :, None] & (zs.abs()[None, None, :] <= zmax[:, :, None])
    return inside
