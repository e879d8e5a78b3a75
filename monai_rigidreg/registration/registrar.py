"""Register a CBCT (moving) to a planning CT (fixed): :class:`RigidRegistrar`, its stages in call order.

The data flow (``docs/architecture.md``): the volumes are read once (:mod:`monai_rigidreg.registration.inputs`),
both are resampled once onto the network grid placed on the CBCT (:mod:`monai_rigidreg.registration.network_run`,
the same resampling and normalization as training), the network returns six parameters about that grid's centre,
and the result is re-expressed about the fixed (CT) image centre, the project's convention (``docs/conventions.md``);
its ``Euler3DTransform`` resamples the original, full-resolution CBCT onto the CT grid.

Stages, one method each, sharing one :class:`~monai_rigidreg.registration.state.RegistrationState`; the methods of
stages 3-5 and 8 are defined with their concern (:class:`~monai_rigidreg.registration.search.StartChoice`,
:class:`~monai_rigidreg.registration.network_run.NetworkRuns`,
:class:`~monai_rigidreg.registration.confidence.ConfidenceStage`, which ``RigidRegistrar`` derives from), the others
here:

1. :meth:`RigidRegistrar._read` - the inputs (:mod:`.inputs`), the match region (:mod:`.match_region`) and the
   CBCT's field of view;
2. :meth:`RigidRegistrar._exclude_couch` - the CT's body and its couch (:mod:`.body`);
3. :meth:`RigidRegistrar._start_search` - the global search in a worker thread (:mod:`.search`);
4. :meth:`RigidRegistrar._run_identity` - the network from the identity (:mod:`.network_run`);
5. :meth:`RigidRegistrar._choose_start` - the network from the search's candidates, the best start kept
   (:mod:`.search`);
6. :meth:`RigidRegistrar._last_level` - the last Gauss-Newton level at native resolution (:mod:`.last_level`);
7. :meth:`RigidRegistrar._refine` - the classical refinement, with ``refine`` (:mod:`.classical`);
8. :meth:`RigidRegistrar._assess` - the confidence (:mod:`.confidence`, :mod:`.region_check`);
9. :meth:`RigidRegistrar._result` - the CBCT resampled, the estimate re-expressed about the CT centre.

That is the thorough path (``thorough=True``, ``network_leads=False``, and every call with ``refine``). By default
the network leads (:class:`~monai_rigidreg.registration.lead.LeadPath`): stages 4 and 6 and a cheap check; stages 3
and 5 and stage 8's swapped-input estimate run only as the fallback where the check fails (``details["fallback"]``).

>>> import SimpleITK as sitk
>>> from monai_rigidreg.simulation.toy import blob_ct
>>> ct = blob_ct()  # a CT-like test object in HU, 96 mm wide
>>> cbct = sitk.Resample(ct, ct, sitk.TranslationTransform(3, (-4.0, 0.0, 0.0)), sitk.sitkLinear, -1000.0)
>>> registrar = RigidRegistrar.from_bundle(device="cpu")  # once; then one call per pair
>>> result = registrar(ct, cbct, resample_moving=False)
>>> [int(round(v)) for v in result.params]  # the CBCT shows the CT's content moved by +4 mm along x
[4, 0, 0, 0, 0, 0]
>>> result.center.tolist()  # the parameters are about the CT's centre (LPS mm)
[0.0, 0.0, 0.0]
"""

from __future__ import annotations

import contextlib
import dataclasses
import inspect
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch
from torch import nn

