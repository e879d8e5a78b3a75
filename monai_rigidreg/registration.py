"""Register a CBCT (moving) to a planning CT (fixed): network estimate, optional classical refinement, confidence.

Data flow (``docs/architecture.md``): the volumes are read once (:mod:`monai_rigidreg.io`), both are resampled
once onto the network grid placed on the CBCT (:meth:`~monai_rigidreg.network_grid.NetworkGridSpec.on_moving`,
the same resampling and normalization as training), the network returns six parameters about that grid's centre,
and the result is re-expressed about the fixed (CT) image centre, the project's convention
(``docs/conventions.md``); its ``Euler3DTransform`` resamples the original, full-resolution CBCT onto the CT grid.
Writing the output files is :mod:`monai_rigidreg.outputs`; the confidence check is :mod:`monai_rigidreg.confidence`.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch
from torch import nn

from monai_rigidreg.body import BodyMaskCache, without_couch
from monai_rigidreg.bundle import default_bundle_path, load_bundle_network
from monai_rigidreg.classical import register_sitk
from monai_rigidreg.confidence import (
    CONFIDENCE_THRESHOLD,
    LOCAL_GAIN_LIMIT,
    SWAP_AGREE_MM,
    assess_estimate,
    confidence_score,
    cylindrical_fov_mask,
    swap_inputs,
)
from monai_rigidreg.device import adapted_cpu_threads, resolve_device
from monai_rigidreg.errors import InputError
from monai_rigidreg.geometry import (
    LPS_TO_RAS,
    PARAM_NAMES,
    Grid,
    grid_points,
    invert_matrix,
    matrix_to_params,
    params_to_matrix,
    params_to_sitk,
    recenter_params,
    target_registration_error,
    transform_points,
)
from monai_rigidreg.global_init import SEARCH_AGREE_MM, fov_similarity, global_search, matrix_distance_mm
from monai_rigidreg.grid_sampling import normalize_hu, sitk_on_grid
from monai_rigidreg.io import as_image, check_distinct_inputs, grid_within, grids_overlap, resample
from monai_rigidreg.json_safe import json_safe
from monai_rigidreg.match_region import RoiLike, match_weight, parse_roi, weight_on_grid
from monai_rigidreg.network_grid import NetworkGridSpec
from monai_rigidreg.networks import cascade_register
from monai_rigidreg.precision import refine_native
from monai_rigidreg.provenance import bundle_record
from monai_rigidreg.region_check import block_shifts

__all__ = ["RegistrationResult", "RigidRegistrar", "register", "check_intensities", "not_hu", "fine_stage_switch"]

logger = logging.getLogger(__name__)


@dataclass
class RegistrationResult:
    """Result of :func:`register`.

    Attributes:
        params: ``(tx, ty, tz, rx, ry, rz)`` mm / degrees, fixed -> moving, about ``center``.
        center: rotation centre (LPS mm): the fixed image centre.
        registered: the moving image resampled onto the fixed grid (``None`` if not asked for).
        timings: seconds per stage (``load``, ``body``, ``preprocess``, ``network``, ``global_search``,
            ``second_start``, ``native_level``, ``refine``, ``confidence``, ``resample``, ``total``; those that ran).
            The global search runs in a worker thread beside the network from the identity: ``global_search`` is
            its own duration, which overlaps ``network``, and ``global_search_wait`` the time the registration
            waited for it afterwards. The confidence check's swapped-input estimate runs in a worker thread beside
            the last level: ``swap_estimate`` is its own duration (overlapping ``native_level``; ``confidence``
            includes only the wait for it).
        confidence: score in [0, 1] (see :func:`confidence_score`); ``flagged`` when below the threshold. 0 where
            an input's intensities are certainly not HU (:func:`not_hu`; ``details.signals.not_hu`` names it): the
            signals are calibrated on HU.
        flagged: likely failure: check the QC figure.
        details: network-only parameters, refinement change, similarity before/after, swap consistency, and
            ``warnings`` (a list of sentences, e.g. an input whose intensities are not HU) where there are any.
        provenance: the audit trail (:func:`~monai_rigidreg.provenance.registration_provenance`: inputs and their
            DICOM UIDs, bundle and weights' SHA-256, software versions, device, time, command line), filled in by
            :func:`~monai_rigidreg.outputs.register_files`; empty for in-memory images.
        couch_shift: the correction in IEC 61217 couch terms at the isocentre
            (:func:`~monai_rigidreg.couch.couch_shifts`), filled in by :func:`~monai_rigidreg.outputs.register_files`.
    """

    params: np.ndarray
    center: np.ndarray
    registered: sitk.Image | None = None
    timings: dict[str, float] = field(default_factory=dict)
    confidence: float = float("nan")
    flagged: bool = False
    details: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    couch_shift: dict[str, Any] = field(default_factory=dict)

    @property
    def transform(self) -> sitk.Euler3DTransform:
        """The ``SimpleITK.Euler3DTransform`` (fixed -> moving): ``sitk.Resample(moving, fixed, transform)``."""
        return params_to_sitk(self.params, self.center)

    @property
    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix of :attr:`transform` (LPS mm)."""
        return params_to_matrix(self.params, self.center)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (``result.json``)."""
        return {
            "params": {n: float(v) for n, v in zip(PARAM_NAMES, self.params)},
            "units": {"translation": "mm", "rotation": "degrees"},
            "convention": "ITK LPS; maps fixed (CT) points to moving (CBCT) points; Euler3DTransform, "
            "rotation R = Rz @ Rx @ Ry about center",
            "center": [float(v) for v in self.center],
            "matrix": [[float(v) for v in row] for row in self.matrix],
            # the same transform the other way round (CBCT points -> CT points, LPS: what a DICOM Spatial
            # Registration stores) and in RAS for 3D Slicer (the "to parent" matrix Slicer shows for the CBCT
            # placed under the loaded transform.tfm)
            "matrix_moving_to_fixed": [[float(v) for v in row] for row in invert_matrix(self.matrix)],
            "matrix_moving_to_fixed_ras": [[float(v) for v in row]
                                           for row in LPS_TO_RAS @ invert_matrix(self.matrix) @ LPS_TO_RAS],
            "runtime_s": {k: round(float(v), 4) for k, v in self.timings.items()},
            "confidence": json_safe(float(self.confidence)),  # null where the check did not run
            "flagged": bool(self.flagged),
            "details": json_safe(self.details),
            "provenance": json_safe(self.provenance),
            **({"couch_shift": json_safe(self.couch_shift)} if self.couch_shift else {}),
        }


class RigidRegistrar:
    """A loaded network plus its preprocessing settings, reusable across many registrations.

    Args:
        network: module mapping ``[B, 2, x, y, z]`` (moving, fixed; intensities normalized) to ``[B, 6]``, e.g. the
            shipped :class:`~monai_rigidreg.networks.TwoStageRigidNet` (regression + fine stage).
        network_size: network grid size in voxels (default: the shipped bundle's, see ``network_spacing``).
        network_spacing: network grid spacing in mm. Both default to the shipped bundle's
            (:meth:`~monai_rigidreg.network_grid.NetworkGridSpec.from_bundle`): a checkpoint is tied to its grid, so
            give the sizes of the bundle the network came from. A fine stage built for another spacing is refused.
        cascade_steps: network applications (1 = single pass, the bundle's setting; each further step estimates a
            correction on the CBCT warped by the running estimate).
        device: ``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:N"``.
        hu_range: HU window mapped to [0, 1] before the network (as in training).
        inferer: optional MONAI ``Inferer`` (``inferer(inputs [B, 2, x, y, z], network) -> [B, 6]``) through which
            every network application runs (the bundle's ``inferer``: ``SimpleInferer``); ``None`` calls the network.
        global_init: run the global search for large offsets by default (:mod:`monai_rigidreg.global_init`: the
            network also starts from its best candidates when they disagree with the estimate from the identity,
            ``search_starts``); a call's ``global_init`` overrides.
        search_settings: keyword arguments of :func:`~monai_rigidreg.global_init.global_search` (``spacing_mm``,
            ``max_translation_mm``, ``rotations_deg``, ...).
        search_starts: when the estimate from the identity and the search's best candidate disagree, the network
            also starts from this many of the best-scoring candidates (from the best one first, and from the others
            only when that run does not end at the identity's pose, ``SAME_POSE_MM``) and the estimate whose CBCT
            field of view matches the CT best goes on (the search's score ranks rotations by a coarse correlation
            that a head's near-symmetric outline can fool; the network from a candidate within its capture range
            reaches a much better match). The constructor's default, 1, is the best candidate alone (as before
            0.4.4); the shipped bundle's ``search_starts`` is 4 (measured on the clinical-geometry pairs, README).
        native_level: after the network's fine stage, one more Gauss-Newton level over the whole CBCT field of view
            at the inputs' own resolution (:func:`~monai_rigidreg.precision.refine_native`); skipped when the fine
            stage is off (the learned network alone). Measured both ways (README): on the clinical-geometry pairs
            (CBCTs larger than the network's 128 mm cube, off the CT centre) it lifted the success rate from 90 to
            100 % up to 40 mm / 30 degrees and from 75 to 85 % up to 60 mm / 45 degrees; on the paper-protocol pairs
            (128 mm CBCTs) it moved the mean TRE from 0.33 to 0.49 mm (all still under 2 mm). On by default;
            ``--no-native-level`` turns it off.
        native_bias_degree: the intensity bias the last level estimates with the pose over the whole field of view
            (a polynomial of this degree per feature channel,
            :func:`~monai_rigidreg.networks.gauss_newton.gauss_newton_align`; -1: none). The constructor's default
            (2, the fine stage's) is kept for code that builds a registrar by hand; the shipped bundle's
            ``native_bias_degree`` is 0 since 0.4.3. Measured on the clinical-geometry pairs (``python
            benchmarks/bench_native_bias.py``): without a region of interest a constant is more precise (mean TRE
            over 18 successes 0.46 mm instead of 0.59, ``bench_native_bias_2026-12-02.txt``). A constant absorbs a
            CBCT's HU offset from the CT (``tests/test_precision.py``).
        native_bias_degree_roi: the same with a match region (``--roi``, ``--match bone``); ``None``: the same as
            ``native_bias_degree`` (the bundle's ``native_bias_degree_roi``, 2, is used by ``from_bundle`` unless
            overridden too). With the ``--roi`` box on deformed anatomy the quadratic is more precise (mean landmark
            error 2.05 mm instead of 2.11, one pair lost with 0, ``bench_native_bias_deformed_2026-12-02.txt``).
        native_highpass_sigma_mm: the Gaussian (mm) of the last level's local-contrast feature (``None``: the fine
            stage's, 16 mm, which the network grid was tuned with; the bundle's ``native_highpass_sigma_mm`` is 4
            since 0.4.5). At the inputs' own resolution the finer contrast aligns better: on the clinical-geometry
            pairs the rigid successes' mean TRE 0.45 -> 0.27 mm (seed 1500) and 0.44 -> 0.23 mm (seed 2500), better
            on 19 of 19 pairs in each set (``python benchmarks/bench_native_bias.py --highpass-sigmas 16 4``,
            ``bench_native_highpass_*``).

    ``adapt_threads`` (attribute, default ``True``): on the CPU each call runs with torch's and SimpleITK's thread
    counts lowered by the cores other work keeps busy as it starts (:func:`~monai_rigidreg.device.adaptive_threads`;
    beside a busy loop on 2 cores, one thread is faster than two) and restored afterwards; ``details["cpu_threads"]``
    records the count used. ``False`` keeps the counts as set (``monai-rigidreg register --threads N`` does).

    Build it once and reuse it: ``registrar = RigidRegistrar.from_bundle()`` then
    ``monai_rigidreg.register(ct, cbct, model=registrar)`` (or ``registrar(ct, cbct)``).
    """

    def __init__(
        self,
        network: nn.Module,
        network_size: Sequence[int] | None = None,
        network_spacing: Sequence[float] | None = None,
        cascade_steps: int = 1,
        device: str | torch.device | None = "auto",
        hu_range: tuple[float, float] = (-1000.0, 2000.0),
        inferer: Callable[[torch.Tensor, nn.Module], torch.Tensor] | None = None,
        global_init: bool = True,
        search_settings: dict[str, Any] | None = None,
        search_starts: int = 1,
        native_level: bool = True,
        native_bias_degree: int = 2,
        native_bias_degree_roi: int | None = None,
        native_highpass_sigma_mm: float | None = None,
    ) -> None:
        if network_size is None or network_spacing is None:
            shipped = NetworkGridSpec.from_bundle()
            network_size = shipped.size if network_size is None else network_size
            network_spacing = shipped.spacing if network_spacing is None else network_spacing
        self.grid_spec = NetworkGridSpec(network_size, network_spacing)
        fine = getattr(network, "fine_stage", None)
        if fine is not None and tuple(fine.grid_spacing) != self.grid_spec.spacing:
            raise InputError(f"the network's fine stage works at {tuple(fine.grid_spacing)} mm but the network grid "
                             f"is {self.grid_spec.spacing} mm: give the network_spacing of its bundle")
        regression = getattr(network, "regression", network)
        for name, want in (("grid_spacing", self.grid_spec.spacing), ("grid_size", self.grid_spec.size)):
            have = getattr(regression, name, None)
            if have is not None and tuple(have) != tuple(want):
                raise InputError(f"the network's regression is built for a {name.replace('_', ' ')} of "
                                 f"{tuple(have)} but the network grid has {tuple(want)}: give the network_size and "
                                 "network_spacing of its bundle")
        self.device = resolve_device(device)
        self.network = network.to(self.device).eval()
        self.cascade_steps = _check_steps(cascade_steps)
        self.hu_range = hu_range
        self.inferer = inferer
        self.global_init = bool(global_init)
        self.search_settings = dict(search_settings or {})
        if int(search_starts) < 1:
            raise InputError(f"search_starts must be >= 1, got {search_starts}")
        self.search_starts = int(search_starts)
        self.native_level = bool(native_level)
        if native_bias_degree_roi is None:
            native_bias_degree_roi = native_bias_degree
        for name, degree in (("native_bias_degree", native_bias_degree),
                             ("native_bias_degree_roi", native_bias_degree_roi)):
            if int(degree) < -1:
                raise InputError(f"{name} must be -1 (none) or a degree >= 0, got {degree}")
        self.native_bias_degree = int(native_bias_degree)
        self.native_bias_degree_roi = int(native_bias_degree_roi)
        if native_highpass_sigma_mm is not None and not float(native_highpass_sigma_mm) > 0:
            raise InputError(f"native_highpass_sigma_mm must be > 0 mm (or None), got {native_highpass_sigma_mm}")
        self.native_highpass_sigma_mm = None if native_highpass_sigma_mm is None else float(native_highpass_sigma_mm)
        # a network that takes the match-region weight (TwoStageRigidNet, CorrelationRigidNet); others ignore it
        self.accepts_weight = "fixed_weight" in inspect.signature(self.network.forward).parameters
        # a regression with a CT context (ContextCorrelationNet) gets the CT on its context grid too: same centre,
        # context_factor times the spacing (what it was trained with: RigidPairSampler)
        self.context_grid_spec = None
        if getattr(regression, "takes_context", False):
            self.context_grid_spec = NetworkGridSpec(regression.context_size,
                                                     [s * regression.context_factor for s in self.grid_spec.spacing])
        # one registration at a time per registrar: fine_stage_switch changes the shared network's setting
        self._lock = threading.RLock()
        self._workers: list[_Background] = []  # this call's worker threads: all joined before __call__ returns
        self.adapt_threads = True
        self._bodies = BodyMaskCache()  # the CT's body mask, computed once per planning CT
        self.source: dict[str, Any] = {}  # the bundle and weights it came from (from_bundle), for the audit trail
        self.antialias = True  # as ResampleToNetworkGrid's default, the training preprocessing

    @property
    def network_size(self) -> tuple[int, int, int]:
        """Network grid size (voxels)."""
        return self.grid_spec.size

    @property
    def network_spacing(self) -> tuple[float, float, float]:
        """Network grid spacing (mm)."""
        return self.grid_spec.spacing

    @classmethod
    def from_bundle(
        cls, bundle: str | Path | None = None, device: str | torch.device | None = "auto", **overrides: Any
    ) -> RigidRegistrar:
        """Load the composed network (regression + fine stage) and its settings from a MONAI bundle, once.

        Args:
            bundle: bundle directory (default: the shipped ``cbct_ct_rigid``).
            device: ``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:N"``.
            overrides: constructor arguments that replace the bundle's settings (e.g. ``cascade_steps=2``).
        """
        net, settings = load_bundle_network(bundle, device=resolve_device(device))
        settings.update(overrides)
        registrar = cls(net, device=device, **settings)
        registrar.source = bundle_record(bundle if bundle is not None else default_bundle_path())
        return registrar

    # -- stages ------------------------------------------------------------------------------------------------
    def network_grid(self, fixed: sitk.Image, moving: sitk.Image | None = None) -> Grid:
        """The inference placement of the network grid: centred on the CBCT (moving) centre
        (:meth:`~monai_rigidreg.network_grid.NetworkGridSpec.on_moving`), or on the fixed image without a CBCT.

        Estimates on this grid are about its centre; :meth:`__call__` re-expresses them about the fixed image centre.
        """
        return self.grid_spec.on_moving(moving) if moving is not None else self.grid_spec.on_fixed(fixed)

    def preprocess(self, image: sitk.Image, grid: Grid, matrix: np.ndarray | None = None) -> torch.Tensor:
        """``[1, x, y, z]`` normalized plain tensor of ``image`` on the network grid (the training preprocessing:
        :class:`~monai_rigidreg.transforms.ResampleToNetworkGrid` then :class:`~monai_rigidreg.transforms.NormalizeHU`,
        through their MONAI-free functions in :mod:`~monai_rigidreg.grid_sampling`);
        ``matrix``: sample ``image`` through this 4x4 grid -> image transform (LPS mm; a start estimate)."""
        out = self._on_grid(image, grid, "bilinear", self.hu_range[0], matrix)
        return normalize_hu(out, self.hu_range[0], self.hu_range[1]).float()

    def _on_grid(self, image: sitk.Image, grid: Grid, mode: str, padding_value: float,
                 matrix: np.ndarray | None = None) -> torch.Tensor:
        """``[1, x, y, z]`` float32 plain tensor of ``image`` resampled onto ``grid`` (no normalization).

        The ``[z, y, x]`` array is viewed as ``[x, y, z]`` without a copy, so for a CT much larger than the grid only
        the part the grid covers is transposed, and plain tensors skip ``MetaTensor`` bookkeeping in the network
        (``benchmarks/bench_inference_speed.py``: both volumes in 0.04 s instead of 0.20 s through
        ``sitk_to_metatensor`` and the MONAI transforms; the forward pass 0.105 s instead of 0.138 s).
        """
        return sitk_on_grid(image, grid, mode, padding_value, antialias=self.antialias, matrix=matrix)

    def estimate(self, moving_t: torch.Tensor, fixed_t: torch.Tensor, grid: Grid, steps: int | None = None,
                 fixed_weight: torch.Tensor | None = None) -> np.ndarray:
        """Network (+ cascade) estimate ``[6]`` (numpy, mm/deg about the grid centre) from preprocessed
        ``[1, x, y, z]`` tensors on ``grid``; ``fixed_weight``: optional ``[1, x, y, z]`` match-region weights
        on the grid (passed to the network as ``fixed_weight``)."""
        return self.estimate_batch(moving_t[None], fixed_t[None], grid, steps,
                                   None if fixed_weight is None else fixed_weight[None])[0]

    @torch.no_grad()
    def estimate_batch(self, moving_t: torch.Tensor, fixed_t: torch.Tensor, grid: Grid, steps: int | None = None,
                       fixed_weight: torch.Tensor | None = None) -> np.ndarray:
        """:meth:`estimate` for a batch: ``[B, 1, x, y, z]`` tensors on grids of ``grid``'s size and spacing ->
        ``[B, 6]`` (numpy, mm/deg about each case's grid centre)."""
        k = self.cascade_steps if steps is None else _check_steps(steps)
        m = moving_t.to(self.device)
        f = fixed_t.to(self.device)
        kwargs = {}
        if fixed_weight is not None and self.accepts_weight:
            kwargs["fixed_weight"] = fixed_weight.to(self.device)
        if self.inferer is None:
            net = functools.partial(self.network, **kwargs) if kwargs else self.network
        else:
            net = functools.partial(self.inferer, network=self.network, **kwargs)
        params = cascade_register(net, m, f, grid, steps=k)
        return params.double().cpu().numpy()

    def assess(
        self, moving_t: torch.Tensor, fixed_t: torch.Tensor, grid: Grid, params: np.ndarray, fov: torch.Tensor,
        swap: bool = True, region: torch.Tensor | None = None, swapped: Callable[[], np.ndarray] | None = None,
    ) -> dict[str, Any]:
        """Failure signals of ``params`` (mm/deg about the grid centre):
        :func:`~monai_rigidreg.confidence.assess_estimate` with this registrar's network as the swapped-input
        estimator (``swap=False``: without that check); ``region``: the match-region weight on ``grid`` (the edge
        test looks there only); ``swapped``: the swapped estimate already under way (its result function)."""
        estimate = (lambda m, f: self.estimate(m, f, grid)) if swap else None
        return assess_estimate(moving_t, fixed_t, grid, params, fov, estimate, region=region, hu_range=self.hu_range,
                               swapped=swapped if swap else None)

    def _image_match(self, fixed_img: sitk.Image, moving_img: sitk.Image, fov_img: sitk.Image,
                     matrices: list[np.ndarray], region: sitk.Image | None = None) -> list[float]:
        """How well each fixed -> moving estimate matches the images: the NCC of the CBCT's field of view with the CT
        mapped into it (:func:`~monai_rigidreg.global_init.fov_similarity`) on the network grid pooled by 2, centred
        on the CBCT; with a match region (``--roi``, ``--match bone``: ``region``, CT frame) inside it only, where
        the user asked the images to match (over the whole field of view where the region leaves fewer than 10
        voxels for an estimate). The one rule that chooses between starts and between an estimate and
        its swapped-input twin (the starts are scored over the whole field of view when the region only weights the
        last level, see ``region_last`` in :meth:`_register`)."""
        ref_grid = self.grid_spec.pooled(2).centered(Grid.from_sitk(moving_img).center())
        scores = fov_similarity(fixed_img, moving_img, fov_img, matrices, ref_grid, self.hu_range, region=region)
        if region is not None and not np.all(np.isfinite(scores)):
            # the region leaves (almost) no voxel of this grid for some estimate (an ROI off the CBCT's centre, or an
            # estimate that moves it out of view): NaN compares as neither better nor worse, so all are scored over
            # the whole field of view instead
            scores = fov_similarity(fixed_img, moving_img, fov_img, matrices, ref_grid, self.hu_range)
        return scores

    def _native(self, fixed_img: sitk.Image, moving_img: sitk.Image, matrix: np.ndarray, fov_img: sitk.Image,
                weights: list[sitk.Image], grid: Grid, region: bool = False) -> tuple[np.ndarray, dict[str, Any]]:
        """The last level (:func:`~monai_rigidreg.precision.refine_native`) from ``matrix`` with the fine stage's
        feature settings (the local contrast at ``native_highpass_sigma_mm`` when set) and this registrar's
        ``native_bias_degree`` (``native_bias_degree_roi`` when ``region``: a
        match region, ``--roi`` or ``--match bone``, is among ``weights``). Returns the refined matrix and
        ``details.native_level``: the level's grid, bias degree and how far it moved the estimate (mean distance over
        the points of ``grid``, the network grid, mm)."""
        stage = self.network.fine_stage
        degree = self.native_bias_degree_roi if region else self.native_bias_degree
        sigma = stage.highpass_sigma_mm if self.native_highpass_sigma_mm is None else self.native_highpass_sigma_mm
        refined, native_grid = refine_native(
            fixed_img, moving_img, matrix, fov_img, weights, highpass_sigma_mm=sigma,
            highpass_weight=stage.highpass_weight, support_erosion_mm=stage.support_erosion_mm,
            bias_degree=degree, device=self.device, tolerance=getattr(stage, "tolerance", None),
            secant=getattr(stage, "secant", False))
        detail = {"spacing_mm": float(native_grid.spacing[0]), "size": list(native_grid.size), "bias_degree": degree,
                  "highpass_sigma_mm": float(sigma),
                  "change_mm": round(matrix_distance_mm(refined, matrix, grid_points(grid, 8)), 3)}
        return refined, detail

    def __call__(
        self,
        fixed: sitk.Image | str | Path,
        moving: sitk.Image | str | Path,
        refine: bool = False,
        cascade_steps: int | None = None,
        resample_moving: bool = True,
        moving_fov: sitk.Image | None = None,
        assess: bool = True,
        fine_stage: bool | None = None,
        global_init: bool | None = None,
        roi: RoiLike = None,
        match: str = "soft",
        keep_couch: bool = False,
    ) -> RegistrationResult:
        """Register ``moving`` (CBCT) to ``fixed`` (CT); see :func:`register` (``fine_stage=False``: the learned
        regression alone, also in the confidence check's swapped-input estimate, and no global search; ``None``:
        as the network is configured, e.g. by the bundle's ``fine_stage``)."""
        with self._lock, fine_stage_switch(self.network, fine_stage), self._cpu_threads() as threads:
            if global_init is None:
                global_init = self.global_init and fine_stage is not False
            if fine_stage is False:  # the learned network alone sees the inputs as they are (no couch removal)
                keep_couch = True
            self._workers = []
            try:
                result = self._register(fixed, moving, refine, cascade_steps, resample_moving, moving_fov, assess,
                                        bool(global_init), roi, match, keep_couch)
            finally:
                # whatever raised, no worker is left using the network after the lock and the fine-stage setting
                # are released (a worker's own error is dropped here: the caller gets the first one raised)
                for worker in self._workers:
                    worker.wait()
                self._workers = []
            used = getattr(self.network, "fine_stage", None) is not None and getattr(
                self.network, "fine_stage_enabled", True)
        result.details["fine_stage"] = bool(used)
        if threads is not None:
            result.details["cpu_threads"] = threads
        return result

    def _cpu_threads(self) -> contextlib.AbstractContextManager[int | None]:
        """torch's and SimpleITK's thread counts for one call (``adapt_threads``,
        :func:`~monai_rigidreg.device.adapted_cpu_threads`); the context yields the torch count in use on the CPU,
        ``None`` on another device."""
        if self.device.type != "cpu":
            return contextlib.nullcontext(None)
        return adapted_cpu_threads(self.adapt_threads)

    def _in_background(self, fn: Callable[..., Any], *args: Any, thread_name: str, **kwargs: Any) -> _Background:
        """``fn`` started in a worker thread and registered with this call, whose end joins it (:meth:`__call__`)."""
        worker = _Background(fn, *args, thread_name=thread_name, **kwargs)
        self._workers.append(worker)
        return worker

    def _start_tensors(self, fixed_img: sitk.Image, moving_img: sitk.Image, start: np.ndarray,
                       body: sitk.Image | None = None) -> tuple[Grid, torch.Tensor, torch.Tensor]:
        """The network grid for a start (4x4 fixed -> moving, LPS mm), centred on the CT point the start maps to the
        CBCT centre, and ``[1, x, y, z]`` normalized CT and CBCT on it: the CBCT sampled through the start (one
        interpolation), the CT with its tissue-like voxels outside ``body`` (the couch) set to air."""
        sampling = None if np.allclose(start, np.eye(4)) else start
        center = Grid.from_sitk(moving_img).center()
        if sampling is not None:
            center = transform_points(invert_matrix(sampling), center[None])[0]
        grid = self.grid_spec.centered(center)
        fixed_t = self.preprocess(fixed_img, grid)
        moving_t = self.preprocess(moving_img, grid, sampling)
        if body is not None:
            fixed_t = without_couch(fixed_t, self._on_grid(body, grid, "bilinear", 0.0), self.hu_range)
        return grid, fixed_t, moving_t

    def _context(self, fixed_img: sitk.Image, grid: Grid, body: sitk.Image | None) -> torch.Tensor:
        """``[1, *context size]`` normalized CT on the context grid of ``grid``'s centre (the couch removed as on
        the network grid)."""
        ctx_grid = self.context_grid_spec.centered(grid.center())
        ctx = self.preprocess(fixed_img, ctx_grid)
        if body is not None:
            ctx = without_couch(ctx, self._on_grid(body, ctx_grid, "bilinear", 0.0), self.hu_range)
        return ctx

    def _run_from(self, fixed_img: sitk.Image, moving_img: sitk.Image, start: np.ndarray, steps: int | None,
                  weights: Sequence[sitk.Image], timings: dict[str, float], body: sitk.Image | None = None) -> _Run:
        """The network from a start (4x4 fixed -> moving, LPS mm) on :meth:`_start_tensors`' grid and tensors: the
        network estimates the residual and the total is ``start o residual``. ``weights``: CT-frame images whose
        product on the grid is the match weight; ``body``: the CT's body (tissue-like voxels outside it, the couch,
        become air). Adds to ``timings["preprocess"]`` and ``["network"]``."""
        return self._runs_from(fixed_img, moving_img, [start], steps, weights, timings, body)[0]

    def _runs_from(self, fixed_img: sitk.Image, moving_img: sitk.Image, starts: Sequence[np.ndarray],
                   steps: int | None, weights: Sequence[sitk.Image], timings: dict[str, float],
                   body: sitk.Image | None = None) -> list[_Run]:
        """:meth:`_run_from` for several starts in one batch of the network (the global search's candidates):
        each start has its own grid and tensors, the network sees them as one ``[B, 1, x, y, z]`` batch. Every
        operation of the network and its fine stage is per case, so a case's estimate is the one it gets alone, but
        for the fine stage's early stop, which waits for the slowest case of the batch (a few more steps of the
        same iteration). On 2 CPU cores three starts take 0.57 s in one batch instead of 0.73 s one by one
        (``benchmarks/bench_network_paths.py``)."""
        t = time.perf_counter()
        prepared = [self._start_tensors(fixed_img, moving_img, start, body) for start in starts]
        weight_ts = [weight_on_grid(weights, grid) for grid, _, _ in prepared]
        fixed_in = [f for _, f, _ in prepared]
        if self.context_grid_spec is not None:  # the CT context rides along as a second channel of the fixed input
            fixed_in = [torch.cat([f, self._context(fixed_img, grid, body)], 0) for (grid, _, _), f in
                        zip(prepared, fixed_in)]
        timings["preprocess"] = timings.get("preprocess", 0.0) + time.perf_counter() - t
        t = time.perf_counter()
        # the network works about its grid's centre: a grid of the same size and spacing stands for all of them
        canonical = self.grid_spec.canonical()
        residuals = self.estimate_batch(torch.stack([m for _, _, m in prepared]),
                                        torch.stack(fixed_in), canonical, steps,
                                        None if weight_ts[0] is None else torch.stack(weight_ts))
        timings["network"] = timings.get("network", 0.0) + time.perf_counter() - t
        runs = []
        for (grid, fixed_t, moving_t), start, residual in zip(prepared, starts, residuals):
            total = start @ params_to_matrix(residual, grid.center())
            runs.append(_Run(grid, fixed_t, moving_t, start, residual, total))
        return runs

    def _best_start(self, fixed_img: sitk.Image, moving_img: sitk.Image, fov_img: sitk.Image, run: _Run,
                    cascade_steps: int | None, pose_weights: Sequence[sitk.Image], timings: dict[str, float],
                    body: sitk.Image | None, region: sitk.Image | None, searching: _Background
                    ) -> tuple[_Run, dict[str, Any], str]:
        """The global search's candidates (:func:`~monai_rigidreg.global_init.global_search`, running in
        ``searching`` since before the network from the identity) and, where its best candidate and
        the estimate from the identity (``run``) disagree by more than ``SEARCH_AGREE_MM``, the network from the
        search's best candidate and, unless it ends where the identity's estimate did (within ``SAME_POSE_MM``), from
        the next best up to ``search_starts`` in all; the estimate whose CBCT field of view matches the CT best
        (:meth:`_image_match`, inside ``region`` when given) goes on, the identity's on a tie. Returns the winning
        run, ``details.global_search`` (``starts_run``: how many candidates the network ran from) and
        ``details.start`` (``"identity"`` or ``"search"``)."""
        t = time.perf_counter()
        candidates = searching.result()
        timings["global_search_wait"] = time.perf_counter() - t
        points = grid_points(run.grid, 8)
        agree = matrix_distance_mm(candidates[0].matrix, run.total, points)
        search: dict[str, Any] = {"best": candidates[0].to_dict(), "distance_to_identity_start_mm": round(agree, 2),
                                  "candidates": [c.to_dict() for c in candidates]}
        timings["global_search"] = searching.seconds
        started = "identity"
        if agree > SEARCH_AGREE_MM:
            t = time.perf_counter()
            # the search's candidates are 25 degrees / 8 mm apart, so a right estimate from the identity can be more
            # than SEARCH_AGREE_MM from the nearest one: the network from the best candidate tells whether it leads
            # anywhere else; only then do the further candidates run (one batch)
            alts = self._runs_from(fixed_img, moving_img, [candidates[0].matrix], cascade_steps, pose_weights,
                                   timings, body)
            same = matrix_distance_mm(alts[0].total, run.total, points)
            search["best_start_to_identity_estimate_mm"] = round(same, 2)
            if same > SAME_POSE_MM and self.search_starts > 1:
                alts += self._runs_from(fixed_img, moving_img,
                                        [c.matrix for c in candidates[1: self.search_starts]], cascade_steps,
                                        pose_weights, timings, body)
            search["starts_run"] = len(alts)
            scores = self._image_match(fixed_img, moving_img, fov_img, [run.total] + [a.total for a in alts], region)
            search.update(identity_start_ncc=round(scores[0], 4), search_start_ncc=[round(v, 4) for v in scores[1:]])
            k = int(np.argmax(np.nan_to_num(np.asarray(scores, dtype=np.float64), nan=-np.inf)))
            if scores[k] > scores[0]:
                run, started = alts[k - 1], "search"
                search["start_rank"] = k - 1
            timings["second_start"] = time.perf_counter() - t
        return run, search, started

    def _confidence(self, fixed_img: sitk.Image, moving_img: sitk.Image, fov_img: sitk.Image, fov_t: torch.Tensor,
                    run: _Run, params: np.ndarray, weights: list[sitk.Image], weight_img: sitk.Image | None,
                    roi_img: sitk.Image | None, native: bool, may_replace: bool, details: dict[str, Any],
                    early_swap: _Background | None = None) -> tuple[np.ndarray, bool, dict[str, Any]]:
        """The failure signals and the confidence of ``params`` (mm/deg about ``run.grid``'s centre), with the
        swapped-input check: where the swapped estimate disagrees by more than ``SWAP_AGREE_MM``, the one whose CBCT
        field of view matches the CT better (inside the match region ``weight_img``) is trusted, and a better
        swapped estimate replaces ``params`` once (``may_replace``; after its own last level when ``native``).
        ``roi_img``: the ROI's mask on the CT for the region check (:func:`~monai_rigidreg.region_check.block_shifts`;
        ``None``: no ROI, no check).
        ``early_swap``: the swapped estimate started beside the last level (:meth:`_register`), used for the first
        assessment (a replacement's is computed here).
        Records ``details.swap_check`` (and ``start``, ``native_level`` on a replacement). Returns ``(params,
        replaced, signals)``, ``signals["confidence"]`` included."""
        grid = run.grid
        grid_center = grid.center()
        region = None if weight_img is None else weight_on_grid([weight_img], grid)[0]
        replaced = False
        while True:
            # in the frame of the winning start: its resampled CBCT and the residual of the final estimate
            to_start = invert_matrix(run.start)
            residual = matrix_to_params(to_start @ params_to_matrix(params, grid_center), grid_center)
            signals = self.assess(run.moving_t, run.fixed_t, grid, residual, fov_t, region=region,
                                  swapped=None if early_swap is None or replaced else early_swap.result)
            swapped = run.start @ params_to_matrix(signals.pop("swap_params"), grid_center)
            if not signals["swap_tre_mm"] > SWAP_AGREE_MM:
                break
            # the two estimates disagree: the one whose CBCT field of view matches the CT better is trusted (the rule
            # that chooses between starts); a better swapped estimate replaces this one, once (not after --refine,
            # which the user asked to start from the network's estimate, and not for the learned network alone,
            # fine_stage=False, which must stay measurable as it is).
            # Scored inside the match region even when the region only weighted the last level: the estimate judged
            # here is the region's (after that level). Over the whole view instead, the twin (a whole-view network
            # estimate) tends to win on deformed anatomy and its disagreement counts: seed-2500 deformed pairs, false
            # alarms 2 -> 3 of 7 (bench_clinical_geometry_0.4.4_seed2500_deformed_swap_whole_view_*)
            s_est, s_swap = self._image_match(fixed_img, moving_img, fov_img,
                                              [params_to_matrix(params, grid_center), swapped], weight_img)
            check = {"estimate_ncc": round(s_est, 4), "swapped_ncc": round(s_swap, 4),
                     "swap_tre_mm": round(signals["swap_tre_mm"], 2)}
            if s_swap > s_est and may_replace and not replaced:
                replaced = True
                details["swap_check"] = {**check, "replaced": True}
                if native:
                    # the last level from the swapped estimate: details.native_level describes this run
                    swapped, details["native_level"] = self._native(fixed_img, moving_img, swapped, fov_img,
                                                                    weights, grid, region=weight_img is not None)
                params = matrix_to_params(swapped, grid_center)
                details["start"] = "swapped"
                continue
            details.setdefault("swap_check", {**check, "replaced": False})
            # a worse twin does not count against the estimate, unless the estimate is itself a replacing twin: then
            # the two directions kept disagreeing and neither settles the pose (a clinical-geometry head pair ended
            # 9.3 mm off that way, every other signal reading well; bench_confidence_clinical_0.4.5_*)
            signals["swap_counted"] = bool(s_swap >= s_est) or replaced
            if replaced:
                details["swap_check"]["after_replacement"] = check
            break
        if roi_img is not None:
            # the region's structures against the CBCT (block matching): on flat or deformed anatomy an image optimum
            # can leave them millimetres off while every other signal reads well
            blocks = block_shifts(fixed_img, moving_img, params_to_matrix(params, grid_center), roi_img, fov_img)
            shift = blocks.median_shift()
            signals["region_shift_mm"] = float(np.linalg.norm(shift)) if np.all(np.isfinite(shift)) else float("nan")
            signals["region_shift_vector_mm"] = [round(float(v), 2) for v in shift]
            signals["region_blocks"] = blocks.count
        signals["confidence"] = confidence_score(signals["local_gain"], signals["swap_tre_mm"],
                                                 swap_counted=signals.get("swap_counted", True),
                                                 tissue_on_air_share=signals["tissue_on_air"],
                                                 region_shift_mm=signals.get("region_shift_mm", float("nan")))
        return params, replaced, signals

    def _register(
        self,
        fixed: sitk.Image | str | Path,
        moving: sitk.Image | str | Path,
        refine: bool,
        cascade_steps: int | None,
        resample_moving: bool,
        moving_fov: sitk.Image | None,
        assess: bool,
        global_init: bool,
        roi: RoiLike,
        match: str,
        keep_couch: bool,
    ) -> RegistrationResult:
        t_start = time.perf_counter()
        timings: dict[str, float] = {}
        fixed_img = as_image(fixed, "fixed")
        moving_img = as_image(moving, "moving")
        checked = {name: _check_hu(img, name, self.hu_range)
                   for img, name in ((fixed_img, "fixed (CT)"), (moving_img, "moving (CBCT)"))}
        warnings = [w for found, _ in checked.values() for w in found]
        timings["load"] = time.perf_counter() - t_start
        fixed_grid, moving_grid = Grid.from_sitk(fixed_img), Grid.from_sitk(moving_img)
        if not grids_overlap(fixed_grid, moving_grid):
            raise InputError(
                "the CT (fixed) and CBCT (moving) do not overlap in physical space: check that both are in the "
                "same patient coordinate system (origins and directions)"
            )
        if grid_within(fixed_grid, moving_grid):
            msg = ("the fixed image lies inside the moving one and covers less than half of it, as a CBCT would the "
                   "planning CT: check that fixed (--fixed) is the CT and moving (--moving) the CBCT (swapped, the "
                   "transform and the couch shifts come out inverted)")
            logger.warning("%s", msg)
            warnings.append(msg)
        roi = parse_roi(roi)  # once: a mask file is read here
        weight_img = match_weight(fixed_img, roi, match)
        stage = getattr(self.network, "fine_stage", None)
        staged = stage is not None and getattr(self.network, "fine_stage_enabled", True)  # False: the network alone
        native = self.native_level and staged
        # the CBCT field of view: for the refinement, the confidence signals, the global search and the last level
        fov_img = None
        if refine or assess or global_init or native:
            fov_img = cylindrical_fov_mask(moving_img) if moving_fov is None else moving_fov

        body = None
        if not keep_couch:
            # the couches do not move with the patient: the CT's tissue-like voxels outside its body become air, and
            # the match weight is zero there, so the CBCT's couch, wherever an estimate puts it, meets no weight.
            # (A CBCT's own body mask is not used: a lung cut by its field of view breaks it, measured on the
            # clinical-geometry thorax pairs.)
            t = time.perf_counter()
            hits = self._bodies.hits
            body = self._bodies(fixed_img)
            timings["body"] = time.perf_counter() - t
            body_cached = self._bodies.hits > hits
        weights = [w for w in (weight_img, body) if w is not None]
        # With a match region and the last level to apply it, the pose is found over the whole field of view (the
        # network's starts, the search and the choice between them) and the region weights the last level (and the
        # confidence's edge test): a region is where the images should match, but a small one on deformed or flat
        # anatomy is no place to search for the pose. Measured on the clinical-geometry deformed pairs (README,
        # "Clinical geometry", 0.4.4): on a head pair the region-weighted network ended 17-52 mm off from every start
        # while the whole view's estimate from the identity is 5.7 mm off (bench_starts_0.4.4_seed2500_head_deformed_
        # 001); the deformed groups' landmark error 2.03 / 12.56 mm (seeds 1500 / 2500, 0.4.3) -> 2.04 / 3.48.
        region_last = weight_img is not None and native
        pose_weights = [w for w in (body,) if w is not None] if region_last else weights
        searching = None
        if global_init:  # the search needs no network estimate: it runs beside the network from the identity
            searching = self._in_background(global_search, fixed_img, moving_img, fov_img, hu_range=self.hu_range,
                                            fixed_body=body, thread_name="monai-rigidreg-search",
                                            **self.search_settings)
        run = self._run_from(fixed_img, moving_img, np.eye(4), cascade_steps, pose_weights, timings, body)
        details: dict[str, Any] = {"network_params": {},
                                   "cascade_steps": self.cascade_steps if cascade_steps is None else cascade_steps,
                                   "device": str(self.device), "start": "identity",
                                   "couch_excluded": body is not None}
        if not keep_couch:
            details["body_mask"] = "cached" if body_cached else "computed"
        if (roi is not None or match != "soft") and not region_last and not self.accepts_weight:
            details.setdefault("warnings", []).append(
                "this network takes no match-region weight and the last level is off: the region of interest / bone "
                "match only scopes the choice between starts and the confidence check")
        if roi is not None or match != "soft":
            details["match_region"] = {"roi": "mask" if isinstance(roi, sitk.Image) else list(roi) if roi else None,
                                       "match": match,
                                       "applied_to": "last level" if region_last else "network" if self.accepts_weight
                                       else "choice of start"}
        if warnings:
            details.setdefault("warnings", []).extend(warnings)
        if global_init:
            run, details["global_search"], started = self._best_start(
                fixed_img, moving_img, fov_img, run, cascade_steps, pose_weights, timings, body,
                None if region_last else weight_img, searching)
            details["start"] = started
        grid = run.grid
        grid_center = grid.center()  # params are about it until re-expressed at the end
        net_params = matrix_to_params(run.total, grid_center)
        params = net_params.copy()
        fov_t = None
        if refine or assess:
            fov_t = self._on_grid(fov_img, grid, "nearest", 0.0, run.sampling)[0]
        early_swap = None
        if native:
            if assess and not refine:
                # the confidence check's swapped-input estimate runs in a worker thread beside the last level: the
                # network's many small operations keep about one core busy whatever the thread count, and the last
                # level has the other. Its CT is masked by the field of view as the network's estimate places it;
                # where the last level moves the estimate by more than EARLY_SWAP_MAX_CHANGE_MM, that mask is stale
                # and the twin is computed again after it, from the refined estimate (as before 0.4.7)
                early_swap = self._in_background(self.estimate, *swap_inputs(run.moving_t, run.fixed_t, grid,
                                                                             run.residual, fov_t), grid,
                                                 thread_name="monai-rigidreg-swap")
            t = time.perf_counter()
            refined, details["native_level"] = self._native(fixed_img, moving_img, run.total, fov_img, weights, grid,
                                                            region=weight_img is not None)
            params = matrix_to_params(refined, grid_center)
            net_params = params.copy()
            timings["native_level"] = time.perf_counter() - t
            if early_swap is not None:
                stale = details["native_level"]["change_mm"] > EARLY_SWAP_MAX_CHANGE_MM
                details["swap_estimate"] = "after the last level" if stale else "beside the last level"
                if stale:
                    early_swap.wait()
                    early_swap = None

        if refine:
            def refine_from(start_params: np.ndarray) -> Any:
                return register_sitk(fixed_img, moving_img, initial_params=start_params, center=grid_center,
                                     moving_mask=fov_img, shrink_factors=(2, 1), smoothing_sigmas_mm=(1.0, 0.0))

            t = time.perf_counter()
            res, start_name = refine_from(net_params), "network"
            # safeguard: a network estimate that looks wrong can drag the optimizer into a wrong basin; then the
            # optimizer also starts from the identity and the lower (better) Mattes MI value wins
            pre = self.assess(run.moving_t, run.fixed_t, grid, run.residual, fov_t, swap=False)
            if pre["local_gain"] > LOCAL_GAIN_LIMIT:
                alt_res = refine_from(np.zeros(6))
                if alt_res.metric < res.metric:
                    res, start_name = alt_res, "identity"
            params = res.params
            timings["refine"] = time.perf_counter() - t
            details["refine"] = {
                "start": start_name,
                "change": {},
                "change_tre_mm": float(target_registration_error(params, net_params, grid_points(grid, 4),
                                                                 center=grid_center)),
                "metric": res.metric,
                "stop_condition": res.stop_condition,
            }

        confidence, flagged = float("nan"), False
        if assess:
            t = time.perf_counter()
            # the region check looks at the ROI itself (with --match bone too: the blocks need the soft tissue
            # around the bone to match, and the box's layout of blocks)
            roi_img = None if roi is None else weight_img if match == "soft" else match_weight(fixed_img, roi)
            params, replaced, signals = self._confidence(fixed_img, moving_img, fov_img, fov_t, run, params, weights,
                                                         weight_img, roi_img, native, staged and not refine,
                                                         details, early_swap)
            if early_swap is not None:
                timings["swap_estimate"] = early_swap.seconds
            if replaced:
                net_params = params.copy()
            timings["confidence"] = time.perf_counter() - t
            confidence = signals.pop("confidence")
            not_hu_inputs = [name for name, (_, certain) in checked.items() if certain]
            if not_hu_inputs:
                # the signals are calibrated on HU images: on others they can pass a gross failure (a uint8 export of
                # a bench_speed CBCT registered about 24 mm off scored 0.58), so such a result is flagged whatever
                # they say
                signals["not_hu"] = not_hu_inputs
                confidence = 0.0
            flagged = confidence < CONFIDENCE_THRESHOLD
            details["signals"] = signals
            if flagged:
                logger.warning("registration flagged as a likely failure (confidence %.2f): check the QC figure",
                               confidence)

        registered = None
        if resample_moving:
            t = time.perf_counter()
            registered = resample(moving_img, fixed_img, params_to_sitk(params, grid_center))
            timings["resample"] = time.perf_counter() - t
        # report about the fixed image centre (the project's convention); the network grid may be centred elsewhere
        fixed_center = fixed_grid.center()
        params = recenter_params(params, grid_center, fixed_center)
        net_fixed = recenter_params(net_params, grid_center, fixed_center)
        details["network_params"] = {n: float(v) for n, v in zip(PARAM_NAMES, net_fixed)}
        if "refine" in details:
            details["refine"]["change"] = {n: float(v) for n, v in zip(PARAM_NAMES, params - net_fixed)}
        timings["total"] = time.perf_counter() - t_start
        return RegistrationResult(params, fixed_center, registered, timings, confidence, flagged, details)


class _Background:
    """``fn(*args, **kwargs)`` in a worker thread; :meth:`result` waits for it and returns its value or raises its
    exception. PyTorch and SimpleITK release the GIL in their kernels, so the global search's FFTs and sampling run
    while the main thread runs the network from the identity: on the ``bench_speed.py`` pairs the in-process median
    1.81 -> 1.56 s, beside a busy loop 2.32 -> 2.06 s, beside a second registration 2.46 -> 2.38 s
    (``bench_speed_0.4.6_*``). Since 0.4.7 the confidence check's swapped-input network run goes beside the last level
    the same way (thread ``monai-rigidreg-swap``; in-process 1.64 -> 1.43 s, ``bench_speed_0.4.7_2026-12-03.txt``).
    torch's intra-op thread count carries over to the worker thread."""

    def __init__(self, fn: Callable[..., Any], *args: Any, thread_name: str = "monai-rigidreg-worker",
                 **kwargs: Any) -> None:
        self._value: Any = None
        self._error: BaseException | None = None
        self.seconds = 0.0  # how long fn ran

        def run() -> None:
            t = time.perf_counter()
            try:
                self._value = fn(*args, **kwargs)
            except BaseException as exc:  # noqa: BLE001 - handed to the caller by result()
                self._error = exc
            self.seconds = time.perf_counter() - t

        self._thread = threading.Thread(target=run, name=thread_name, daemon=True)
        self._thread.start()

    def result(self) -> Any:
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value

    def wait(self) -> None:
        """Wait for the worker to finish, its result or error dropped (the caller is raising its own)."""
        self._thread.join()


@dataclass
class _Run:
    """One network run from a start (:meth:`RigidRegistrar._run_from`): its grid and tensors, the start and the
    residual (mm/deg about the grid centre) and the total fixed -> moving matrix (LPS mm)."""

    grid: Grid
    fixed_t: torch.Tensor
    moving_t: torch.Tensor
    start: np.ndarray
    residual: np.ndarray
    total: np.ndarray

    @property
    def sampling(self) -> np.ndarray | None:
        """The matrix the CBCT was sampled through onto ``grid`` (``None`` for the identity start)."""
        return None if np.allclose(self.start, np.eye(4)) else self.start


EARLY_SWAP_MAX_CHANGE_MM = 1.0
"""The confidence check's swapped-input estimate, started beside the last level with the CT masked by the field of
view as the network's estimate places it, is used when the last level moved that estimate by at most this (mm,
``details.native_level.change_mm``, the mean over the network grid's points); beyond it the twin is computed again
from the refined estimate (``details.swap_estimate``: ``"beside the last level"`` or ``"after the last level"``).
On the clinical-geometry pairs the last level moves a converged estimate by a few tenths of a millimetre."""


SAME_POSE_MM = 2.0
"""The network from the search's best candidate and from the identity reached the same pose when the mean distance
between the network-grid points their estimates map is below this (mm): the further candidates are then skipped.
Converged estimates of one pose differ by a fraction of a millimetre and different poses by several millimetres or
more (``details.global_search.best_start_to_identity_estimate_mm`` records it per case); with this rule every
clinical-geometry pair of seeds 1500 and 2500 ends as it did with all four starts
(``benchmarks/results/bench_clinical_geometry_0.4.6_network_*``)."""


HU_AIR_LIMIT = -500.0
"""A CT or CBCT in HU holds air (about -1000 HU) somewhere: an image whose minimum lies above this is probably not in
HU (or is cropped to the body)."""
EIGHT_BIT_RANGE = 256.0
"""An image whose intensities span at most this many units is an 8-bit export (or a normalized image), never a CT
in HU: tissue alone spans fat (-100 HU) to bone (several hundred HU)."""


def check_intensities(image: sitk.Image, name: str, hu_range: tuple[float, float] = (-1000.0, 2000.0)) -> list[str]:
    """Check that ``image`` can be registered as a CT/CBCT in Hounsfield units.

    Returns:
        warnings (also logged): an intensity range that is not HU, or may not be (no air: e.g. a uint8 or int8
        export, a normalized or raw-detector image, or a CT cropped to the body), which the network, trained on
        HU, reads as something else. See :func:`not_hu` for the ranges that are certainly not HU.

    Raises:
        InputError: the image is constant (every voxel the same value, e.g. all zero): nothing to register.
    """
    return _check_hu(image, name, hu_range)[0]


def not_hu(lo: float, hi: float) -> bool:
    """Whether an intensity range ``[lo, hi]`` is certainly not a CT or CBCT in HU: no negative value (an unsigned
    export, raw detector units, or HU stored without the rescale intercept) or a span of at most
    :data:`EIGHT_BIT_RANGE`. A range from about -100 HU up, without air, may be a CT cropped to the body: not this."""
    return lo >= 0.0 or hi - lo <= EIGHT_BIT_RANGE


def _check_hu(image: sitk.Image, name: str, hu_range: tuple[float, float]) -> tuple[list[str], bool]:
    """:func:`check_intensities`' warnings and whether the range is certainly not HU (:func:`not_hu`)."""
    stats = sitk.MinimumMaximumImageFilter()
    stats.Execute(image)
    lo, hi = stats.GetMinimum(), stats.GetMaximum()
    if not hi > lo:
        raise InputError(f"the {name} image is constant (every voxel is {lo:g}): there is nothing to register")
    if lo <= HU_AIR_LIMIT:
        return [], False
    if not_hu(lo, hi):
        msg = (f"the {name} image's intensities range from {lo:g} to {hi:g}, which is not HU (CT air is about -1000; "
               f"the network maps {hu_range[0]:g}..{hu_range[1]:g} HU to its input range): convert it to HU first "
               "(e.g. rescale slope/intercept); the result is flagged")
    else:
        msg = (f"the {name} image holds no air: its intensities range from {lo:g} to {hi:g} (air is about -1000 HU): "
               "if it is not in HU, convert it first; a CT cropped to the body can look like this")
    logger.warning("%s", msg)
    return [msg], not_hu(lo, hi)


_DEFAULT_REGISTRARS: dict[tuple[str, str], RigidRegistrar] = {}


def register(
    fixed: sitk.Image | str | Path,
    moving: sitk.Image | str | Path,
    *,
    model: nn.Module | RigidRegistrar | None = None,
    bundle: str | Path | None = None,
    device: str | torch.device | None = "auto",
    cascade_steps: int | None = None,
    refine: bool = False,
    resample_moving: bool = True,
    moving_fov: sitk.Image | None = None,
    fine_stage: bool | None = None,
    global_init: bool | None = None,
    roi: RoiLike = None,
    match: str = "soft",
    keep_couch: bool = False,
) -> RegistrationResult:
    """Rigidly register a CBCT (``moving``) to a planning CT (``fixed``).

    Args:
        fixed: planning CT: path (NIfTI, MetaImage, NRRD, DICOM directory) or ``SimpleITK.Image`` (HU).
        moving: CBCT, likewise; any grid, spacing, origin, direction and field of view overlapping the CT.
        model: a :class:`RigidRegistrar` built once (:meth:`RigidRegistrar.from_bundle`), or a bare network (on the
            shipped bundle's network grid), or ``None`` for the shipped (or ``bundle``'s) network, loaded once per
            bundle and device and kept for later calls.
        bundle: MONAI bundle directory to load the network from (default: the shipped ``cbct_ct_rigid``).
        device: ``"auto"`` (CUDA if available), ``"cpu"``, ``"cuda"``...
        cascade_steps: network applications (default: the bundle's setting).
        refine: polish the network estimate with SimpleITK Mattes-MI (Euler3D, masked to the CBCT FOV).
        resample_moving: also return the CBCT resampled onto the CT grid.
        moving_fov: mask of the CBCT field of view on the CBCT grid (default: inscribed cylinder).
        fine_stage: ``False`` measures the learned network alone: the regression's estimate, without the
            Gauss-Newton stage, search, multi-start or optimizer (``refine`` adds its optimizer, so keep it off for
            that). Also with ``model=`` a registrar built once. ``None`` (default): as the network is configured
            (the shipped bundle: on). ``details["fine_stage"]`` records what ran.
        global_init: the global search for large offsets (translations over +-72 mm for 27 rotation
            candidates, :mod:`monai_rigidreg.global_init`): the network also starts from the search's best
            candidates (the registrar's ``search_starts``) when the best one disagrees with the estimate from the
            identity, and the estimate whose CBCT field of view matches the CT best is kept (``details["start"]``
            says which: ``"identity"`` or ``"search"``). ``None``
            (default): on, except with ``fine_stage=False`` (the learned network alone); ``False``: off. The
            confidence check's swapped-input estimate is a third candidate: when it disagrees by more than
            :data:`~monai_rigidreg.confidence.SWAP_AGREE_MM` and matches better, it replaces the estimate (after its
            own last level; ``details["start"] == "swapped"``; not with ``refine`` or ``fine_stage=False``), and
            when it matches worse its disagreement does not lower the confidence (``details["swap_check"]``).
        roi: restrict the match to a region of the CT: a box ``(x0, y0, z0, x1, y1, z1)`` in CT LPS mm or a mask
            image (non-zero inside) on the CT's physical space (:mod:`monai_rigidreg.match_region`).
        match: ``"soft"`` (all tissue, default) or ``"bone"`` (the CT's bone and a few mm around it).
        keep_couch: by default the couches (which do not move with the patient) are excluded from the match: the
            CT's tissue-like voxels outside its body (:func:`~monai_rigidreg.body.coarse_body_mask`, 4 mm beyond the
            skin) count as air, and the match weight is zero outside that body, so the CBCT's couch meets no weight
            wherever an estimate puts it. ``True`` keeps them, and so does ``fine_stage=False`` (the learned network
            alone on the inputs as they are).

    Returns:
        :class:`RegistrationResult` with ``params`` (mm/deg, fixed -> moving, about the fixed image centre),
        ``transform`` (``Euler3DTransform``), ``registered``, ``timings`` and ``confidence``.

    Raises:
        InputError: bad input, e.g. both paths naming the same file or the same DICOM series, or a constant
            image.
    """
    if isinstance(fixed, (str, Path)) and isinstance(moving, (str, Path)):
        check_distinct_inputs(fixed, moving)
    if isinstance(model, RigidRegistrar):
        registrar = model
    elif isinstance(model, nn.Module):
        registrar = RigidRegistrar(model, device=device)
    else:
        key = (str(bundle), str(resolve_device(device)))
        if key not in _DEFAULT_REGISTRARS:
            _DEFAULT_REGISTRARS[key] = RigidRegistrar.from_bundle(bundle, device=device)
        registrar = _DEFAULT_REGISTRARS[key]
    return registrar(fixed, moving, refine=refine, cascade_steps=cascade_steps, resample_moving=resample_moving,
                     moving_fov=moving_fov, fine_stage=fine_stage, global_init=global_init, roi=roi, match=match,
                     keep_couch=keep_couch)


@contextlib.contextmanager
def fine_stage_switch(network: nn.Module, enabled: bool | None) -> Iterator[None]:
    """Run ``network`` with its fine stage on or off for the duration of the block (a
    :class:`~monai_rigidreg.networks.TwoStageRigidNet`'s ``fine_stage_enabled``; other networks, and ``enabled=None``,
    leave it as it is), and restore the setting afterwards, whatever happens."""
    if enabled is None or not hasattr(network, "fine_stage_enabled"):
        yield
        return
    before = network.fine_stage_enabled
    network.fine_stage_enabled = bool(enabled)
    try:
        yield
    finally:
        network.fine_stage_enabled = before


def _check_steps(steps: Any) -> int:
    """``steps`` as an int >= 1, else :class:`~monai_rigidreg.errors.InputError` naming the value."""
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or int(steps) < 1:
        raise InputError(f"cascade_steps must be a whole number >= 1, got {steps!r}")
    return int(steps)
