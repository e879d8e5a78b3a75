"""Global initialisation for large offsets: an exhaustive coarse translation search for a few rotations.

The learned network sees a 128 mm cube around the CBCT centre and captures about +-30 mm / +-30 degrees. Clinical
pairs can be further apart (table shifts of several centimetres, the CBCT isocentre anywhere in a larger CT), so
before the network, :func:`global_search` compares the CBCT with the CT at **every** translation within
``max_translation_mm`` (72 mm per axis) on a coarse grid (8 mm), for each of a few rotation candidates:

* the CBCT (a template on an axis-aligned ``spacing_mm`` grid around its centre, rotated by the candidate about that
  centre, with its field-of-view mask) and the CT (the same spacing, the template's extent plus the search margin,
  air outside the CT) are resampled once per candidate;
* the masked normalized cross-correlation of the template with the CT at every integer shift comes from five FFTs
  (Padfield, "Masked object registration in the Fourier domain", IEEE TIP 2012), in float64;
* the peak (refined to sub-voxel by a parabola per axis) gives the translation; its NCC is the candidate's score.

Frames: the result is a fixed (CT) -> moving (CBCT) 4x4 matrix in LPS mm, ``T(x) = R (x - d - c) + c`` with ``c``
the CBCT centre, ``R`` the candidate rotation and ``d`` the CT shift the correlation found (see
``docs/conventions.md``). :class:`~monai_rigidreg.registration.RigidRegistrar` uses the best candidates (its
``search_starts``) as further starts of the network (the first is the identity) and keeps the estimate whose CBCT field
of view matches the CT best.

Cost: ``RegistrationResult.timings["global_search"]`` (27 rotation candidates at 8 mm over +-72 mm; the registrar
runs it in a worker thread beside the network from the identity, ``timings["global_search_wait"]`` is what it
waited for it).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import SimpleITK as sitk
import torch

from monai_rigidreg.core.geometry import (
    Grid,
    grid_points,
    invert_matrix,
    matrix_to_params,
    params_to_matrix,
    target_registration_error,
    transform_points,
)
from monai_rigidreg.core.grid_sampling import (
    antialias_for_grid,
    crop_to_grid,
    normalize_hu,
    resample_to_grid,
    sitk_on_grid,
    sitk_tensor,
)
from monai_rigidreg.core.image_ops import subvoxel_peaks
from monai_rigidreg.core.warp import warp_volume_many
from monai_rigidreg.registration.body import without_couch
from monai_rigidreg.registration.confidence import cylindrical_fov_mask, fov_ncc

if TYPE_CHECKING:
    from monai_rigidreg.core.network_grid import NetworkGridSpec
    from monai_rigidreg.registration.state import Background, NetworkRun, RegistrationState

__all__ = ["SearchCandidate", "global_search", "masked_ncc_map", "masked_ncc_maps", "volume_spectra",
           "DEFAULT_ROTATIONS_DEG", "matrix_distance_mm", "fov_similarity", "SEARCH_AGREE_MM", "SAME_POSE_MM",
           "StartChoice"]

def _rotation_candidates(step: float = 25.0) -> tuple[tuple[float, float, float], ...]:
    """The identity, +-``step`` about each axis, about each pair of axes and about all three (27 candidates)."""
    out: list[tuple[float, float, float]] = [(0.0, 0.0, 0.0)]
    for axis in range(3):
        for sign in (1.0, -1.0):
            r = [0.0, 0.0, 0.0]
            r[axis] = sign * step
            out.append((r[0], r[1], r[2]))
    for a, b in ((0, 1), (0, 2), (1, 2)):
        for sa in (1.0, -1.0):
            for sb in (1.0, -1.0):
                r = [0.0, 0.0, 0.0]
                r[a], r[b] = sa * step, sb * step
                out.append((r[0], r[1], r[2]))
    for sx in (1.0, -1.0):
        for sy in (1.0, -1.0):
            for sz in (1.0, -1.0):
                out.append((sx * step, sy * step, sz * step))
    return tuple(out)


DEFAULT_ROTATIONS_DEG: tuple[tuple[float, float, float], ...] = _rotation_candidates(25.0)
"""Rotation candidates (degrees about x, y, z): the identity, +-25 degrees about each axis, about each pair of axes
and about all three at once (27). The learned network captures about +-30 degrees around a start, so rotations up
to about 45 degrees on any axes are within reach of a candidate (without the three-axis ones, 19 candidates, the
clinical-geometry benchmark's failures were three-axis rotations of 25-45 degrees)."""


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
                   min_overlap: float = 0.5, fft_dtype: torch.dtype = torch.float64,
                   spectra: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Masked NCC of ``template`` (where ``mask`` > 0) with ``volume`` at every shift that keeps it inside.

    Args:
        volume: ``[X, Y, Z]`` search volume.
        template: ``[x, y, z]`` template, ``x <= X`` etc.
        mask: ``[x, y, z]`` template weights in {0, 1}.
        min_overlap: shifts where the volume's variance under the mask is below this fraction of its median are
            set to -1 (flat regions, e.g. air, have no defined NCC).
        fft_dtype: precision of the FFTs (float32 halves their cost; intensities of order 1 keep it exact to
            about 1e-5 in NCC, ``tests/test_global_init.py``); the NCC itself is combined in float64.
        spectra: the volume's ``(rfftn(volume), rfftn(volume**2))`` in ``fft_dtype`` when several templates are
            correlated with one volume (:func:`volume_spectra`).

    Returns:
        ``[X - x + 1, Y - y + 1, Z - z + 1]`` float64: entry ``s`` is the NCC of ``template`` with
        ``volume[s0:s0+x, s1:s1+y, s2:s2+z]`` over the mask.
    """
    return masked_ncc_maps(volume, template[None], mask[None], min_overlap, fft_dtype, spectra)[0]


def masked_ncc_maps(volume: torch.Tensor, templates: torch.Tensor, masks: torch.Tensor,
                    min_overlap: float = 0.5, fft_dtype: torch.dtype = torch.float64,
                    spectra: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """:func:`masked_ncc_map` of ``K`` templates ``[K, x, y, z]`` (masks ``[K, x, y, z]``) with one volume:
    ``[K, X - x + 1, Y - y + 1, Z - z + 1]`` float64, each map as :func:`masked_ncc_map` computes it alone.

    One batched FFT per term instead of a few dozen small operations per template (with the package's passive
    OpenMP wait policy every parallel operation wakes the worker threads): 27 templates of 24^3 in a 42^3 volume
    0.033 s instead of 0.064 s (``benchmarks/speed/bench_network_paths.py``); with the batched sampling
    (:func:`~monai_rigidreg.core.warp.warp_volume_many`) the whole search went from 0.62 to 0.29 s
    (``benchmarks/speed/bench_speed.py``'s stage medians).
    """
    f = volume.to(torch.float64)
    t = templates.to(torch.float64)
    m = (masks > 0).to(torch.float64)
    shape = tuple(f.shape)
    valid = [shape[i] - t.shape[i + 1] + 1 for i in range(3)]
    if min(valid) < 1:
        raise ValueError(f"template {tuple(t.shape[1:])} larger than the search volume {shape}")
    dims = (-3, -2, -1)
    n = m.sum(dim=(1, 2, 3)).view(-1, 1, 1, 1)
    f_hat, f2_hat = spectra if spectra is not None else volume_spectra(f, fft_dtype)
    tm = t * m
    s_t = tm.sum(dim=(1, 2, 3)).view(-1, 1, 1, 1)
    s_tt = (tm * t).sum(dim=(1, 2, 3)).view(-1, 1, 1, 1)
    # sum_y a(y + s) b(y) for the valid shifts s (circular correlation; b zero-padded to the volume)
    b_hat = torch.fft.rfftn(torch.stack([m, tm], 1).to(fft_dtype), s=shape, dim=dims)  # [K, 2, ...]
    m_hat, tm_hat = b_hat[:, 0].conj(), b_hat[:, 1].conj()
    products = torch.stack([f_hat * m_hat, f2_hat * m_hat, f_hat * tm_hat], 1)
    sums = torch.fft.irfftn(products, s=shape, dim=dims)[..., : valid[0], : valid[1], : valid[2]].to(torch.float64)
    s_f, s_ff, s_ft = sums[:, 0], sums[:, 1], sums[:, 2]
    var_t = s_tt - s_t * s_t / n
    var_f = (s_ff - s_f * s_f / n).clamp_min(0.0)
    num = s_ft - s_f * s_t / n
    floor = min_overlap * var_f.flatten(1).median(dim=1).values.view(-1, 1, 1, 1) + 1e-12
    ncc = num / torch.sqrt(var_f * var_t + 1e-12)
    out = torch.where(var_f > floor, ncc, torch.full_like(ncc, -1.0))
    # a template whose mask leaves fewer than 10 voxels has no defined NCC anywhere
    return torch.where(n < 10, torch.full_like(out, -1.0), out)


def volume_spectra(volume: torch.Tensor, fft_dtype: torch.dtype = torch.float64
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(rfftn(volume), rfftn(volume**2))`` for :func:`masked_ncc_map` with many templates."""
    f = volume.to(torch.float64)
    return torch.fft.rfftn(f.to(fft_dtype)), torch.fft.rfftn((f * f).to(fft_dtype))


def global_search(
    fixed: sitk.Image,
    moving: sitk.Image,
    moving_fov: sitk.Image | None = None,
    spacing_mm: float = 8.0,
    max_translation_mm: float = 72.0,
    template_extent_mm: float = 192.0,
    rotations_deg: Sequence[Sequence[float]] = DEFAULT_ROTATIONS_DEG,
    hu_range: tuple[float, float] = (-1000.0, 2000.0),
    fixed_body: sitk.Image | None = None,
) -> list[SearchCandidate]:
    """Best translation for each rotation candidate, by masked NCC over all shifts (see the module doc).

    Args:
        fixed: planning CT (HU), any grid.
        moving: CBCT (HU), any grid overlapping the CT's physical space.
        moving_fov: CBCT field-of-view mask on the CBCT grid (default: the inscribed cylinder,
            :func:`~monai_rigidreg.registration.confidence.cylindrical_fov_mask`).
        spacing_mm: search grid spacing (the translation step before sub-voxel refinement).
        max_translation_mm: half-width of the searched translations along each axis.
        template_extent_mm: the template covers at most this cube of the CBCT around its centre.
        rotations_deg: rotation candidates ``(rx, ry, rz)`` about the CBCT centre, degrees.
        hu_range: intensities are clipped to this window first.
        fixed_body: optional body mask of the CT (any grid on its physical space, e.g.
            :func:`~monai_rigidreg.registration.body.coarse_body_mask`): tissue-like voxels outside it (the couch) count
            as air.

    Returns:
        one :class:`SearchCandidate` per rotation, best score first.
    """
    ct, ct_grid = sitk_tensor(fixed)
    cb, cb_grid = sitk_tensor(moving)
    if moving_fov is None:  # the registration's default: the inscribed cylinder (not "above air": a mask of the
        # tissue alone lets the template slide over the body by several mm)
        moving_fov = cylindrical_fov_mask(moving)
    fov, fov_grid = sitk_tensor(moving_fov)
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
    volume = (volume - a) / (b - a)  # intensities of order 1: float32 FFTs stay accurate
    if fixed_body is not None:  # tissue-like voxels outside the CT's body (the couch) become air
        volume = without_couch(volume, sitk_on_grid(fixed_body, s_grid, "bilinear", 0.0, antialias=False)[0],
                               hu_range)
    t_origin = np.asarray(t_grid.origin, dtype=np.float64)
    s_origin = np.asarray(s_grid.origin, dtype=np.float64)
    out: list[SearchCandidate] = []
    # the CBCT is anti-aliased once for the template spacing (a rotation does not change the spacing), then every
    # candidate samples it without further smoothing
    crop, crop_grid = crop_to_grid(cb, cb_grid, s_grid, 0)
    cb_smooth = antialias_for_grid(normalize_hu(crop, a, b), crop_grid, t_grid)
    spectra = volume_spectra(volume, torch.float32)
    # every candidate's template and mask in one batched sampling, their NCC maps in one batched FFT
    r_matrices = [params_to_matrix([0.0, 0.0, 0.0, *[float(v) for v in rot]], center) for rot in rotations_deg]
    batch = torch.as_tensor(np.stack(r_matrices), dtype=torch.float64)
    templates = warp_volume_many(cb_smooth[None], batch, t_grid, crop_grid)[:, 0]
    masks = warp_volume_many(fov[None], batch, t_grid, fov_grid, mode="nearest")[:, 0]
    ncc = masked_ncc_maps(volume, templates, masks, fft_dtype=torch.float32, spectra=spectra)
    subs, scores = subvoxel_peaks(ncc)
    for rot, r_matrix, sub, score in zip(rotations_deg, r_matrices, subs, scores):
        shift = s_origin + sub * spacing_mm - t_origin  # axis-aligned grids: index offset * spacing
        to_shifted = np.eye(4)
        to_shifted[:3, 3] = -shift
        out.append(SearchCandidate(r_matrix @ to_shifted, float(score), tuple(float(v) for v in rot),
                                   tuple(float(v) for v in shift)))
    out.sort(key=lambda c: -c.score)
    return out


def matrix_distance_mm(a: np.ndarray, b: np.ndarray, points: np.ndarray) -> float:
    """Mean distance (mm) between ``points`` mapped by the 4x4 matrices ``a`` and ``b``
    (:func:`~monai_rigidreg.core.geometry.target_registration_error`)."""
    return float(target_registration_error(a, b, points))


def fov_similarity(fixed: sitk.Image, moving: sitk.Image, fov: sitk.Image, matrices: Sequence[np.ndarray],
                   grid: Grid, hu_range: tuple[float, float], region: sitk.Image | None = None) -> list[float]:
    """For each fixed -> moving matrix, the NCC of the CBCT and the CT mapped into it, over the CBCT field of view on
    ``grid`` (a grid in the CBCT frame, so every estimate is scored on the same CBCT voxels; the CBCT and its field
    of view are resampled once) and where the CT has data; with ``region`` (a CT-frame weight image, e.g. the
    ``--roi`` box) only where it, mapped by the matrix, is above 0.5 (NaN where fewer than 10 voxels remain)."""
    a, b = hu_range
    cb = sitk_on_grid(moving, grid, "bilinear", a)[0].clamp(a, b)
    in_fov = sitk_on_grid(fov, grid, "nearest", 0.0)[0] > 0
    points = grid_points(grid, 1)
    to_index = np.linalg.inv(Grid.from_sitk(fixed).index_to_physical())
    out = []
    for matrix in matrices:
        to_fixed = invert_matrix(matrix)
        ct = sitk_on_grid(fixed, grid, "bilinear", a, matrix=to_fixed)[0].clamp(a, b)
        # only where the CT has data: the grid points mapped into the CT's index space
        idx = transform_points(to_index @ to_fixed, points)
        inside = np.all((idx >= 0) & (idx <= np.asarray(fixed.GetSize()) - 1), axis=1).reshape(grid.size)
        mask = in_fov & torch.from_numpy(inside)
        if region is not None:
            mask &= sitk_on_grid(region, grid, "bilinear", 0.0, matrix=to_fixed)[0] > 0.5
        out.append(fov_ncc(cb, ct, mask.to(torch.float32)))
    return out


SEARCH_AGREE_MM = 10.0
"""The network's estimate from the identity and the global search's best candidate agree when the mean distance
between the network-grid points they map is below this: the further starts are then skipped."""


SAME_POSE_MM = 2.0
"""The network from the search's best candidate and from the identity reached the same pose when the mean distance
between the network-grid points their estimates map is below this (mm): the further candidates are then skipped.
Converged estimates of one pose differ by a fraction of a millimetre and different poses by several millimetres or
more (``details.global_search.best_start_to_identity_estimate_mm`` records it per case)."""


class StartChoice:
    """Stages 3 and 5 of :class:`~monai_rigidreg.registration.RigidRegistrar`: the global search started beside the
    network from the identity, then the network from its best candidates and the choice between the starts. For a
    class with the registrar's ``search_starts``, ``search_settings``, ``hu_range``, ``grid_spec``,
    ``_in_background`` and ``_runs_from``."""

    search_starts: int
    search_settings: dict[str, Any]
    hu_range: tuple[float, float]
    grid_spec: NetworkGridSpec
    _in_background: Callable[..., Background]
    _runs_from: Callable[..., list[NetworkRun]]
    _on_grid: Callable[..., torch.Tensor]

    def _start_search(self, state: RegistrationState) -> Background | None:
        """Stage 3: the global search (:func:`~monai_rigidreg.registration.search.global_search`) started in a worker
        thread: it needs no network estimate, so it runs beside the network from the identity."""
        if not state.options.global_init:
            return None
        return self._in_background(global_search, state.inputs.fixed, state.inputs.moving, state.fov_img,
                                   hu_range=self.hu_range, fixed_body=state.body,
                                   thread_name="monai-rigidreg-search", **self.search_settings)

    def _choose_start(self, state: RegistrationState, searching: Background | None) -> None:
        """Stage 5: the global search's candidates (running in ``searching`` since before the network from the
        identity) and, where its best candidate and the estimate from the identity disagree by more than
        ``SEARCH_AGREE_MM``, the network from the search's best candidate and, unless it ends where the identity's
        estimate did (within :data:`SAME_POSE_MM`), from the next best up to ``search_starts`` in all; the estimate
        whose CBCT field of view matches the CT best (:meth:`_image_match`, inside the match region unless the
        region only weights the last level) goes on, the identity's on a tie. Records ``details.global_search``
        (``starts_run``: how many candidates the network ran from) and ``details.start`` (``"identity"`` or
        ``"search"``)."""
        if searching is not None:
            s, run, timings = state, state.run, state.timings
            t = time.perf_counter()
            candidates = searching.result()
            timings["global_search_wait"] = time.perf_counter() - t
            points = grid_points(run.grid, 8)
            agree = matrix_distance_mm(candidates[0].matrix, run.total, points)
            search: dict[str, Any] = {"best": candidates[0].to_dict(),
                                      "distance_to_identity_start_mm": round(agree, 2),
                                      "candidates": [c.to_dict() for c in candidates]}
            timings["global_search"] = searching.seconds
            started = "identity"
            if agree > SEARCH_AGREE_MM:
                t = time.perf_counter()
                # the search's candidates are 25 degrees / 8 mm apart, so a right estimate from the identity can be
                # more than SEARCH_AGREE_MM from the nearest one: the network from the best candidate tells whether
                # it leads anywhere else; only then do the further candidates run (one batch)
                fixed_img, moving_img, steps = s.inputs.fixed, s.inputs.moving, s.options.cascade_steps
                alts = self._runs_from(fixed_img, moving_img, [candidates[0].matrix], steps, s.pose_weights,
                                       timings, s.body)
                same = matrix_distance_mm(alts[0].total, run.total, points)
                search["best_start_to_identity_estimate_mm"] = round(same, 2)
                if same > SAME_POSE_MM and self.search_starts > 1:
                    alts += self._runs_from(fixed_img, moving_img,
                                            [c.matrix for c in candidates[1: self.search_starts]], steps,
                                            s.pose_weights, timings, s.body)
                search["starts_run"] = len(alts)
                region = None if s.region_last else s.weight_img
                scores = self._image_match(fixed_img, moving_img, s.fov_img, [run.total] + [a.total for a in alts],
                                           s.domain if region is None else region)
                search.update(identity_start_ncc=round(scores[0], 4),
                              search_start_ncc=[round(v, 4) for v in scores[1:]])
                ranked = np.nan_to_num(np.asarray(scores, dtype=np.float64), nan=-np.inf)
                k = int(np.argmax(ranked))
                runs = [run, *alts]
                if scores[k] > scores[0]:
                    state.run, started = alts[k - 1], "search"
                    search["start_rank"] = k - 1
                else:
                    k = 0
                state.other_runs = [runs[i] for i in np.argsort(-ranked, kind="stable") if i != k]
                timings["second_start"] = time.perf_counter() - t
            state.details["global_search"] = search
            state.details["start"] = started
        # the estimate is about the winning run's grid centre until the result re-expresses it
        state.net_params = matrix_to_params(state.run.total, state.run.grid.center())
        state.params = state.net_params.copy()
        if state.options.refine or state.options.assess:
            state.fov_t = self._on_grid(state.fov_img, state.run.grid, "nearest", 0.0, state.run.sampling)[0]

    def _image_match(self, fixed_img: sitk.Image, moving_img: sitk.Image, fov_img: sitk.Image,
                     matrices: list[np.ndarray], region: sitk.Image | None = None) -> list[float]:
        """How well each fixed -> moving estimate matches the images: the NCC of the CBCT's field of view with the CT
        mapped into it (:func:`~monai_rigidreg.registration.search.fov_similarity`) on the network grid pooled by 2,
        centred on the CBCT; with a match region (``--roi``, ``--match bone``: ``region``, CT frame) inside it only,
        where the user asked the images to match (over the whole field of view where the region leaves fewer than
        10 voxels for an estimate). The one rule that chooses between starts and between an estimate and its
        swapped-input twin."""
        ref_grid = self.grid_spec.pooled(2).centered(Grid.from_sitk(moving_img).center())
        scores = fov_similarity(fixed_img, moving_img, fov_img, matrices, ref_grid, self.hu_range, region=region)
        if region is not None and not np.all(np.isfinite(scores)):
            # the region leaves (almost) no voxel of this grid for some estimate (an ROI off the CBCT's centre, or an
            # estimate that moves it out of view): NaN compares as neither better nor worse, so all are scored over
            # the whole field of view instead
            scores = fov_similarity(fixed_img, moving_img, fov_img, matrices, ref_grid, self.hu_range)
        return scores