from monai_rigidreg.bundle.loader import default_bundle_path, load_bundle_network
from monai_rigidreg.core.device import adapted_cpu_threads, resolve_device
from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import (
    PARAM_NAMES,
    grid_points,
    params_to_sitk,
    recenter_params,
    target_registration_error,
)
from monai_rigidreg.core.network_grid import NetworkGridSpec
from monai_rigidreg.export.provenance import bundle_record
from monai_rigidreg.io.volumes import resample
from monai_rigidreg.registration.body import BodyMaskCache
from monai_rigidreg.registration.calibration import UNCALIBRATED_MEANING, load_calibration
from monai_rigidreg.registration.classical import register_sitk
from monai_rigidreg.registration.confidence import LOCAL_GAIN_LIMIT, ConfidenceStage, cylindrical_fov_mask
from monai_rigidreg.registration.inputs import check_cascade_steps, read_inputs
from monai_rigidreg.registration.last_level import EARLY_SWAP_MAX_CHANGE_MM, FINE_STAGE_CHOICE_MM, LastLevelStage
from monai_rigidreg.registration.lead import LeadPath
from monai_rigidreg.registration.match_region import RoiLike, match_weight, parse_roi
from monai_rigidreg.registration.network_run import NetworkRuns
from monai_rigidreg.registration.overlap import OverlapStage
from monai_rigidreg.registration.result import RegistrationResult
from monai_rigidreg.registration.search import StartChoice
from monai_rigidreg.registration.state import Background, RegistrationOptions, RegistrationState

__all__ = ["RigidRegistrar", "fine_stage_switch", "EARLY_SWAP_MAX_CHANGE_MM"]

logger = logging.getLogger(__name__)




