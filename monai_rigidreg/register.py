"""Register a CBCT (moving) to a planning CT (fixed): network estimate, optional classical refinement, confidence.

Data flow (``shared/architecture.md``): the volumes are read once (:mod:`monai_rigidreg.io`), both are resampled
once onto the network grid (:class:`~monai_rigidreg.transforms.ResampleToNetworkGrid`, the same preprocessing as
training), the network (with ``cascade_steps`` refinements) returns six parameters about the fixed image centre,
and the resulting ``Euler3DTransform`` resamples the original, full-resolution CBCT onto the CT grid.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk
import torch
from monai.data import MetaTensor
from torch import nn

from monai_rigidreg.errors import InputError
from monai_rigidreg.geometry import (
    PARAM_NAMES,
    Grid,
    grid_points,
    invert_matrix,
    matrix_to_params,
    params_to_matrix,
    params_to_sitk,
    recenter_params,
    target_registration_error,
)
from monai_rigidreg.io import as_image, grids_overlap, resample
from monai_rigidreg.networks.alignment import erode, gradient_magnitude, pyramid
from monai_rigidreg.transforms.grid import resample_to_grid
from monai_rigidreg.warp import warp_volume_params

__all__ = [
    "RegistrationResult",
    "RigidRegistrar",
    "register",
    "resolve_device",
    "cylindrical_fov_mask",
    "fov_ncc",
    "CONFIDENCE_THRESHOLD",
    "register_files",
    "write_outputs",
    "confidence_score",
]

logger = logging.getLogger(__name__)

CONFIDENCE_THRESHOLD = 0.5
"""Results whose confidence falls below this are flagged as likely failures (see :func:`confidence_score`)."""
LOCAL_GAIN_LIMIT = 0.01
"""Edge-alignment gain (see :func:`confidence_score`) above which an estimate is treated as likely wrong."""
EDGE_SPACING_MM = 4.0
"""Resolution (mm) at which :meth:`RigidRegistrar.assess` compares edges (finer network grids are pooled to it)."""


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    """``"auto"`` (or ``None``) -> CUDA when available, else CPU; anything else is passed to ``torch.device``."""
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"device {device!r} was asked for but CUDA is not available")
    return dev


@dataclass
class RegistrationResult:
    """Result of :func:`register`.

    Attributes:
        params: ``(tx, ty, tz, rx, ry, rz)`` mm / degrees, fixed -> moving, about ``center``.
        center: rotation centre (LPS mm): the fixed image centre.
        registered: the moving image resampled onto the fixed grid (``None`` if not asked for).
        timings: seconds per stage (``preprocess``, ``network``, ``refine``, ``confidence``, ``resample``,
            ``total``).
        confidence: score in [0, 1] (see :func:`confidence_score`); ``flagged`` when below the threshold.
        flagged: likely failure: check the QC figure.
        details: network-only parameters, refinement change, similarity before/after, swap consistency.
    """

    params: np.ndarray
    center: np.ndarray
    registered: sitk.Image | None = None
    timings: dict[str, float] = field(default_factory=dict)
    confidence: float = float("nan")
    flagged: bool = False
    details: dict[str, Any] = field(default_factory=dict)

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
            "runtime_s": {k: round(float(v), 4) for k, v in self.timings.items()},
            "confidence": float(self.confidence),
            "flagged": bool(self.flagged),
            "details": _jsonable(self.details),
        }


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return x


def cylindrical_fov_mask(image: sitk.Image, margin_mm: float = 2.0) -> sitk.Image:
    """uint8 mask of the largest cylinder (axis along the image's z index axis) inside the image's grid.

    CBCT scanners reconstruct a cylindrical field of view; outside it a CBCT holds no information, so similarity
    metrics (refinement, confidence) are restricted to this mask.
    """
    size = np.array(image.GetSize())
    spacing = np.array(image.GetSpacing())
    half = (size - 1) / 2.0
    radius_mm = float(min(half[0] * spacing[0], half[1] * spacing[1])) - margin_mm
    yy, xx = np.meshgrid(np.arange(size[1]), np.arange(size[0]), indexing="ij")
    r2 = ((xx - half[0]) * spacing[0]) ** 2 + ((yy - half[1]) * spacing[1]) ** 2
    disk = (r2 <= radius_mm**2).astype(np.uint8)
    arr = np.broadcast_to(disk, (size[2], size[1], size[0])).copy()
    mask = sitk.GetImageFromArray(arr)
    mask.CopyInformation(image)
    return mask


def fov_ncc(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    """Normalized cross-correlation of two ``[x, y, z]`` volumes over the voxels where ``mask`` > 0."""
    m = mask > 0
    if int(m.sum()) < 10:
        return float("nan")
    x = a[m].double()
    y = b[m].double()
    x = x - x.mean()
    y = y - y.mean()
    return float((x * y).sum() / (x.norm() * y.norm() + 1e-12))


def confidence_score(
    local_gain: float, swap_tre_mm: float, gain_ref: float = LOCAL_GAIN_LIMIT, tre_ref_mm: float = 3.0
) -> float:
    """Combine two failure signals into a score in [0, 1] (below 0.5: flagged).

    * ``local_gain``: how much the edge alignment (NCC of gradient magnitudes in the field of view) improves when
      the estimate is perturbed by half a network voxel or 2 degrees along any parameter. A correct estimate sits
      at the optimum (gain about 0); calibrated on simulated pairs, errors of about 3 mm or 10 degrees and more give
      gains above ``gain_ref`` (see ``tests/test_register.py``).
    * ``swap_tre_mm``: disagreement (mean TRE over the network grid, mm) between the forward estimate and the
      inverse of the estimate with the inputs swapped; ``tre_ref_mm`` gives 0.5.

    Each signal maps through a logistic to [0, 1]; the score is the smaller, so either failure mode flags.
    """
    s_gain = 1.0 / (1.0 + np.exp((local_gain - gain_ref) / 0.003)) if np.isfinite(local_gain) else 0.0
    s_swap = 1.0 / (1.0 + np.exp((swap_tre_mm - tre_ref_mm) / 0.75)) if np.isfinite(swap_tre_mm) else 1.0
    return float(min(s_gain, s_swap))


class RigidRegistrar:
    """A loaded network plus its preprocessing settings, reusable across many registrations.

    Args:
        network: module mapping ``[B, 2, x, y, z]`` (moving, fixed; intensities normalized) to ``[B, 6]``.
        network_size: network grid size in voxels.
        network_spacing: network grid spacing in mm.
        cascade_steps: network applications (1 = single pass; each further step estimates a correction).
        device: ``"auto"``, ``"cpu"``, ``"cuda"``, ...
        hu_range: HU window mapped to [0, 1] before the network (as in training).
    """

    def __init__(
        self,
        network: nn.Module,
        network_size: Sequence[int] = (64, 64, 64),
        network_spacing: Sequence[float] = (4.0, 4.0, 4.0),
        cascade_steps: int = 2,
        device: str | torch.device | None = "auto",
        hu_range: tuple[float, float] = (-1000.0, 2000.0),
    ) -> None:
        from monai_rigidreg.transforms import NormalizeHU, ResampleToNetworkGrid

        self.device = resolve_device(device)
        self.network = network.to(self.device).eval()
        self.network_size = tuple(int(s) for s in network_size)
        self.network_spacing = tuple(float(s) for s in network_spacing)
        self.cascade_steps = int(cascade_steps)
        self.hu_range = hu_range
        self._resampler = ResampleToNetworkGrid(self.network_size, self.network_spacing, padding_value=hu_range[0])
        self._normalize = NormalizeHU(a_min=hu_range[0], a_max=hu_range[1])

    @classmethod
    def from_bundle(
        cls, bundle: str | Path | None = None, device: str | torch.device | None = "auto", **overrides: Any
    ) -> RigidRegistrar:
        """Load the network and its settings from a MONAI bundle (default: the shipped ``cbct_ct_rigid``)."""
        from monai_rigidreg.bundle import load_bundle_network

        net, settings = load_bundle_network(bundle, device=resolve_device(device))
        settings.update(overrides)
        return cls(net, device=device, **settings)

    # -- stages ------------------------------------------------------------------------------------------------
    def network_grid(self, fixed: sitk.Image, moving: sitk.Image | None = None) -> Grid:
        """The network grid: axis-aligned LPS, centred on the CBCT (moving) centre, else on the fixed image centre.

        Centring on the CBCT keeps its field of view on the grid when the CT is much larger or the CBCT is off the
        CT centre (clinical geometry); in the simulated training pairs both centres are the isocentre. Estimates
        on this grid are about its centre; :meth:`__call__` re-expresses them about the fixed image centre.
        """
        ref = fixed if moving is None else moving
        return Grid.centered(self.network_size, self.network_spacing, Grid.from_sitk(ref).center())

    def preprocess(self, image: sitk.Image, grid: Grid) -> torch.Tensor:
        """``[1, x, y, z]`` normalized plain tensor of ``image`` on the network grid (the training preprocessing:
        :class:`~monai_rigidreg.transforms.ResampleToNetworkGrid` then :class:`~monai_rigidreg.transforms.NormalizeHU`).
        """
        out = self._normalize(self._on_grid(image, grid, "bilinear", self.hu_range[0]))
        return (out.as_tensor() if isinstance(out, MetaTensor) else out).float()

    def _on_grid(self, image: sitk.Image, grid: Grid, mode: str, padding_value: float) -> torch.Tensor:
        """``[1, x, y, z]`` float32 plain tensor of ``image`` resampled onto ``grid`` (no normalization).

        The ``[z, y, x]`` array is viewed as ``[x, y, z]`` without a copy, so for a CT much larger than the grid only
        the part the grid covers is transposed, and plain tensors skip ``MetaTensor`` bookkeeping in the network
        (``benchmarks/bench_inference_speed.py``: both volumes in 0.04 s instead of 0.20 s through
        ``sitk_to_metatensor`` and the MONAI transforms; the forward pass 0.105 s instead of 0.138 s).
        """
        if image.GetPixelID() != sitk.sitkFloat32:
            image = sitk.Cast(image, sitk.sitkFloat32)
        raw = torch.from_numpy(sitk.GetArrayFromImage(image)).permute(2, 1, 0)[None]
        return resample_to_grid(raw, Grid.from_sitk(image), grid, mode, "zeros", padding_value,
                                antialias=self._resampler.antialias)

    @torch.no_grad()
    def estimate(self, moving_t: torch.Tensor, fixed_t: torch.Tensor, grid: Grid, steps: int | None = None):
        """Network (+ cascade) estimate ``[6]`` (numpy, mm/deg about the grid centre) from preprocessed tensors."""
        from monai_rigidreg.networks import cascade_register

        k = self.cascade_steps if steps is None else int(steps)
        m = moving_t[None].to(self.device)
        f = fixed_t[None].to(self.device)
        params = cascade_register(self.network, m, f, grid, steps=k)
        return params[0].double().cpu().numpy()

    def assess(
        self, moving_t: torch.Tensor, fixed_t: torch.Tensor, grid: Grid, params: np.ndarray, fov: torch.Tensor,
        swap: bool = True,
    ) -> dict[str, float]:
        """Failure signals of an estimate ``params`` (mm/deg about the grid centre) on preprocessed tensors.

        Returns ``ncc_before``/``ncc_after`` (intensity NCC in the field of view), ``edge_ncc`` (NCC of gradient
        magnitudes), ``local_gain`` and ``swap_tre_mm`` (see :func:`confidence_score`) and ``confidence``.
        """
        p0 = np.asarray(params, dtype=np.float64)
        # edges are compared at about 4 mm (the grid pooled by ``factor``), where the gain threshold was calibrated:
        # finer grids see CBCT/CT edge differences (noise, blur) that shift the edge optimum by a fraction of a voxel
        factor = max(1, int(round(EDGE_SPACING_MM / min(grid.spacing))))
        steps = [0.5 * min(grid.spacing) * factor] * 3 + [2.0] * 3
        candidates = [p0]
        for i, step in enumerate(steps):
            for sign in (-1.0, 1.0):
                q = p0.copy()
                q[i] += sign * step
                candidates.append(q)
        with torch.no_grad():
            fixed_f = fixed_t[0].float()
            batch = torch.as_tensor(np.stack(candidates), dtype=torch.float32)
            moved0 = warp_volume_params(moving_t[None].float(), batch[:1], grid)[0, 0]
            fov_w = warp_volume_params(fov[None, None].float(), batch[:1], grid, mode="nearest")[0, 0]
            out = {"ncc_before": fov_ncc(moving_t[0], fixed_f, fov), "ncc_after": fov_ncc(moved0, fixed_f, fov_w)}
            # away from the field-of-view border: the CBCT's own edge there (data to zero) is no anatomy, and the
            # candidates move it by up to a pooled voxel (erosion radius: that step plus the gradient stencil)
            r = 2 * factor + 1
            fov_e = erode(fov_w[None, None], (r, r, r))
            # all candidates in one batched warp of the pooled volume on the pooled grid: [13, 1, x, y, z]
            moving_p, grid_p = pyramid(moving_t[None].float(), grid, factor)
            fixed_p, _ = pyramid(fixed_f[None, None], grid, factor)
            fov_e = (pyramid(fov_e, grid, factor)[0][0, 0] > 0.999).to(fov_w.dtype)
            moved = warp_volume_params(moving_p.expand(len(candidates), -1, -1, -1, -1), batch, grid_p)
            edges_f = gradient_magnitude(fixed_p[0, 0])
            edges_m = gradient_magnitude(moved[:, 0])
            scores = [fov_ncc(edges_m[k], edges_f, fov_e) for k in range(len(candidates))]
        edge, best = scores[0], max(scores)
        out["edge_ncc"] = edge
        out["local_gain"] = float(best - edge)
        if swap:
            # the CT restricted to the CBCT's field of view as placed by the estimate: a network with a fine stage
            # aligns only where its moving input has data, so an unmasked CT (data everywhere) against a truncated
            # CBCT would bias the swapped estimate even when the forward one is right
            masked_fixed = fixed_t * (fov_w > 0.5).to(fixed_t.dtype)[None]
            swapped = self.estimate(masked_fixed, moving_t, grid)
            inv = matrix_to_params(invert_matrix(params_to_matrix(swapped, grid.center())), grid.center())
            out["swap_tre_mm"] = float(target_registration_error(params, inv, grid_points(grid, 4),
                                                                 center=grid.center()))
        else:
            out["swap_tre_mm"] = float("nan")
        out["confidence"] = confidence_score(out["local_gain"], out["swap_tre_mm"])
        return out

    def __call__(
        self,
        fixed: sitk.Image | str | Path,
        moving: sitk.Image | str | Path,
        refine: bool = False,
        cascade_steps: int | None = None,
        resample_moving: bool = True,
        moving_fov: sitk.Image | None = None,
        assess: bool = True,
    ) -> RegistrationResult:
        """Register ``moving`` (CBCT) to ``fixed`` (CT); see :func:`register`."""
        t_start = time.perf_counter()
        timings: dict[str, float] = {}
        fixed_img = as_image(fixed, "fixed")
        moving_img = as_image(moving, "moving")
        timings["load"] = time.perf_counter() - t_start
        if not grids_overlap(Grid.from_sitk(fixed_img), Grid.from_sitk(moving_img)):
            raise InputError(
                "the CT (fixed) and CBCT (moving) do not overlap in physical space: check that both are in the "
                "same patient coordinate system (origins and directions)"
            )
        # the CBCT field of view is only needed by the refinement and the confidence signals
        fov_img = None
        if refine or assess:
            fov_img = cylindrical_fov_mask(moving_img) if moving_fov is None else moving_fov

        t = time.perf_counter()
        grid = self.network_grid(fixed_img, moving_img)
        fixed_t = self.preprocess(fixed_img, grid)
        moving_t = self.preprocess(moving_img, grid)
        timings["preprocess"] = time.perf_counter() - t

        t = time.perf_counter()
        net_params = self.estimate(moving_t, fixed_t, grid, cascade_steps)
        timings["network"] = time.perf_counter() - t
        center = grid.center()
        params = net_params.copy()
        # network_params and the refinement's change are filled in at the end, about the fixed image centre
        details: dict[str, Any] = {"network_params": {},
                                   "cascade_steps": self.cascade_steps if cascade_steps is None else cascade_steps,
                                   "device": str(self.device)}

        fov_t = None
        if refine or assess:
            fov_t = self._on_grid(fov_img, grid, "nearest", 0.0)[0]
        if refine:
            from monai_rigidreg.classical import register_sitk

            def refine_from(start_params: np.ndarray) -> Any:
                return register_sitk(fixed_img, moving_img, initial_params=start_params, center=center,
                                     moving_mask=fov_img, shrink_factors=(2, 1), smoothing_sigmas_mm=(1.0, 0.0))

            t = time.perf_counter()
            res, start = refine_from(net_params), "network"
            # safeguard: a network estimate that looks wrong can drag the optimizer into a wrong basin; then the
            # optimizer also starts from the identity and the lower (better) Mattes MI value wins
            pre = self.assess(moving_t, fixed_t, grid, net_params, fov_t, swap=False)
            if pre["local_gain"] > LOCAL_GAIN_LIMIT:
                alt = refine_from(np.zeros(6))
                if alt.metric < res.metric:
                    res, start = alt, "identity"
            params = res.params
            timings["refine"] = time.perf_counter() - t
            details["refine"] = {
                "start": start,
                "change": {},
                "change_tre_mm": float(target_registration_error(params, net_params, grid_points(grid, 4),
                                                                 center=center)),
                "metric": res.metric,
                "stop_condition": res.stop_condition,
            }

        confidence, flagged = float("nan"), False
        if assess:
            t = time.perf_counter()
            signals = self.assess(moving_t, fixed_t, grid, params, fov_t)
            timings["confidence"] = time.perf_counter() - t
            confidence = signals.pop("confidence")
            flagged = confidence < CONFIDENCE_THRESHOLD
            details["signals"] = signals
            if flagged:
                logger.warning("registration flagged as a likely failure (confidence %.2f): check the QC figure",
                               confidence)

        registered = None
        if resample_moving:
            t = time.perf_counter()
            registered = resample(moving_img, fixed_img, params_to_sitk(params, center))
            timings["resample"] = time.perf_counter() - t
        # report about the fixed image centre (the project's convention); the network grid may be centred elsewhere
        fixed_center = Grid.from_sitk(fixed_img).center()
        params = recenter_params(params, center, fixed_center)
        net_fixed = recenter_params(net_params, center, fixed_center)
        details["network_params"] = {n: float(v) for n, v in zip(PARAM_NAMES, net_fixed)}
        if "refine" in details:
            details["refine"]["change"] = {n: float(v) for n, v in zip(PARAM_NAMES, params - net_fixed)}
        timings["total"] = time.perf_counter() - t_start
        return RegistrationResult(params, fixed_center, registered, timings, confidence, flagged, details)


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
) -> RegistrationResult:
    """Rigidly register a CBCT (``moving``) to a planning CT (``fixed``).

    Args:
        fixed: planning CT: path (NIfTI, MetaImage, NRRD, DICOM directory) or ``SimpleITK.Image`` (HU).
        moving: CBCT, likewise; any grid, spacing, origin, direction and field of view overlapping the CT.
        model: a :class:`RigidRegistrar`, or a bare network (default grid settings), or ``None`` for the bundle.
        bundle: MONAI bundle directory to load the network from (default: the shipped ``cbct_ct_rigid``).
        device: ``"auto"`` (CUDA if available), ``"cpu"``, ``"cuda"``...
        cascade_steps: network applications (default: the bundle's setting).
        refine: polish the network estimate with SimpleITK Mattes-MI (Euler3D, masked to the CBCT FOV).
        resample_moving: also return the CBCT resampled onto the CT grid.
        moving_fov: mask of the CBCT field of view on the CBCT grid (default: inscribed cylinder).

    Returns:
        :class:`RegistrationResult` with ``params`` (mm/deg), ``transform`` (``Euler3DTransform``), ``registered``,
        ``timings`` and ``confidence``.
    """
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
                     moving_fov=moving_fov)


def write_outputs(
    result: RegistrationResult,
    fixed: sitk.Image,
    moving: sitk.Image,
    output_dir: str | Path,
    overwrite: bool = False,
    qc: bool = True,
) -> dict[str, Path]:
    """Write ``transform.tfm``, ``registered.nii.gz``, ``result.json`` and ``qc.png`` into ``output_dir``.

    Everything is written to a temporary sibling directory first and moved into place at the end, so a failure
    leaves no partial output; an existing ``output_dir`` is refused unless ``overwrite``.
    """
    import shutil
    import tempfile

    from monai_rigidreg.errors import OutputExistsError
    from monai_rigidreg.io import save_volume, write_transform
    from monai_rigidreg.qc import qc_figure

    out = Path(output_dir)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise OutputExistsError(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        write_transform(result.transform, tmp / "transform.tfm")
        registered = result.registered if result.registered is not None else resample(moving, fixed, result.transform)
        save_volume(registered, tmp / "registered.nii.gz")
        (tmp / "result.json").write_text(json.dumps(result.to_dict(), indent=2))
        if qc:
            p = result.params
            title = (f"tx={p[0]:.2f} ty={p[1]:.2f} tz={p[2]:.2f} mm   rx={p[3]:.2f} ry={p[4]:.2f} rz={p[5]:.2f} deg"
                     f"   confidence={result.confidence:.2f}{'  FLAGGED' if result.flagged else ''}")
            qc_figure(fixed, moving, registered, tmp / "qc.png", title=title)
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {name: out / name for name in ("transform.tfm", "registered.nii.gz", "result.json", "qc.png")
            if (out / name).exists()}


def register_files(
    registrar: RigidRegistrar,
    fixed: str | Path,
    moving: str | Path,
    output_dir: str | Path,
    refine: bool = False,
    overwrite: bool = False,
    qc: bool = True,
) -> dict[str, Path]:
    """Load, register and write the standard outputs (the bundle's ``inference.json`` ``run`` step).

    Returns:
        ``{file name: path}`` of ``transform.tfm``, ``registered.nii.gz``, ``result.json`` and ``qc.png``.
    """
    from monai_rigidreg.errors import OutputExistsError
    from monai_rigidreg.io import load_volume

    if not fixed or not moving:
        raise InputError("both 'fixed' and 'moving' must be given (e.g. --fixed CT.nii.gz --moving CBCT.nii.gz)")
    out = Path(output_dir)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise OutputExistsError(out)
    fixed_img = load_volume(fixed)
    moving_img = load_volume(moving)
    result = registrar(fixed_img, moving_img, refine=refine)
    paths = write_outputs(result, fixed_img, moving_img, out, overwrite=overwrite, qc=qc)
    logger.info("registered %s to %s: %s (confidence %.2f)", moving, fixed,
                ", ".join(f"{n}={v:.2f}" for n, v in zip(PARAM_NAMES, result.params)), result.confidence)
    return paths
