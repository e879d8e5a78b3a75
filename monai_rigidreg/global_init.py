"""Global initialisation for large offsets: an exhaustive coarse translation search for a few rotations.

The learned network sees a 128 mm cube around the CBCT centre and captures about +-30 mm / +-30 degrees. Clinical
pairs can be further apart (table shifts of several centimetres, the CBCT isocentre anywhere in a larger CT), so
before the network, :func:`global_search` compares the CBCT with the CT at **every** translation within
``max_translation_mm`` on a coarse grid, for each of a few rotation candidates:

* the CBCT (a template on an axis-aligned ``spacing_mm`` grid around its centre, rotated by the candidate about that
  centre, with its field-of-view mask) and the CT (the same spacing, the template's extent plus the search margin,
  air outside the CT) are resampled once per candidate;
* the masked normalized cross-correlation of the template with the CT at every integer shift comes from five FFTs
  (Padfield, "Masked object registration in the Fourier domain", IEEE TIP 2012), in float64;
* the peak (refined to sub-voxel by a parabola per axis) gives the translation; its NCC is the candidate's score.

Frames: the result is a fixed (CT) -> moving (CBCT) 4x4 matrix in LPS mm, ``T(x) = R (x - d - c) + c`` with ``c``
the CBCT centre, ``R`` the candidate rotation and ``d`` the CT shift the correlation found (see
``docs/conventions.md``). :class:`~monai_rigidreg.registration.RigidRegistrar` uses the best candidate as a second
start of the network (the first is the identity) and keeps the estimate whose CBCT field of view matches the CT best.

Cost (``benchmarks/bench_clinical_geometry.py`` prints it as the ``global_search`` timing): 7 rotation candidates
at 6 mm over +-80 mm, about 0.1-0.3 s on 2 CPU cores.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.geometry import Grid, params_to_matrix, transform_points
from monai_rigidreg.transforms.grid import resample_to_grid

__all__ = ["SearchCandidate", "global_search", "masked_ncc_map", "DEFAULT_ROTATIONS_DEG", "matrix_distance_mm"]

DEFAULT_ROTATIONS_DEG: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.0, 0.0),
    (25.0, 0.0, 0.0), (-25.0, 0.0, 0.0),
    (0.0, 25.0, 0.0), (0.0, -25.0, 0.0),
    (0.0, 0.0, 25.0), (0.0, 0.0, -25.0),
)
"""Rotation candidates (degrees about x, y, z): the identity and +-25 degrees about each axis. The learned network
captures about +-30 degrees around a start, so single-axis rotations up to about 50 degrees are within reach."""


@dataclass(frozen=True)
class SearchCandidate:
    """One rotation candidate of :func:`global_search` at its best translation.

    Attributes:
        matrix: ``[4, 4]`` fixed (CT) -> moving (CBCT) transform, LPS mm.
        score: masked NCC of the CBCT template with the CT at that translation, in [-1, 1].
        rotation_deg: the candidate rotation ``(rx, ry, rz)`` about the CBCT centre, degrees.
        shift_mm: ``d``, the CT shift that matched the template (LPS mm).
    """

    matrix: np.ndarray
    score: float
    rotation_deg: tuple[float, float, float]
    shift_mm: tuple[float, float, float]

    def to_dict(self) -> dict[str, object]:
        return {"score": round(float(self.score), 4), "rotation_deg": [float(v) for v in self.rotation_deg],
                "shift_mm": [round(float(v), 2) for v in self.shift_mm]}


def masked_ncc_map(volume: torch.Tensor, template: torch.Tensor, mask: torch.Tensor,
                   min_overlap: float = 0.5) -> torch.Tensor:
    """Masked NCC of ``template`` (where ``mask`` > 0) with ``volume`` at every shift that keeps it inside.

    Args:
        volume: ``[X, Y, Z]`` search volume.
        template: ``[x, y, z]`` template, ``x <= X`` etc.
        mask: ``[x, y, z]`` template weights in {0, 1}.
        min_overlap: shifts where the volume's variance under the mask is below this fraction of its median are
            set to -1 (flat regions, e.g. air, have no defined NCC).

    Returns:
        ``[X - x + 1, Y - y + 1, Z - z + 1]`` float64: entry ``s`` is the NCC of ``template`` with
        ``volume[s0:s0+x, s1:s1+y, s2:s2+z]`` over the mask.
    """
    f = volume.to(torch.float64)
    t = template.to(torch.float64)
    m = (mask > 0).to(torch.float64)
    shape = f.shape
    valid = [shape[i] - t.shape[i] + 1 for i in range(3)]
    if min(valid) < 1:
        raise ValueError(f"template {tuple(t.shape)} larger than the search volume {tuple(shape)}")
    n = m.sum()
    if n < 10:
        return torch.full(valid, -1.0, dtype=torch.float64)

    def corr(a_hat: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """sum_y a(y + s) b(y) for the valid shifts s (circular correlation; b zero-padded to the volume)."""
        b_hat = torch.fft.rfftn(b, s=shape)
        out = torch.fft.irfftn(a_hat * b_hat.conj(), s=shape)
        return out[: valid[0], : valid[1], : valid[2]]

    f_hat = torch.fft.rfftn(f)
    f2_hat = torch.fft.rfftn(f * f)
    tm = t * m
    s_t = tm.sum()
    s_tt = (tm * t).sum()
    s_f = corr(f_hat, m)
    s_ff = corr(f2_hat, m)
    s_ft = corr(f_hat, tm)
    var_t = s_tt - s_t * s_t / n
    var_f = (s_ff - s_f * s_f / n).clamp_min(0.0)
    num = s_ft - s_f * s_t / n
    floor = min_overlap * float(var_f.median()) + 1e-12
    ncc = num / torch.sqrt(var_f * var_t + 1e-12)
    return torch.where(var_f > floor, ncc, torch.full_like(ncc, -1.0))


def _subvoxel_peak(ncc: torch.Tensor) -> tuple[np.ndarray, float]:
    """Index of the maximum of ``ncc`` refined by a parabola through its neighbours on each axis, and the maximum."""
    flat = int(torch.argmax(ncc))
    idx = np.array(np.unravel_index(flat, tuple(ncc.shape)), dtype=np.int64)
    peak = float(ncc.flatten()[flat])
    sub = idx.astype(np.float64)
    for ax in range(3):
        if 0 < idx[ax] < ncc.shape[ax] - 1:
            lo, hi = idx.copy(), idx.copy()
            lo[ax] -= 1
            hi[ax] += 1
            cm, cp = float(ncc[tuple(lo)]), float(ncc[tuple(hi)])
            den = cm - 2.0 * peak + cp
            if den < -1e-9:
                sub[ax] += float(np.clip(0.5 * (cm - cp) / den, -0.5, 0.5))
    return sub, peak


def _image_tensor(image: sitk.Image) -> tuple[torch.Tensor, Grid]:
    """``[1, x, y, z]`` float32 view of a SimpleITK image and its grid."""
    if image.GetPixelID() != sitk.sitkFloat32:
        image = sitk.Cast(image, sitk.sitkFloat32)
    return torch.from_numpy(sitk.GetArrayFromImage(image)).permute(2, 1, 0)[None], Grid.from_sitk(image)


def global_search(
    fixed: sitk.Image,
    moving: sitk.Image,
    moving_fov: sitk.Image | None = None,
    spacing_mm: float = 6.0,
    max_translation_mm: float = 80.0,
    template_extent_mm: float = 192.0,
    rotations_deg: Sequence[Sequence[float]] = DEFAULT_ROTATIONS_DEG,
    hu_range: tuple[float, float] = (-1000.0, 2000.0),
) -> list[SearchCandidate]:
    """Best translation for each rotation candidate, by masked NCC over all shifts (see the module doc).

    Args:
        fixed: planning CT (HU), any grid.
        moving: CBCT (HU), any grid overlapping the CT's physical space.
        moving_fov: CBCT field-of-view mask on the CBCT grid (default: where the CBCT is above air, -990 HU).
        spacing_mm: search grid spacing (the translation step before sub-voxel refinement).
        max_translation_mm: half-width of the searched translations along each axis.
        template_extent_mm: the template covers at most this cube of the CBCT around its centre.
        rotations_deg: rotation candidates ``(rx, ry, rz)`` about the CBCT centre, degrees.
        hu_range: intensities are clipped to this window first.

    Returns:
        one :class:`SearchCandidate` per rotation, best score first.
    """
    ct, ct_grid = _image_tensor(fixed)
    cb, cb_grid = _image_tensor(moving)
    if moving_fov is None:
        fov = (cb > -990.0).to(torch.float32)
        fov_grid = cb_grid
    else:
        fov, fov_grid = _image_tensor(moving_fov)
    center = cb_grid.center()
    lo, hi = cb_grid.physical_extent()
    extent = np.minimum(np.asarray(hi) - np.asarray(lo), template_extent_mm)
    t_size = [max(4, int(np.floor(e / spacing_mm))) for e in extent]
    margin = int(np.ceil(max_translation_mm / spacing_mm))
    s_size = [n + 2 * margin for n in t_size]
    t_grid = Grid.centered(t_size, (spacing_mm,) * 3, center)
    s_grid = Grid.centered(s_size, (spacing_mm,) * 3, center)
    a, b = hu_range
    volume = resample_to_grid(ct.clamp(a, b), ct_grid, s_grid, "bilinear", "zeros", a)[0]
    t_origin = np.asarray(t_grid.origin, dtype=np.float64)
    s_origin = np.asarray(s_grid.origin, dtype=np.float64)
    out: list[SearchCandidate] = []
    cb_clamped = cb.clamp(a, b)
    for rot in rotations_deg:
        r_matrix = params_to_matrix([0.0, 0.0, 0.0, *[float(v) for v in rot]], center)
        template = resample_to_grid(cb_clamped, cb_grid, t_grid, "bilinear", "zeros", a, matrix=r_matrix)[0]
        mask = resample_to_grid(fov, fov_grid, t_grid, "nearest", "zeros", 0.0, antialias=False,
                                matrix=r_matrix)[0]
        ncc = masked_ncc_map(volume, template, mask)
        sub, score = _subvoxel_peak(ncc)
        shift = s_origin + sub * spacing_mm - t_origin  # axis-aligned grids: index offset * spacing
        to_shifted = np.eye(4)
        to_shifted[:3, 3] = -shift
        out.append(SearchCandidate(r_matrix @ to_shifted, score, tuple(float(v) for v in rot),
                                   tuple(float(v) for v in shift)))
    out.sort(key=lambda c: -c.score)
    return out


def matrix_distance_mm(a: np.ndarray, b: np.ndarray, points: np.ndarray) -> float:
    """Mean distance (mm) between ``points`` mapped by the 4x4 matrices ``a`` and ``b``."""
    return float(np.linalg.norm(transform_points(a, points) - transform_points(b, points), axis=1).mean())
