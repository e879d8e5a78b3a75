"""Synthetic anatomy for domain randomization: random label maps and random-contrast CT volumes.

In the spirit of SynthMorph / SynthSeg: a network trained on images whose shapes and contrasts are drawn at random
must learn to match *structure* rather than one scanner's or one phantom's intensities. Here the images are CT-like
(HU, attenuation) so that the projection-domain simulator (fan-beam Sim-CT, cone-beam CBCT) can take them as a
phantom (``make_phantom("synth", ...)``, ``monai-rigidreg simulate --phantom synth``), and an on-the-fly training
pipeline can call :func:`synth_phantom` / :func:`synth_hu_volume` directly.

The object is defined in **physical space** (LPS mm, centred on the isocentre ``(0, 0, 0)``), not on a voxel grid:
every random field lives on a lattice of fixed physical spacing and is interpolated at the grid's voxel centres, and
every shape has its size in mm. The same seed therefore gives the same object on any grid (the Sim-CT grid and the
larger, coarser object grid the CBCT is projected from), and a smoothness in mm gives the same structure size at
2 mm and at 4 mm spacing.

Label layout of :func:`synth_label_map` (``int64``, ``[nx, ny, nz]``):

* :data:`AIR` (0): outside the body (only with ``body=True``);
* :data:`WALL` (1): the body wall, a subcutaneous layer of random, varying thickness under the skin;
* :data:`CORTEX` (2): thin bone shells (cortex of curved rods, partial ellipsoidal shells: long bones, ribs,
  pelvis- or skull-like plates), the high-contrast edges a CBCT keeps;
* :data:`MARROW` (3): the inside of the rods;
* :data:`FIRST_TISSUE` (4) and up: the tissue compartments, ``argmax`` over smooth random fields (a random
  tessellation of smooth, blob-like regions).

:func:`synth_hu_volume` gives every label a HU value from a tissue class (air, gas, fat, soft tissue, contrast
organ, bone; the tissue labels' classes are drawn at random), multiplies the density ``1 + HU / 1000`` by a smooth
texture of random strength per label and by a smooth bias field, and blurs for the partial-volume effect; outside
the body it is air, exactly -1000 HU beyond the blur.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from monai_rigidreg.core.device import resolve_device
from monai_rigidreg.core.geometry import Grid, rotation_matrix
from monai_rigidreg.core.image_ops import gaussian_smooth

# the module, not its names: phantoms.py imports this module for its "synth" phantom (whichever of the two is
# imported first, the other is then complete when its functions are called)
from monai_rigidreg.simulation import phantoms as _phantoms

__all__ = [
    "AIR",
    "WALL",
    "CORTEX",
    "MARROW",
    "FIRST_TISSUE",
    "HU_RANGES",
    "TISSUE_CLASSES",
    "synth_label_map",
    "synth_hu_volume",
    "synth_phantom",
]

AIR: int = 0
"""Label outside the body."""
WALL: int = 1
"""Label of the body wall (subcutaneous layer)."""
CORTEX: int = 2
"""Label of the thin bone shells (cortical bone)."""
MARROW: int = 3
"""Label of the inside of the bone rods (cancellous bone / marrow)."""
FIRST_TISSUE: int = 4
"""First label of the random tissue compartments."""

HU_RANGES: dict[str, tuple[float, float]] = {
    "air": (-1000.0, -1000.0),
    "gas": (-950.0, -700.0),
    "fat": (-120.0, -60.0),
    "soft": (0.0, 80.0),
    "organ": (40.0, 300.0),
    "bone": (300.0, 1500.0),
}
"""HU range of each tissue class (lung or bowel gas, fat, soft tissue, contrast-enhanced organ, bone)."""

TISSUE_CLASSES: dict[str, float] = {"gas": 0.04, "fat": 0.2, "soft": 0.4, "organ": 0.3, "bone": 0.06}
"""Probability of each class for a tissue compartment (labels >= :data:`FIRST_TISSUE`)."""

_MAX_LATTICE = 96
"""Most lattice nodes per axis of a random field (the lattice spacing grows beyond that)."""
_SLAB_POINTS = 1 << 20
"""Voxels per slab when fields are evaluated on a grid (bounds the memory of the ``num_labels`` channels)."""


# ---------------------------------------------------------------------------------------------------------------
# Random fields in physical space
# ---------------------------------------------------------------------------------------------------------------
class _Fields:
    """``C`` smooth, zero-mean, unit-variance random fields on a cubic lattice about the isocentre.

    White noise on a lattice of spacing ``h = sigma / 2`` mm (coarser if it would exceed :data:`_MAX_LATTICE`
    nodes per axis), Gaussian-smoothed with ``sigma`` mm, normalized per field, and interpolated trilinearly at
    physical points: the field depends on the seed, ``sigma`` and the half-size only, never on the output grid.

    Args:
        gen: CPU torch generator (the noise).
        num: number of fields ``C``.
        sigma_mm: correlation length (Gaussian sigma), mm.
        half_mm: the lattice covers ``[-half_mm, half_mm]^3`` (LPS mm); beyond, the border value continues.
        device: device of the lattice.
    """

    def __init__(self, gen: torch.Generator, num: int, sigma_mm: float, half_mm: float, device: torch.device):
        h = max(sigma_mm / 2.0, 2.0 * half_mm / (_MAX_LATTICE - 1))
        n = int(math.ceil(2.0 * half_mm / h)) + 1
        self.half = 0.5 * (n - 1) * h
        s = sigma_mm / h
        pad = int(math.ceil(4.0 * s)) + 1
        noise = torch.randn((num, n + 2 * pad, n + 2 * pad, n + 2 * pad), generator=gen)
        f = gaussian_smooth(noise, (s, s, s))[:, pad:-pad, pad:-pad, pad:-pad]
        f = f - f.mean(dim=(1, 2, 3), keepdim=True)
        f = f / f.std(dim=(1, 2, 3), keepdim=True).clamp_min(1e-6)
        self.values = f.to(device).contiguous()  # [C, n, n, n], lattice axes = LPS x, y, z

    def __call__(self, pts: torch.Tensor) -> torch.Tensor:
        """Field values ``[C, ...]`` at points ``[..., 3]`` (LPS mm)."""
        shape = pts.shape[:-1]
        # grid_sample reads the grid's last dimension last tensor axis first: component 0 moves along z
        g = (pts.flip(-1) / self.half).reshape(1, 1, 1, -1, 3).to(self.values.dtype)
        out = F.grid_sample(self.values[None], g, mode="bilinear", padding_mode="border", align_corners=True)
        return out.reshape(self.values.shape[0], *shape)


def _streams(seed: int, stream: int) -> tuple[np.random.Generator, torch.Generator]:
    """A numpy generator (scalar parameters) and a CPU torch generator (noise) for ``(seed, stream)``."""
    ss = np.random.SeedSequence([int(seed), int(stream)])
    rng = np.random.default_rng(ss.spawn(1)[0])
    gen = torch.Generator().manual_seed(int(ss.generate_state(1)[0]))
    return rng, gen


def _slabs(grid: Grid, device: torch.device) -> Iterator[tuple[int, int, torch.Tensor]]:
    """``(x0, x1, points)``: the LPS positions (mm, float32, ``[x1 - x0, ny, nz, 3]``) of x-slabs of ``grid``."""
    m = torch.as_tensor(grid.index_to_physical(), dtype=torch.float64, device=device)
    nx, ny, nz = grid.size
    step = max(1, _SLAB_POINTS // (ny * nz))
    j = torch.arange(ny, dtype=torch.float64, device=device)[None, :, None, None] * m[:3, 1]
    k = torch.arange(nz, dtype=torch.float64, device=device)[None, None, :, None] * m[:3, 2]
    for x0 in range(0, nx, step):
        x1 = min(nx, x0 + step)
        i = torch.arange(x0, x1, dtype=torch.float64, device=device)[:, None, None, None] * m[:3, 0]
        yield x0, x1, (m[:3, 3] + i + j + k).float()


def _default_radius(grid: Grid) -> float:
    """Half the smallest physical extent of ``grid``, mm (the default phantom radius, as for analytic phantoms)."""
    return 0.5 * min(n * s for n, s in zip(grid.size, grid.spacing))


def _range(value: float | Sequence[float], name: str) -> tuple[float, float]:
    lo, hi = (float(value), float(value)) if isinstance(value, (int, float)) else (float(value[0]), float(value[1]))
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
        raise ValueError(f"{name} must be a number or a (low, high) pair with low <= high, got {value!r}")
    return lo, hi


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / max(np.linalg.norm(v), 1e-12)


# ---------------------------------------------------------------------------------------------------------------
# Label map
# ---------------------------------------------------------------------------------------------------------------
def synth_label_map(
    grid: Grid,
    seed: int,
    num_labels: int | Sequence[int] = (8, 24),
    smoothness_mm: float | Sequence[float] = (8.0, 30.0),
    body: bool = True,
    radius_mm: float | None = None,
    device: str | torch.device | None = "cpu",
) -> torch.Tensor:
    """A random anatomy-like label map on ``grid``: tissue compartments, bone shells and rods, a body wall and air.

    Drawn from ``seed`` (same seed and arguments: the identical map; the noise is drawn on the CPU, so another
    device differs at most by rounding at label boundaries); the object is defined in LPS mm about the isocentre
    ``(0, 0, 0)``, so grids of different spacing or extent show the same object.

    * Tissue: ``argmax`` over ``num_labels - 4`` smooth random fields (Gaussian sigma drawn log-uniformly from
      ``smoothness_mm``; each field gets a random offset so that compartments differ in size).
    * Body (``body=True``): a superellipsoid (random semi-axes, cross-section exponent 2-4, flat-ish ends) with a
      smoothly perturbed surface, yawed by up to 10 degrees, clipped to a sphere of ``0.95 radius_mm`` (so that
      any rotation keeps it inside a grid of half-size ``radius_mm``); air (label 0) outside; in 85 % of the maps a
      wall layer of 4-20 mm, varying smoothly around the body.
    * Bone (inside the body, under the wall): 1-4 curved capsule rods (radius 5-14 mm, cortex 2-5 mm, mostly along z)
      and 0-2 partial ellipsoidal shells (2.5-6 mm thick, cut by a random plane).

    Args:
        grid: output grid (LPS; any direction). The map is ``[nx, ny, nz]`` (MONAI order).
        seed: random seed (int >= 0).
        num_labels: number of labels ``n`` (labels ``0 .. n - 1``, 0-3 reserved, see the module docstring), or a
            ``(low, high)`` range it is drawn from (inclusive); ``n >= 5``. Small compartments may lose every voxel
            to bone or to a neighbour, so a map can hold fewer labels than ``n``.
        smoothness_mm: Gaussian sigma (mm) of the tissue fields, or a ``(low, high)`` range (log-uniform).
        body: a body in air (``True``) or tissue filling the whole grid (``False``: no air, no wall).
        radius_mm: half-size of the region the body lives in, mm (default: half the smallest extent of ``grid``;
            pass the same value for every grid that must show the same object). With ``body=False`` the fields
            cover the grid's bounding cube.
        device: torch device of the result and of the computation.

    Returns:
        ``[nx, ny, nz]`` int64 labels.
    """
    lo, hi = (int(num_labels), int(num_labels)) if isinstance(num_labels, int) else map(int, num_labels)
    if lo < FIRST_TISSUE + 1 or lo > hi:
        raise ValueError(f"num_labels must be >= {FIRST_TISSUE + 1} (or a range low <= high), got {num_labels!r}")
    s_lo, s_hi = _range(smoothness_mm, "smoothness_mm")
    if s_lo <= 0:
        raise ValueError(f"smoothness_mm must be > 0 mm, got {smoothness_mm!r}")
    dev = resolve_device(device)
    r = float(radius_mm) if radius_mm is not None else _default_radius(grid)
    if r <= 0:
        raise ValueError(f"radius_mm must be > 0, got {radius_mm!r}")
    rng, gen = _streams(seed, 0)

    n = int(rng.integers(lo, hi + 1))
    n_tissue = n - FIRST_TISSUE
    sigma = float(math.exp(rng.uniform(math.log(s_lo), math.log(s_hi))))
    if body:
        half = r
    else:  # fill the grid: the fields cover its bounding cube
        corners = np.array([[i, j, k, 1.0] for i in (0, grid.size[0] - 1) for j in (0, grid.size[1] - 1)
                            for k in (0, grid.size[2] - 1)]) @ grid.index_to_physical().T
        half = max(r, float(np.abs(corners[:, :3]).max()))
    tissue = _Fields(gen, n_tissue, sigma, half, dev)
    offsets = torch.as_tensor(rng.normal(0.0, 0.4, n_tissue), dtype=torch.float32, device=dev)

    # body: semi-axes (mm) x (left-right), y (antero-posterior), z; exponents; surface perturbation; wall
    a, b, c = rng.uniform(0.55, 0.85) * r, rng.uniform(0.4, 0.7) * r, rng.uniform(0.6, 1.3) * r
    p_xy, p_z = rng.uniform(2.0, 4.0), rng.uniform(2.0, 6.0)
    yaw = torch.as_tensor(rotation_matrix(0.0, 0.0, math.radians(rng.uniform(-10, 10))), dtype=torch.float32,
                          device=dev)
    surface = _Fields(gen, 2, rng.uniform(25.0, 50.0), half, dev)
    bump = rng.uniform(0.0, 0.08)
    wall_mm = rng.uniform(4.0, 20.0) if rng.random() < 0.85 else 0.0
    inner = (0.6 * a, 0.6 * b, 0.6 * c) if body else (0.8 * half,) * 3
    inner_r = 0.7 * r if body else 0.8 * half * math.sqrt(3)

    def inside_point() -> np.ndarray:
        while True:
            p = rng.uniform(-1.0, 1.0, 3) * inner
            if np.linalg.norm(p) <= inner_r:
                return p

    rods = []
    for _ in range(int(rng.integers(1, 5))):
        p0 = inside_point()
        if rng.random() < 0.6:  # mostly along z (long bones, spine), tilted by up to 25 degrees
            tilt, az = math.radians(rng.uniform(0, 25)), rng.uniform(0, 2 * math.pi)
            d = np.array([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), math.cos(tilt)])
        else:
            d = _unit(rng)
        e = np.cross(d, _unit(rng))
        e /= max(np.linalg.norm(e), 1e-12)
        radius = rng.uniform(5.0, 14.0)
        rods.append((p0, d, e, rng.uniform(-1, 1) / rng.uniform(80.0, 300.0), rng.uniform(25.0, 0.9 * r),
                     radius, rng.uniform(2.0, min(5.0, 0.5 * radius))))
    shells = []
    for _ in range(int(rng.integers(0, 3))):
        axes = rng.uniform(25.0, max(26.0, 0.55 * r), 3)
        rot = rotation_matrix(*np.deg2rad(rng.uniform(-180, 180, 3)))
        cut = rng.uniform(-0.6, 0.6) * axes.mean()  # keep the part beyond a random plane: a plate or a bowl
        shells.append((inside_point(), rot, axes, rng.uniform(2.5, 6.0), _unit(rng), cut))

    def as_t(v: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.asarray(v, dtype=np.float64), dtype=torch.float32, device=dev)

    # bounding boxes (LPS mm) of the bones: only the points inside one are tested
    boxes = []
    for p0, d, e, kappa, half_len, radius, _ in rods:
        t = np.linspace(-half_len, half_len, 33)[:, None]
        line = p0 + t * d + 0.5 * kappa * t * t * e
        boxes.append((line.min(0) - radius - 1.0, line.max(0) + radius + 1.0))
    for ctr, rot, axes, thick, _, _ in shells:
        ext = np.sqrt(((rot * axes[None, :]) ** 2).sum(1)) + thick + 1.0
        boxes.append((ctr - ext, ctr + ext))
    boxes_t = [(as_t(lo_), as_t(hi_)) for lo_, hi_ in boxes]

    out = torch.empty(grid.size, dtype=torch.int64, device=dev)
    for x0, x1, pts in _slabs(grid, dev):
        pts = pts.reshape(-1, 3)
        lab = torch.full(pts.shape[:1], AIR, dtype=torch.int64, device=dev)
        wall = torch.zeros(pts.shape[:1], dtype=torch.bool, device=dev)
        if body:
            u = pts @ yaw  # body coordinates: u = yaw^T p
            rho = u.norm(dim=-1)
            xy = ((u[:, 0] / a).abs() ** p_xy + (u[:, 1] / b).abs() ** p_xy) ** (1.0 / p_xy)
            big = (xy**p_z + (u[:, 2] / c).abs() ** p_z) ** (1.0 / p_z)
            n_surf = surface(pts)
            big = big * (1.0 + bump * n_surf[0])
            depth = torch.maximum(rho * (1.0 - 1.0 / big.clamp_min(1e-6)), rho - 0.95 * r)  # ~ mm outside (> 0)
            inside = (depth <= 0).nonzero().squeeze(1)
            if wall_mm > 0:
                wall = depth > -(wall_mm * (1.0 + 0.5 * n_surf[1])).clamp_min(1.0)
        else:
            inside = torch.arange(pts.shape[0], device=dev)
        q = pts[inside]
        lab_in = FIRST_TISSUE + (tissue(q) + offsets[:, None]).argmax(0)
        wall_in = wall[inside]
        lab_in[wall_in] = WALL
        marrow = torch.zeros_like(wall_in)
        cortex = torch.zeros_like(wall_in)
        bones = [("rod", *rod) for rod in rods] + [("shell", *shell) for shell in shells]
        for (kind, *par), (lo_, hi_) in zip(bones, boxes_t):
            sel = ((q >= lo_) & (q <= hi_)).all(-1).nonzero().squeeze(1)
            if sel.numel() == 0:
                continue
            if kind == "rod":
                p0, d, e, kappa, half_len, radius, thick = par
                v = q[sel] - as_t(p0)
                s = (v @ as_t(d)).clamp(-half_len, half_len)[:, None]
                dist = (v - s * as_t(d) - 0.5 * kappa * s * s * as_t(e)).norm(dim=-1)  # to the curved centre line
                marrow[sel] |= dist <= radius - thick
                cortex[sel] |= (dist > radius - thick) & (dist <= radius)
            else:
                ctr, rot, axes, thick, normal, offset = par
                v = q[sel] - as_t(ctr)
                loc = v @ as_t(rot)  # local coordinates R^T v
                g = (loc / as_t(axes)).norm(dim=-1).clamp_min(1e-6)
                grad = (loc / as_t(axes**2)).norm(dim=-1).clamp_min(1e-9) / g
                # (g - 1) / |grad g|: about the distance to the ellipsoid; the part beyond the cutting plane
                cortex[sel] |= (((g - 1.0) / grad).abs() <= 0.5 * thick) & ((v @ as_t(normal)) > offset)
        lab_in[marrow & ~wall_in] = MARROW
        lab_in[cortex & ~wall_in] = CORTEX
        lab[inside] = lab_in
        out[x0:x1] = lab.view(x1 - x0, *grid.size[1:])
    return out


# ---------------------------------------------------------------------------------------------------------------
# Intensities
# ---------------------------------------------------------------------------------------------------------------
def _label_hu(
    rng: np.random.Generator, num: int, ranges: Mapping[str, tuple[float, float]], classes: Mapping[str, float]
) -> np.ndarray:
    """HU of labels ``0 .. num - 1``: fixed classes for the reserved labels, random ones for the tissue labels."""
    names = list(classes)
    probs = np.asarray([classes[k] for k in names], dtype=np.float64)
    if probs.min() < 0 or probs.sum() <= 0:
        raise ValueError(f"tissue_classes must be non-negative weights, got {dict(classes)!r}")
    probs /= probs.sum()

    def draw(name: str, lo_frac: float = 0.0, hi_frac: float = 1.0) -> float:
        lo, hi = ranges[name]
        return float(rng.uniform(lo + lo_frac * (hi - lo), lo + hi_frac * (hi - lo)))

    hu = np.empty(num, dtype=np.float64)
    hu[AIR] = ranges["air"][0]
    hu[WALL] = draw("fat") if rng.random() < 0.75 else draw("soft")
    hu[CORTEX] = draw("bone", 0.3, 1.0)  # always bone: the edges a CBCT keeps
    org_lo, org_hi = ranges["organ"]
    bone_lo, bone_hi = ranges["bone"]
    hu[MARROW] = float(rng.uniform(0.5 * (org_lo + org_hi), bone_lo + 0.3 * (bone_hi - bone_lo)))
    for label in range(FIRST_TISSUE, num):
        hu[label] = draw(str(rng.choice(names, p=probs)))
    return hu


def synth_hu_volume(
    labels: torch.Tensor,
    seed: int,
    grid: Grid | None = None,
    hu_ranges: Mapping[str, Sequence[float]] | None = None,
    tissue_classes: Mapping[str, float] | None = None,
    texture: float | Sequence[float] = (0.0, 0.05),
    bias: float | Sequence[float] = (0.0, 0.08),
    blur_mm: float | Sequence[float] = (0.0, 1.0),
    radius_mm: float | None = None,
) -> torch.Tensor:
    """A CT-like volume (HU) of a label map: random HU per label, texture, bias field and partial-volume blur.

    * Per label a HU value: :data:`AIR` -1000; :data:`WALL` fat (75 %) or soft tissue; :data:`CORTEX` the upper 70 %
      of the bone range; :data:`MARROW` between the organ range's middle and the lower 30 % of the bone range;
      every tissue label a class drawn from ``tissue_classes`` and a value uniform in its range.
    * Density ``d = 1 + HU / 1000`` (relative to water) times ``1 + s_label * T(x)`` (texture: a smooth random field
      ``T`` of sigma 4-10 mm, unit variance, strength ``s_label`` uniform in ``texture`` per label) times
      ``exp(b * B(x))`` (bias: a smooth field of sigma 60-150 mm, ``b`` uniform in ``bias``). Both fields are
      physical (LPS mm about the isocentre): the same seed gives the same texture on any grid. Air has ``d = 0``.
    * Partial volume: a Gaussian of sigma ``sqrt((0.35 spacing)^2 + blur^2)`` mm per axis (the voxel's box average,
      plus a random extra ``blur`` uniform in ``blur_mm``), edges replicated.
    * ``HU = 1000 (d - 1)``, clipped to ``[-1000, highest upper bound of hu_ranges]``.

    Args:
        labels: ``[nx, ny, nz]`` integer labels (e.g. :func:`synth_label_map`), any device.
        seed: random seed (int >= 0); the label map's seed gives a matching draw, any other seed another contrast.
        grid: the labels' grid (default: 1 mm isotropic, centred on the isocentre).
        hu_ranges: ``{class: (low, high)}`` HU, merged over :data:`HU_RANGES` (classes ``air``, ``gas``, ``fat``,
            ``soft``, ``organ``, ``bone``).
        tissue_classes: ``{class: weight}`` of the tissue labels (default :data:`TISSUE_CLASSES`).
        texture: texture strength (relative density std), or a ``(low, high)`` range drawn per label.
        bias: bias-field strength (std of the log-density), or a range.
        blur_mm: extra partial-volume blur (Gaussian sigma, mm), or a range.
        radius_mm: half-size of the region the texture and bias fields cover, mm (default: half the smallest extent
            of ``grid``; pass the label map's ``radius_mm``).

    Returns:
        ``[nx, ny, nz]`` float32 HU on the labels' device.
    """
    if labels.dim() != 3:
        raise ValueError(f"labels must be [nx, ny, nz], got shape {tuple(labels.shape)}")
    if grid is None:
        grid = Grid.centered(tuple(labels.shape), (1.0, 1.0, 1.0))
    if tuple(labels.shape) != tuple(grid.size):
        raise ValueError(f"labels {tuple(labels.shape)} do not match the grid size {grid.size}")
    ranges = {**HU_RANGES, **{k: _range(v, f"hu_ranges[{k!r}]") for k, v in (hu_ranges or {}).items()}}
    classes = dict(TISSUE_CLASSES if tissue_classes is None else tissue_classes)
    unknown = set(classes) - set(ranges)
    if unknown:
        raise ValueError(f"tissue classes {sorted(unknown)} have no HU range (known: {sorted(ranges)})")
    t_lo, t_hi = _range(texture, "texture")
    b_lo, b_hi = _range(bias, "bias")
    u_lo, u_hi = _range(blur_mm, "blur_mm")
    dev = labels.device
    labels = labels.long()
    if int(labels.min()) < 0:
        raise ValueError("labels must be >= 0")
    num = max(int(labels.max()) + 1, FIRST_TISSUE)
    r = float(radius_mm) if radius_mm is not None else _default_radius(grid)
    rng, gen = _streams(seed, 1)

    hu = _label_hu(rng, num, ranges, classes)
    density = torch.as_tensor(1.0 + hu / 1000.0, dtype=torch.float32, device=dev).clamp_min(0.0)
    strength = torch.as_tensor(rng.uniform(t_lo, t_hi, num), dtype=torch.float32, device=dev)
    tex = _Fields(gen, 1, rng.uniform(4.0, 10.0), r, dev)
    bias_field = _Fields(gen, 1, rng.uniform(60.0, 150.0), r, dev)
    b = float(rng.uniform(b_lo, b_hi))
    extra = float(rng.uniform(u_lo, u_hi))

    d = torch.empty(grid.size, dtype=torch.float32, device=dev)
    for x0, x1, pts in _slabs(grid, dev):
        lab = labels[x0:x1]
        d[x0:x1] = density[lab] * (1.0 + strength[lab] * tex(pts)[0]).clamp_min(0.0) * torch.exp(b * bias_field(pts)[0])
    sigmas = [math.sqrt((0.35 * s) ** 2 + extra**2) / s for s in grid.spacing]
    d = gaussian_smooth(d[None], sigmas, padding="replicate")[0]
    top = max(hi for _, hi in ranges.values())
    return (1000.0 * (d - 1.0)).clamp_(-1000.0, top)


_LABEL_OPTIONS = ("num_labels", "smoothness_mm", "body", "device")
"""Keywords of :func:`synth_phantom` that go to :func:`synth_label_map`; the others go to :func:`synth_hu_volume`."""


# ---------------------------------------------------------------------------------------------------------------
# Phantom
# ---------------------------------------------------------------------------------------------------------------
def synth_phantom(grid: Grid, seed: int, radius_mm: float | None = None, **options: Any) -> torch.Tensor:
    """Attenuation volume (1/mm, 70 keV) of a synthetic anatomy: :func:`synth_label_map`, then
    :func:`synth_hu_volume` (same seed), then :func:`~monai_rigidreg.simulation.phantoms.hu_to_mu`.

    The form the simulator consumes (``make_phantom("synth", grid, seed)`` returns it with a description). With
    ``body=True`` everything stays inside a sphere of ``0.95 radius_mm`` about the isocentre (plus the blur), so
    rotations keep it in a grid of half-size ``radius_mm``.

    Args:
        grid: output grid (LPS mm).
        seed: random seed (int >= 0) of the shapes and the contrast.
        radius_mm: half-size of the object's region (default: from the grid), for both steps.
        **options: ``num_labels``, ``smoothness_mm``, ``body``, ``device`` of :func:`synth_label_map`, and
            ``hu_ranges``, ``tissue_classes``, ``texture``, ``bias``, ``blur_mm`` of :func:`synth_hu_volume`.

    Returns:
        ``[nx, ny, nz]`` float32 attenuation (1/mm), ``>= 0``.
    """
    r = float(radius_mm) if radius_mm is not None else _default_radius(grid)
    label_options = {k: options.pop(k) for k in _LABEL_OPTIONS if k in options}
    labels = synth_label_map(grid, seed, radius_mm=r, **label_options)
    hu = synth_hu_volume(labels, seed, grid, radius_mm=r, **options)
    return _phantoms.hu_to_mu(hu)
