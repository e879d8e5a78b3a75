"""The feature maps that the Gauss-Newton stages align (the network's fine stage and the last level): the intensity,
its local contrast (optionally normalised by its own local strength) and its gradient magnitude."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from monai_rigidreg.core.image_ops import gradient_magnitude, local_mean

__all__ = ["CONTRAST_NORM_FLOOR", "CONTRAST_NORM_SCALE", "alignment_features"]

CONTRAST_NORM_SCALE = 0.05
"""The normalised local contrast's scale: about the plain local contrast's on soft tissue (normalised intensities),
so that the intensity channel, where kept, weighs about as before."""
CONTRAST_NORM_FLOOR = 1e-2
"""The root mean square of local contrast below which it is not amplified (flat regions stay flat, noise is not
raised to edge strength)."""


def alignment_features(
    volume: torch.Tensor,
    spacing: Sequence[float],
    support_threshold: float = 1e-3,
    highpass_sigma_mm: float = 16.0,
    highpass_weight: float = 3.0,
    gradient_weight: float = 0.0,
    contrast_norm_sigma_mm: float | None = None,
    intensity_weight: float = 1.0,
) -> torch.Tensor:
    """Contrast-robust feature maps for the Gauss-Newton stage: ``[N, C, x, y, z]`` -> ``[N, C * k, x, y, z]``.

    The channels are the input intensity, ``highpass_weight`` times its local contrast (the intensity minus its
    Gaussian mean over the voxels that hold data, a normalized convolution, so the CBCT field-of-view edge and the
    air around the body do not leak in) and, optionally, ``gradient_weight`` times its gradient magnitude (per voxel
    step; off by default: it did not add accuracy on top of the local contrast); a weight of 0 drops that channel.

    Why: aligning raw intensities pulls the estimate towards matching the CBCT's low-frequency errors (scatter
    cupping, beam hardening) with the CT. ``benchmarks/ablation/bench_alignment_features.py`` measures the choice on a
    paper-protocol set (64^3 grid at 2 mm): on the bundle's validation cases the mean TRE drops from about 2.6 mm
    with intensities alone to about 0.6 mm with the local-contrast channel at the defaults (0.4 mm with the
    network's 8 mm support erosion).

    With ``contrast_norm_sigma_mm`` the local contrast is divided by its own root mean square over a Gaussian of that
    sigma (times :data:`CONTRAST_NORM_SCALE`, floored at :data:`CONTRAST_NORM_FLOOR`): a CBCT whose contrast varies
    smoothly across the body (scatter and beam-hardening shading of a large body) then matches the CT's edges where
    they are rather than where the gain ratio moves them (``benchmarks/accuracy/bench_polish_bias.py``, rows
    ``gain-norm``; off by default).

    Args:
        volume: ``[N, C, x, y, z]`` normalized volumes (0 = no data / air).
        spacing: grid spacing in mm (converts ``highpass_sigma_mm`` to voxels).
        support_threshold: intensity above which a voxel holds data.
        highpass_sigma_mm: Gaussian sigma of the local mean (mm).
        highpass_weight, gradient_weight: channel weights.
        contrast_norm_sigma_mm: Gaussian sigma (mm) of the local contrast's normalisation (``None``: none).
        intensity_weight: weight of the intensity channel (0 drops it).

    Example:
        >>> import torch
        >>> v = torch.rand(1, 1, 16, 16, 16)
        >>> alignment_features(v, (2.0, 2.0, 2.0)).shape
        torch.Size([1, 2, 16, 16, 16])
        >>> alignment_features(v, (2.0, 2.0, 2.0), contrast_norm_sigma_mm=12.0, intensity_weight=0.0).shape
        torch.Size([1, 1, 16, 16, 16])
    """
    out = [] if intensity_weight == 0 else [volume if intensity_weight == 1 else intensity_weight * volume]
    if highpass_weight != 0:
        mask = (volume > support_threshold).to(volume.dtype)
        mean = local_mean(volume, mask, [float(highpass_sigma_mm) / float(s) for s in spacing])
        contrast = (volume - mean) * mask
        if contrast_norm_sigma_mm is not None:
            power = local_mean(contrast * contrast, mask, [float(contrast_norm_sigma_mm) / float(s) for s in spacing])
            contrast = CONTRAST_NORM_SCALE * contrast / torch.sqrt(power.clamp_min(0) + CONTRAST_NORM_FLOOR**2) * mask
        out.append(highpass_weight * contrast)
    if gradient_weight != 0:
        out.append(gradient_weight * gradient_magnitude(volume, eps=1e-6))
    return torch.cat(out, 1)