class RigidRegistrar(NetworkRuns, StartChoice, LastLevelStage, OverlapStage, ConfidenceStage, LeadPath):
    """A loaded network plus its preprocessing settings, reusable across many registrations.

    Args:
        network: module mapping ``[B, 2, x, y, z]`` (moving, fixed; intensities normalized) to ``[B, 6]``, e.g. the
            shipped :class:`~monai_rigidreg.networks.TwoStageRigidNet` (regression + fine stage).
        network_size: network grid size in voxels (default: the shipped bundle's, see ``network_spacing``).
        network_spacing: network grid spacing in mm. Both default to the shipped bundle's
            (:meth:`~monai_rigidreg.core.network_grid.NetworkGridSpec.from_bundle`): a checkpoint is tied to its
            grid, so give the sizes of the bundle the network came from. A fine stage built for another spacing is
            refused.
        cascade_steps: network applications (1 = single pass, the bundle's setting; each further step estimates a
            correction on the CBCT warped by the running estimate).
        device: ``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:N"``.
        hu_range: HU window mapped to [0, 1] before the network (as in training).
        inferer: optional MONAI ``Inferer`` (``inferer(inputs [B, 2, x, y, z], network) -> [B, 6]``) through which
            every network application runs (the bundle's ``inferer``: ``SimpleInferer``); ``None`` calls the network.
        global_init: run the global search for large offsets by default (:mod:`monai_rigidreg.registration.search`:
            the network also starts from its best candidates when they disagree with the estimate from the
            identity, ``search_starts``); a call's ``global_init`` overrides.
        search_settings: keyword arguments of :func:`~monai_rigidreg.registration.search.global_search`
            (``spacing_mm``, ``max_translation_mm``, ``rotations_deg``, ...).
        search_starts: when the estimate from the identity and the search's best candidate disagree, the network
            also starts from this many of the best-scoring candidates (from the best one first, and from the others
            only when that run does not end at the identity's pose, :data:`SAME_POSE_MM`) and the estimate whose
            CBCT field of view matches the CT best goes on (the search's score ranks rotations by a coarse
            correlation that a head's near-symmetric outline can fool; the network from a candidate within its
            capture range reaches a much better match). The constructor's default, 1, is the best candidate alone;
            the shipped bundle's ``search_starts`` is 4 (``docs/results.md``).
        native_level: after the network's fine stage, one more Gauss-Newton level over the whole CBCT field of view
            at the inputs' own resolution (:func:`~monai_rigidreg.registration.last_level.refine_native`); skipped
            when the fine stage is off (the learned network alone). On by default; ``--no-native-level`` turns it
            off (what it changes: ``docs/results.md``).
        native_bias_degree: the intensity bias the last level estimates with the pose over the whole field of view
            (a polynomial of this degree per feature channel,
            :func:`~monai_rigidreg.networks.gauss_newton.gauss_newton_align`; -1: none). The constructor's default
            (2, the fine stage's) is kept for code that builds a registrar by hand; the shipped bundle's
            ``native_bias_degree`` is 0: without a region of interest a constant is more precise, and it absorbs a
            CBCT's HU offset from the CT.
        native_bias_degree_roi: the same with a match region (``--roi``, ``--match bone``); ``None``: the same as
            ``native_bias_degree`` (the bundle's ``native_bias_degree_roi``, 2, is used by ``from_bundle`` unless
            overridden too): with a region on deformed anatomy the quadratic is more precise.
        native_highpass_sigma_mm: the Gaussian (mm) of the last level's local-contrast feature (``None``: the fine
            stage's, 16 mm, which the network grid was tuned with; the bundle's ``native_highpass_sigma_mm`` is 4:
            at the inputs' own resolution the finer contrast aligns better).
        network_leads: the network-led path (:mod:`monai_rigidreg.registration.lead`: the network from the identity,
            the last level, a cheap check, and the global search, further starts and swapped-input estimate only
            where the check fails) whenever the last level runs and ``refine`` is off; ``False``: the thorough path
            on every call (the search beside the network, the swapped-input estimate beside the last level), as a
            call's ``thorough=True`` asks for one call. Default ``True`` (the bundle's ``network_leads``).
        native_max_voxels: the last level's grid holds at most this many voxels (its spacing grows by 1.25x steps from
            the inputs' finer spacing until it does, :func:`~monai_rigidreg.registration.last_level.native_grid`).
        native_final_norm_mm: a candidate against the CBCT's shading bias (off by default, ``None``): once the last
            level has converged, one more pass on the local contrast normalised over a Gaussian of this sigma (mm)
            without the intensity channel, kept where it moves the estimate by at most
            :data:`~monai_rigidreg.registration.last_level.FINAL_NORM_MAX_MM` (``details.native_level.final_pass``).
        lead_passes: ``(8 mm, 4 mm)`` passes of a ``ContextCorrelationNet``'s learned levels where the fine stage
            follows (the default path and its fallback; the bundle's: ``[2, 1]``, ``docs/results.md``); ``None``: the
            network's own (``network_def.regression.passes``, which the network alone, ``fine_stage=False``, keeps).
        fine_stage_choice_mm: the fine-stage choice's limit (mm; ``None``: off;
            :meth:`~monai_rigidreg.registration.last_level.LastLevelStage._fine_stage_choice`, the default
            :data:`~monai_rigidreg.registration.last_level.FINE_STAGE_CHOICE_MM`).

    ``lead_fallback`` (attribute, default ``True``): ``False`` records the network-led path's check without running
    its fallback (``python -m benchmarks.accuracy.bench_lead_check`` measures the check that way).

    ``adapt_threads`` (attribute, default ``True``): on the CPU each call runs with torch's and SimpleITK's thread
    counts lowered by the cores other work keeps busy as it starts
    (:func:`~monai_rigidreg.core.device.adaptive_threads`; beside a busy loop on 2 cores, one thread is faster than
    two) and restored afterwards; ``details["cpu_threads"]`` records the count used. ``False`` keeps the counts as
    set (``monai-rigidreg register --threads N`` does).

    Build it once and reuse it: ``registrar = RigidRegistrar.from_bundle()`` then
    ``monai_rigidreg.register(ct, cbct, model=registrar)`` (or ``registrar(ct, cbct)``; the module's example).
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
        network_leads: bool = True,
        native_max_voxels: int = 1_500_000,
        native_final_norm_mm: float | None = None,
        lead_passes: Sequence[int] | None = None,
        fine_stage_choice_mm: float | None = FINE_STAGE_CHOICE_MM,
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
        self.cascade_steps = check_cascade_steps(cascade_steps)
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
        # a regression with a CT context (ContextCorrelationNet) also gets the CT on its context grid
        self.context_grid_spec = None
        if getattr(regression, "takes_context", False):
            self.context_grid_spec = NetworkGridSpec(regression.context_size,
                                                     [s * regression.context_factor for s in self.grid_spec.spacing])
        # one registration at a time per registrar: fine_stage_switch changes the shared network's setting
        self._lock = threading.RLock()
        self._workers: list[Background] = []  # this call's worker threads: all joined before __call__ returns
        self.adapt_threads = True
        self._bodies = BodyMaskCache()  # the CT's body mask, computed once per planning CT
        self.source: dict[str, Any] = {}  # the bundle and weights it came from (from_bundle), for the audit trail
        self.antialias = True  # as ResampleToNetworkGrid's default, the training preprocessing
        # what the confidence means: the shipped calibration (signals -> probability), any network's (from_bundle:
        # the bundle's own where it has one); None: the uncalibrated rule score
        self.calibration = load_calibration()
        self.network_leads = bool(network_leads)
        if int(native_max_voxels) < 512:
            raise InputError(f"native_max_voxels must be >= 512, got {native_max_voxels}")
        self.native_max_voxels = int(native_max_voxels)
        if native_final_norm_mm is not None and not float(native_final_norm_mm) > 0:
            raise InputError(f"native_final_norm_mm must be > 0 mm (or None), got {native_final_norm_mm}")
        self.native_final_norm_mm = None if native_final_norm_mm is None else float(native_final_norm_mm)
        self.lead_fallback = True
        if lead_passes is not None and (len(lead_passes) != 2 or min(int(p) for p in lead_passes) < 0):
            raise InputError(f"lead_passes must be two pass counts >= 0 (8 mm, 4 mm), got {lead_passes}")
        self.lead_passes = None if lead_passes is None else tuple(int(p) for p in lead_passes)
        if fine_stage_choice_mm is not None and not float(fine_stage_choice_mm) >= 0:
            raise InputError(f"fine_stage_choice_mm must be >= 0 mm (or None), got {fine_stage_choice_mm}")
        self.fine_stage_choice_mm = None if fine_stage_choice_mm is None else float(fine_stage_choice_mm)

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
        registrar.calibration = load_calibration(bundle)
        return registrar


    def __call__(self, fixed: sitk.Image | str | Path, moving: sitk.Image | str | Path, refine: bool = False,
                 cascade_steps: int | None = None, resample_moving: bool = True, moving_fov: sitk.Image | None = None,
                 assess: bool = True, fine_stage: bool | None = None, global_init: bool | None = None,
                 roi: RoiLike = None, match: str = "soft", keep_couch: bool = False,
                 allow_swapped: bool = False, thorough: bool | None = None) -> RegistrationResult:
        """Register ``moving`` (CBCT) to ``fixed`` (CT); see :func:`~monai_rigidreg.registration.register`
        (``fine_stage=False``: the learned regression alone, also in the confidence check's swapped-input estimate,
        and no global search; ``None``: as the network is configured, e.g. by the bundle's ``fine_stage``;
        ``thorough``: the thorough path instead of the network-led one, ``None``: as ``network_leads`` says)."""
        with self._lock, fine_stage_switch(self.network, fine_stage, self.lead_passes), \
                self._cpu_threads() as threads:
            if global_init is None:
                global_init = self.global_init and fine_stage is not False
            if fine_stage is False:  # the learned network alone sees the inputs as they are (no couch removal)
                keep_couch = True
            if thorough is None:
                thorough = not self.network_leads
            self._workers = []
            try:
                result = self._register(fixed, moving, RegistrationOptions(
                    refine, cascade_steps, resample_moving, moving_fov, assess, bool(global_init), roi, match,
                    keep_couch, bool(allow_swapped), bool(thorough)))
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
        :func:`~monai_rigidreg.core.device.adapted_cpu_threads`); the context yields the torch count in use on the
        CPU, ``None`` on another device."""
        if self.device.type != "cpu":
            return contextlib.nullcontext(None)
        return adapted_cpu_threads(self.adapt_threads)

    def _in_background(self, fn: Callable[..., Any], *args: Any, thread_name: str, **kwargs: Any) -> Background:
        """``fn`` started in a worker thread and registered with this call, whose end joins it (:meth:`__call__`)."""
        worker = Background(fn, *args, thread_name=thread_name, **kwargs)
        self._workers.append(worker)
        return worker

    # -- the stages, in call order ---------------------------------------------------------------------------------
    def _register(self, fixed: sitk.Image | str | Path, moving: sitk.Image | str | Path,
                  options: RegistrationOptions) -> RegistrationResult:
        state = self._read(fixed, moving, options)
        self._exclude_couch(state)
        if state.native and not (options.thorough or options.refine):
            self._lead(state)  # the network-led path: stages 3, 5 and 8's swap only as its fallback (lead.py)
            return self._result(state)
        state.details["path"] = "thorough"
        searching = self._start_search(state)
        self._run_identity(state)
        self._choose_start(state, searching)
        self._within_ct(state, state.run.total, pose=False)  # the CT covers the CBCT under this estimate?
        self._last_level(state)
        self._refine(state)
        self._assess(state)
        return self._result(state)

    def _read(self, fixed: sitk.Image | str | Path, moving: sitk.Image | str | Path,
              options: RegistrationOptions) -> RegistrationState:
        """Stage 1: both images read and checked (:func:`~monai_rigidreg.registration.inputs.read_inputs`), the
        match region's weight on the CT, which stages run, and the CBCT's field of view where a stage needs it (the
        refinement, the confidence signals, the global search and the last level)."""
        t_start = time.perf_counter()
        inputs = read_inputs(fixed, moving, self.hu_range, allow_swapped=options.allow_swapped)
        state = RegistrationState(options, inputs, t_start)
        state.timings["load"] = time.perf_counter() - t_start
        roi = parse_roi(options.roi)  # once: a mask file is read here
        state.options = options = dataclasses.replace(options, roi=roi)
        state.weight_img = match_weight(inputs.fixed, roi, options.match)
        state.staged = getattr(self.network, "fine_stage", None) is not None and getattr(
            self.network, "fine_stage_enabled", True)  # False: the learned network alone
        state.native = self.native_level and state.staged
        if options.refine or options.assess or options.global_init or state.native:
            state.fov_img = (cylindrical_fov_mask(inputs.moving) if options.moving_fov is None
                             else options.moving_fov)
        self._sample_fov(state)  # an empty field of view is refused here
        return state

    def _exclude_couch(self, state: RegistrationState) -> None:
        """Stage 2: the couches do not move with the patient: unless ``keep_couch``, the CT's tissue-like voxels
        outside its body become air, and the match weight is zero there, so the CBCT's couch, wherever an estimate
        puts it, meets no weight (a CBCT's own body mask is not used: a lung cut by its field of view breaks it).
        Also which weights the pose search uses: with a match region and the last level to apply it, the pose is
        found over the whole field of view (the network's starts, the search and the choice between them) and the
        region weights the last level (and the confidence's edge test): a small region on deformed or flat anatomy
        is no place to search for the pose (``docs/results.md``, "Clinical geometry")."""
        if not state.options.keep_couch:
            t = time.perf_counter()
            hits = self._bodies.hits
            state.body = self._bodies(state.inputs.fixed)
            state.timings["body"] = time.perf_counter() - t
            state.body_cached = self._bodies.hits > hits
        state.weights = [w for w in (state.weight_img, state.body) if w is not None]
        state.region_last = state.weight_img is not None and state.native
        state.pose_weights = ([w for w in (state.body,) if w is not None] if state.region_last
                              else state.weights)
        # where the CT leaves part of the CBCT's tissue uncovered, the match stays inside the CT's box
        # (registration.overlap); pairs the CT covers are matched as before
        self._within_ct(state, None, pose=True)

    def _run_identity(self, state: RegistrationState) -> None:
        """Stage 4: the network from the identity, and the details that describe the call."""
        options = state.options
        state.run = self._run_from(state.inputs.fixed, state.inputs.moving, np.eye(4), options.cascade_steps,
                                   state.pose_weights, state.timings, state.body)
        details = state.details
        details.update({"network_params": {},
                        "cascade_steps": self.cascade_steps if options.cascade_steps is None else options.cascade_steps,
                        "device": str(self.device), "start": "identity", "couch_excluded": state.body is not None})
        if not options.keep_couch:
            details["body_mask"] = "cached" if state.body_cached else "computed"
        region = options.roi is not None or options.match != "soft"
        if region and not state.region_last and not self.accepts_weight:
            details.setdefault("warnings", []).append(
                "this network takes no match-region weight and the last level is off: the region of interest / bone "
                "match only scopes the choice between starts and the confidence check")
        if region:
            roi = options.roi
            details["match_region"] = {
                "roi": "mask" if isinstance(roi, sitk.Image) else list(roi) if roi else None, "match": options.match,
                "applied_to": "last level" if state.region_last else "network" if self.accepts_weight
                else "choice of start"}
        if state.inputs.warnings:
            details.setdefault("warnings", []).extend(state.inputs.warnings)

    def _refine(self, state: RegistrationState) -> None:
        """Stage 7, with ``refine``: SimpleITK Mattes MI (:func:`~monai_rigidreg.registration.classical.register_sitk`)
        from the estimate, on the original images, masked to the CBCT's field of view. A network estimate that looks
        wrong can drag the optimizer into a wrong basin: then the optimizer also starts from the identity and the
        lower (better) Mattes MI value wins. Records ``details.refine``."""
        if not state.options.refine:
            return
        run, grid_center = state.run, state.run.grid.center()

        def refine_from(start_params: np.ndarray) -> Any:
            return register_sitk(state.inputs.fixed, state.inputs.moving, initial_params=start_params,
                                 center=grid_center, moving_mask=state.fov_img, shrink_factors=(2, 1),
                                 smoothing_sigmas_mm=(1.0, 0.0))

        t = time.perf_counter()
        res, start_name = refine_from(state.net_params), "network"
        pre = self.assess(run.moving_t, run.fixed_t, run.grid, run.residual, state.fov_t, swap=False)
        if pre["local_gain"] > LOCAL_GAIN_LIMIT:
            alt_res = refine_from(np.zeros(6))
            if alt_res.metric < res.metric:
                res, start_name = alt_res, "identity"
        state.params = res.params
        state.timings["refine"] = time.perf_counter() - t
        state.details["refine"] = {
            "start": start_name,
            "change": {},
            "change_tre_mm": float(target_registration_error(state.params, state.net_params,
                                                             grid_points(run.grid, 4), center=grid_center)),
            "metric": res.metric,
            "stop_condition": res.stop_condition,
        }

    def _result(self, state: RegistrationState) -> RegistrationResult:
        """Stage 9: the CBCT resampled onto the CT grid (``resample_moving``) and the estimate re-expressed about the
        fixed image centre (the project's convention; the network grid may be centred elsewhere)."""
        grid_center, timings, details = state.run.grid.center(), state.timings, state.details
        registered = None
        if state.options.resample_moving:
            t = time.perf_counter()
            registered = resample(state.inputs.moving, state.inputs.fixed, params_to_sitk(state.params, grid_center))
            timings["resample"] = time.perf_counter() - t
        fixed_center = state.inputs.fixed_grid.center()
        params = recenter_params(state.params, grid_center, fixed_center)
        net_fixed = recenter_params(state.net_params, grid_center, fixed_center)
        details["network_params"] = {n: float(v) for n, v in zip(PARAM_NAMES, net_fixed)}
        if "refine" in details:
            details["refine"]["change"] = {n: float(v) for n, v in zip(PARAM_NAMES, params - net_fixed)}
        timings["total"] = time.perf_counter() - state.t_start
        calibration = self.calibration if state.options.assess else None
        meaning = "" if not state.options.assess else calibration.meaning if calibration else UNCALIBRATED_MEANING
        return RegistrationResult(params, fixed_center, registered, timings, state.confidence, state.flagged, details,
                                  confidence_meaning=meaning)


@contextlib.contextmanager
def fine_stage_switch(network: nn.Module, enabled: bool | None,
                      lead_passes: Sequence[int] | None = None) -> Iterator[None]:
    """Run ``network`` with its fine stage on or off for the duration of the block (a
    :class:`~monai_rigidreg.networks.TwoStageRigidNet`'s ``fine_stage_enabled``; other networks, and ``enabled=None``,
    leave it as it is) and, where the fine stage is then on, its regression with ``lead_passes`` (its ``passes``;
    :class:`RigidRegistrar`'s ``lead_passes``); restore both settings afterwards, whatever happens."""
    regression = getattr(network, "regression", None)
    before = getattr(network, "fine_stage_enabled", None), getattr(regression, "passes", None)
    if enabled is not None and before[0] is not None:
        network.fine_stage_enabled = bool(enabled)
    if lead_passes is not None and before[1] is not None and getattr(network, "fine_stage", None) is not None \
            and network.fine_stage_enabled:
        regression.passes = tuple(lead_passes)
    try:
        yield
    finally:
        if before[0] is not None:
            network.fine_stage_enabled = before[0]
        if before[1] is not None:
            regression.passes = before[1]
