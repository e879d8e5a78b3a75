"""Image-domain CBCT degradation of a clean CT (``RandCBCTDegradation`` / ``RandCBCTDegradationd``).

Turns a CT in Hounsfield units (float) into something that looks like a clinical cone-beam CT. Every effect
has its own probability and range and is recorded. The geometry is never changed: same shape, same affine, no
``applied_operations`` entry (it is an intensity transform); registration ground truth keys are untouched.

Effects, in the order they are applied (``u = (HU + 1000) / 1000`` is the attenuation relative to water):

1. resolution loss: isotropic Gaussian blur of ``blur_sigma`` mm (per-axis voxels from the affine spacing), then
   optionally down-sampling by ``downsample_factor`` (area averaging) and up-sampling back (trilinear);
2. scatter: low-frequency multiplicative shading of the attenuation, ``u <- u * (1 + a * f)``, ``f`` a smooth
   random field in ``[-1, 1]`` (``scatter_control_points`` knots per axis), ``a = scatter_amplitude``;
3. cupping (beam hardening): ``u <- u * (1 - depth * max(0, 1 - (r / R)^2))``, ``r`` the distance (mm) to the
   volume's z axis (third array axis through the volume centre), ``R`` half the smaller in-plane extent (mm);
4. streaks: ``streak_count`` thin lines in axial planes, random angle and offset, amplitude +-``streak_amplitude``
   HU, Gaussian profile of ``streak_width`` mm (sd), over a random z slab;
5. rings: ``ring_count`` concentric rings about the volume z axis, random radii, amplitude +-``ring_amplitude`` HU,
   Gaussian profile of ``ring_width`` mm (sd);
6. quantum noise: Gaussian noise of variance following intensity,
   ``sd(HU) = noise_std * sqrt(noise_floor + max(u, 0))`` (``noise_std`` is the sd in HU at water for
   ``noise_floor = 0``), optionally correlated by a Gaussian of ``noise_correlation`` mm;
7. HU miscalibration: ``HU <- scale * (1000 * max(u, 0)^gamma - 1000) + offset`` (``gamma`` a mild non-linearity);
8. truncated field of view: a cylinder about the volume z axis of radius ``fov_radius`` mm (and optionally a
   half-length ``fov_half_length`` mm along z), soft edge (logistic, ``fov_edge`` mm); outside is ``background``.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from monai.config import KeysCollection
from monai.data.meta_obj import get_track_meta
from monai.transforms import MapTransform, RandomizableTransform
from monai.utils import convert_to_dst_type, convert_to_tensor

from monai_rigidreg.core.image_ops import gaussian_smooth
from monai_rigidreg.transforms.utils import ensure_interval, grid_of

__all__ = ["RandCBCTDegradation", "RandCBCTDegradationd", "CBCT_KEY", "CBCT_RECORD_KEYS"]

CBCT_KEY = "cbct_degradation"
"""Default key of the record written by :class:`RandCBCTDegradationd`."""

CBCT_RECORD_KEYS: tuple[str, ...] = (
    "blur",
    "blur_sigma",
    "downsample",
    "downsample_factor",
    "scatter",
    "scatter_amplitude",
    "cupping",
    "cupping_depth",
    "streaks",
    "streak_count",
    "streak_amplitude",
    "rings",
    "ring_count",
    "ring_amplitude",
    "noise",
    "noise_std",
    "hu",
    "hu_scale",
    "hu_offset",
    "hu_gamma",
    "fov",
    "fov_radius",
    "fov_edge",
    "fov_half_length",
    "seed",
)
"""Keys of the record (flat, fixed, so that it collates): a bool per effect (applied or not) and its values
(neutral values when not applied: 0, or 1 for factors/scales/gamma). ``seed`` seeds the detail draws (streak
angles, ring radii, shading knots, noise), so the record reproduces the output exactly on the same device."""


def _gaussian_blur(x: torch.Tensor, sigma_vox: Sequence[float]) -> torch.Tensor:
    """Separable Gaussian blur of ``[C, x, y, z]``; ``sigma_vox`` per spatial axis (voxels, < 0.05 skipped).

    MONAI's ``erf`` kernel truncated at 3 sigma, renormalized, replicate padding
    (:func:`~monai_rigidreg.core.image_ops.gaussian_smooth`).
    """
    sigmas = [float(s) if s >= 0.05 else 0.0 for s in sigma_vox]
    return gaussian_smooth(x, sigmas, truncated=3.0, padding="replicate", normalize=True)


class RandCBCTDegradation(RandomizableTransform):
    """Make a clean CT (HU, float, channel first ``[C, x, y, z]``) look like a clinical CBCT.

    See the module docstring for the model of each effect. Ranges are ``(low, high)`` (a number means a fixed
    value) and are drawn uniformly; counts are drawn as integers in ``[low, high]``. Every effect has its own
    probability; ``prob`` gates the whole transform. The last draw is kept in :attr:`last_record` (keys
    :data:`CBCT_RECORD_KEYS`). Shape, affine, device and dtype are kept.

    Args:
        prob: probability of degrading at all.
        blur_prob: probability of resolution loss. blur_sigma: Gaussian sd in mm.
        downsample_prob: probability of down/up-sampling (within resolution loss).
        downsample_factor: down-sampling factor (>= 1, unitless).
        scatter_prob: probability of scatter shading. scatter_amplitude: relative amplitude ``a`` (unitless).
        scatter_control_points: knots per axis of the smooth shading field.
        cupping_prob: probability of cupping. cupping_depth: relative attenuation loss at the axis (unitless).
        streak_prob: probability of streaks. streak_count: number of streaks. streak_amplitude: HU (random sign).
        streak_width: line profile sd in mm.
        ring_prob: probability of rings. ring_count: number of rings. ring_amplitude: HU (random sign).
        ring_width: ring profile sd in mm.
        noise_prob: probability of quantum noise. noise_std: noise sd in HU at water (see module docstring).
        noise_floor: relative variance where the attenuation is 0 (air), unitless.
        noise_correlation: sd in mm of a Gaussian that correlates the noise (0: white noise).
        hu_prob: probability of HU miscalibration. hu_scale: scale (unitless). hu_offset: offset in HU.
        hu_gamma: exponent of the non-linear mapping of the attenuation (1: linear).
        fov_prob: probability of field-of-view truncation. fov_radius: cylinder radius in mm.
        fov_edge: soft-edge width in mm (logistic scale). fov_half_length: half-length in mm along the volume z axis,
            a number or a (low, high) range (``None``: no axial truncation; recorded as 0).
        background: value outside the field of view (HU).
    """

    def __init__(
        self,
        prob: float = 1.0,
        blur_prob: float = 1.0,
        blur_sigma: float | Sequence[float] = (0.4, 1.2),
        downsample_prob: float = 0.2,
        downsample_factor: float | Sequence[float] = (1.0, 1.5),
        scatter_prob: float = 0.8,
        scatter_amplitude: float | Sequence[float] = (0.02, 0.08),
        scatter_control_points: int = 4,
        cupping_prob: float = 0.8,
        cupping_depth: float | Sequence[float] = (0.02, 0.08),
        streak_prob: float = 0.3,
        streak_count: int | Sequence[int] = (2, 10),
        streak_amplitude: float | Sequence[float] = (20.0, 80.0),
        streak_width: float = 1.0,
        ring_prob: float = 0.3,
        ring_count: int | Sequence[int] = (2, 8),
        ring_amplitude: float | Sequence[float] = (10.0, 40.0),
        ring_width: float = 0.7,
        noise_prob: float = 1.0,
        noise_std: float | Sequence[float] = (15.0, 45.0),
        noise_floor: float = 0.2,
        noise_correlation: float = 0.6,
        hu_prob: float = 0.8,
        hu_scale: float | Sequence[float] = (0.94, 1.06),
        hu_offset: float | Sequence[float] = (-40.0, 40.0),
        hu_gamma: float | Sequence[float] = (0.92, 1.08),
        fov_prob: float = 0.5,
        fov_radius: float | Sequence[float] = (130.0, 240.0),
        fov_edge: float | Sequence[float] = (2.0, 8.0),
        fov_half_length: float | Sequence[float] | None = None,
        background: float = -1000.0,
    ) -> None:
        RandomizableTransform.__init__(self, prob)
        self.probs = {
            "blur": blur_prob,
            "downsample": downsample_prob,
            "scatter": scatter_prob,
            "cupping": cupping_prob,
            "streaks": streak_prob,
            "rings": ring_prob,
            "noise": noise_prob,
            "hu": hu_prob,
            "fov": fov_prob,
        }
        for name, p in self.probs.items():
            if not 0.0 <= float(p) <= 1.0:
                raise ValueError(f"{name} probability must be in [0, 1], got {p}")
        self.ranges = {
            "blur_sigma": ensure_interval(blur_sigma, "blur_sigma"),
            "downsample_factor": ensure_interval(downsample_factor, "downsample_factor"),
            "scatter_amplitude": ensure_interval(scatter_amplitude, "scatter_amplitude"),
            "cupping_depth": ensure_interval(cupping_depth, "cupping_depth"),
            "streak_count": ensure_interval(streak_count, "streak_count"),
            "streak_amplitude": ensure_interval(streak_amplitude, "streak_amplitude"),
            "ring_count": ensure_interval(ring_count, "ring_count"),
            "ring_amplitude": ensure_interval(ring_amplitude, "ring_amplitude"),
            "noise_std": ensure_interval(noise_std, "noise_std"),
            "hu_scale": ensure_interval(hu_scale, "hu_scale"),
            "hu_offset": ensure_interval(hu_offset, "hu_offset"),
            "hu_gamma": ensure_interval(hu_gamma, "hu_gamma"),
            "fov_radius": ensure_interval(fov_radius, "fov_radius"),
            "fov_edge": ensure_interval(fov_edge, "fov_edge"),
        }
        if fov_half_length is not None:
            self.ranges["fov_half_length"] = ensure_interval(fov_half_length, "fov_half_length")
        if self.ranges["downsample_factor"][0] < 1.0:
            raise ValueError("downsample_factor must be >= 1")
        self.scatter_control_points = int(scatter_control_points)
        self.streak_width = float(streak_width)
        self.ring_width = float(ring_width)
        self.noise_floor = float(noise_floor)
        self.noise_correlation = float(noise_correlation)
        self.background = float(background)
        self.last_record: dict[str, Any] = self._neutral_record()

    @staticmethod
    def _neutral_record() -> dict[str, Any]:
        rec: dict[str, Any] = {k: 0.0 for k in CBCT_RECORD_KEYS}
        for k in ("blur", "downsample", "scatter", "cupping", "streaks", "rings", "noise", "hu", "fov"):
            rec[k] = False
        rec.update(downsample_factor=1.0, hu_scale=1.0, hu_gamma=1.0, streak_count=0, ring_count=0, seed=0)
        return rec

    def randomize(self, data: Any = None) -> None:
        super().randomize(None)
        rec = self._neutral_record()
        # always draw the same amount of numbers so that the stream does not depend on which effects fire
        fire = self.R.uniform(size=len(self.probs))
        vals = {k: float(self.R.uniform(lo, hi)) for k, (lo, hi) in self.ranges.items()}
        counts = {k: int(self.R.randint(int(lo), int(hi) + 1)) for k, (lo, hi) in self.ranges.items() if "count" in k}
        seed = int(self.R.randint(0, 2**31 - 1))
        if self._do_transform:
            for (name, p), u in zip(self.probs.items(), fire):
                rec[name] = bool(u < p)
            if rec["blur"]:
                rec["blur_sigma"] = vals["blur_sigma"]
            if rec["downsample"]:
                rec["downsample_factor"] = vals["downsample_factor"]
            if rec["scatter"]:
                rec["scatter_amplitude"] = vals["scatter_amplitude"]
            if rec["cupping"]:
                rec["cupping_depth"] = vals["cupping_depth"]
            if rec["streaks"]:
                rec["streak_count"], rec["streak_amplitude"] = counts["streak_count"], vals["streak_amplitude"]
            if rec["rings"]:
                rec["ring_count"], rec["ring_amplitude"] = counts["ring_count"], vals["ring_amplitude"]
            if rec["noise"]:
                rec["noise_std"] = vals["noise_std"]
            if rec["hu"]:
                rec["hu_scale"], rec["hu_offset"], rec["hu_gamma"] = (
                    vals["hu_scale"],
                    vals["hu_offset"],
                    vals["hu_gamma"],
                )
            if rec["fov"]:
                rec["fov_radius"], rec["fov_edge"] = vals["fov_radius"], vals["fov_edge"]
                rec["fov_half_length"] = vals.get("fov_half_length", 0.0)
            rec["seed"] = seed
        self.last_record = rec

    def __call__(self, img: Any, randomize: bool = True) -> torch.Tensor:
        """
        Args:
            img: channel-first CT in HU ``[C, x, y, z]`` (``MetaTensor``, tensor or array).
            randomize: draw new parameters (else reuse :attr:`last_record`).

        Returns:
            the degraded image: same type, shape, affine, dtype and device.
        """
        img = convert_to_tensor(img, track_meta=get_track_meta())
        if randomize:
            self.randomize()
        if not self._do_transform:
            return img
        return self.apply(img, self.last_record)

    def apply(self, img: torch.Tensor, rec: Mapping[str, Any]) -> torch.Tensor:
        """Apply the degradation described by a record (keys :data:`CBCT_RECORD_KEYS`) to ``img``."""
        if img.ndim != 4:
            raise ValueError(f"expected a channel-first 3D image [C, x, y, z], got shape {tuple(img.shape)}")
        spacing = np.asarray(grid_of(img).spacing)
        raw = img.as_tensor() if hasattr(img, "as_tensor") else img
        x = raw.to(raw.dtype if raw.dtype in (torch.float32, torch.float64) else torch.float32).clone()
        dev, dt = x.device, x.dtype
        size = tuple(x.shape[1:])
        rng = np.random.RandomState(int(rec["seed"]))
        gen = torch.Generator(device=dev)
        gen.manual_seed(int(rec["seed"]))

        # in-plane coordinates (mm) about the volume z axis through the centre, and z (mm)
        def axis_coords(i: int) -> torch.Tensor:
            return (torch.arange(size[i], device=dev, dtype=dt) - (size[i] - 1) / 2.0) * float(spacing[i])

        cu, cv, cz = axis_coords(0)[:, None], axis_coords(1)[None, :], axis_coords(2)
        r = torch.sqrt(cu**2 + cv**2)  # [x, y]
        r_ref = 0.5 * float(min(size[0] * spacing[0], size[1] * spacing[1]))

        # 1. resolution loss
        if rec["blur"] and rec["blur_sigma"] > 0:
            x = _gaussian_blur(x, [float(rec["blur_sigma"]) / s for s in spacing])
        if rec["downsample"] and rec["downsample_factor"] > 1.0:
            small = [max(1, int(round(n / float(rec["downsample_factor"])))) for n in size]
            x = F.interpolate(x.unsqueeze(0), size=small, mode="area")
            x = F.interpolate(x, size=size, mode="trilinear", align_corners=False)[0]

        u = (x + 1000.0) / 1000.0  # attenuation relative to water
        # 2. scatter shading
        if rec["scatter"]:
            n = max(self.scatter_control_points, 2)
            knots = torch.as_tensor(rng.standard_normal((1, 1, n, n, n)), dtype=dt, device=dev)
            field = F.interpolate(knots, size=size, mode="trilinear", align_corners=True)[0]
            field = field / field.abs().max().clamp_min(1e-6)
            u = u * (1.0 + float(rec["scatter_amplitude"]) * field)
        # 3. cupping
        if rec["cupping"]:
            profile = (1.0 - (r / r_ref) ** 2).clamp_min(0.0)
            u = u * (1.0 - float(rec["cupping_depth"]) * profile)[None, :, :, None]
        x = 1000.0 * u - 1000.0

        # 4. streaks
        if rec["streaks"] and rec["streak_count"] > 0:
            add = torch.zeros(size, dtype=dt, device=dev)
            z_len = float(size[2] * spacing[2])
            for _ in range(int(rec["streak_count"])):
                theta = float(rng.uniform(0.0, np.pi))
                q = [float(v) * r_ref for v in rng.uniform(-0.5, 0.5, size=2)]
                amp = float(rec["streak_amplitude"]) * float(rng.choice([-1.0, 1.0]))
                dist = (cu - q[0]) * math.sin(theta) - (cv - q[1]) * math.cos(theta)
                line = torch.exp(-0.5 * (dist / self.streak_width) ** 2)
                z0, half = float(rng.uniform(-0.5, 0.5)) * z_len, float(rng.uniform(0.1, 0.5)) * z_len
                zprof = torch.sigmoid((half - (cz - z0).abs()) / max(2.0 * float(spacing[2]), 1e-3))
                add = add + amp * line[:, :, None] * zprof[None, None, :]
            x = x + add[None]
        # 5. rings
        if rec["rings"] and rec["ring_count"] > 0:
            ring = torch.zeros_like(r)
            for _ in range(int(rec["ring_count"])):
                radius = float(rng.uniform(0.05, 0.9)) * r_ref
                amp = float(rec["ring_amplitude"]) * float(rng.choice([-1.0, 1.0]))
                ring = ring + amp * torch.exp(-0.5 * ((r - radius) / self.ring_width) ** 2)
            x = x + ring[None, :, :, None]
        # 6. quantum noise (variance follows attenuation)
        if rec["noise"] and rec["noise_std"] > 0:
            noise = torch.randn(x.shape, generator=gen, device=dev, dtype=dt)
            if self.noise_correlation > 0:
                noise = _gaussian_blur(noise, [self.noise_correlation / s for s in spacing])
                noise = noise / noise.std().clamp_min(1e-6)
            u = ((x + 1000.0) / 1000.0).clamp_min(0.0)
            x = x + float(rec["noise_std"]) * torch.sqrt(self.noise_floor + u) * noise
        # 7. HU miscalibration
        if rec["hu"]:
            u = ((x + 1000.0) / 1000.0).clamp_min(0.0)
            x = float(rec["hu_scale"]) * (1000.0 * u ** float(rec["hu_gamma"]) - 1000.0) + float(rec["hu_offset"])
        # 8. truncated field of view
        if rec["fov"]:
            edge = max(float(rec["fov_edge"]), 1e-3)
            inside = torch.sigmoid((float(rec["fov_radius"]) - r) / edge)[:, :, None]
            if float(rec["fov_half_length"]) > 0:
                inside = inside * torch.sigmoid((float(rec["fov_half_length"]) - cz.abs()) / edge)[None, None, :]
            x = inside[None] * x + (1.0 - inside[None]) * self.background

        out = x.to(raw.dtype) if raw.dtype.is_floating_point else x.round().to(raw.dtype)
        return convert_to_dst_type(out, img)[0]


class RandCBCTDegradationd(RandomizableTransform, MapTransform):
    """Dictionary version of :class:`RandCBCTDegradation`: one draw for all ``keys`` (e.g. ``"moving"``).

    The record (a flat dict with keys :data:`CBCT_RECORD_KEYS`: bools, floats and ints, collatable by
    ``list_data_collate``) is written to ``data[output_key]`` (default ``"cbct_degradation"``), also when the
    transform is not applied (neutral values). Other keys (``"fixed"``, ground truth) are untouched.

    Args:
        keys: keys of the CT images (HU) to degrade.
        output_key: where the record is written (``None``: not written).
        allow_missing_keys: don't raise if a key is missing.
        kwargs: :class:`RandCBCTDegradation` arguments (``prob``, ranges, per-effect probabilities).
    """

    def __init__(
        self,
        keys: KeysCollection,
        output_key: Hashable | None = CBCT_KEY,
        allow_missing_keys: bool = False,
        **kwargs: Any,
    ) -> None:
        MapTransform.__init__(self, keys, allow_missing_keys)
        self.degrade = RandCBCTDegradation(**kwargs)
        RandomizableTransform.__init__(self, self.degrade.prob)
        self.output_key = output_key

    def set_random_state(
        self, seed: int | None = None, state: np.random.RandomState | None = None
    ) -> RandCBCTDegradationd:
        super().set_random_state(seed, state)
        self.degrade.set_random_state(seed, state)
        return self

    def randomize(self, data: Any = None) -> None:
        self.degrade.randomize(None)
        self._do_transform = self.degrade._do_transform

    def __call__(self, data: Mapping[Hashable, Any]) -> dict[Hashable, Any]:
        """
        Args:
            data: dictionary with channel-first CTs ``[C, x, y, z]`` in HU under ``keys``.

        Returns:
            a new dictionary with the degraded images and the record under ``output_key``.
        """
        d = dict(data)
        self.randomize()
        for key in self.key_iterator(d):
            d[key] = self.degrade(d[key], randomize=False)
        if self.output_key is not None:
            d[self.output_key] = dict(self.degrade.last_record)
        return d
