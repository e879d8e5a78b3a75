"""Classical intensity-based rigid registration: SimpleITK (Mattes MI, Euler3D) and, optionally, elastix.

Used three ways: as the baseline that evaluations compare against (``--method sitk`` / ``--method elastix``),
and as the ``--refine`` stage that starts from the network's estimate. Every result is reported in the project
convention (fixed -> moving, parameters about the fixed image centre; see :mod:`monai_rigidreg.core.geometry`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.geometry import Grid, matrix_to_params, params_to_sitk, sitk_to_matrix

__all__ = ["ClassicalResult", "register_sitk", "register_elastix", "elastix_available", "moving_footprint"]

logger = logging.getLogger(__name__)


@dataclass
class ClassicalResult:
    """Outcome of a classical registration.

    Attributes:
        params: ``(tx, ty, tz, rx, ry, rz)`` in mm / degrees about ``center`` (fixed -> moving).
        center: rotation centre (LPS mm), the fixed image centre.
        metric: final metric value (Mattes MI: lower is better) or NaN.
        iterations: optimizer iterations at the last level.
        runtime_s: wall time in seconds.
        stop_condition: the optimizer's stop description.
    """

    params: np.ndarray
    center: np.ndarray
    metric: float = float("nan")
    iterations: int = 0
    runtime_s: float = 0.0
    stop_condition: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def transform(self) -> sitk.Euler3DTransform:
        return params_to_sitk(self.params, self.center)


def register_sitk(fixed: sitk.Image, moving: sitk.Image, initial_params: Sequence[float] | None = None,
                  center: Sequence[float] | None = None, fixed_mask: sitk.Image | None = None,
                  moving_mask: sitk.Image | None = None, shrink_factors: Sequence[int] = (4, 2, 1),
                  smoothing_sigmas_mm: Sequence[float] = (2.0, 1.0, 0.0), iterations: int = 200, bins: int = 32,
                  samples: int = 20000, learning_rate: float = 1.0, seed: int = 1) -> ClassicalResult:
    """Mattes-MI, Euler3D, multi-resolution SimpleITK registration.

    Args:
        fixed: planning CT (float).
        moving: CBCT (float).
        initial_params: start ``(tx, ty, tz, rx, ry, rz)`` about ``center``; default identity after a
            geometry-centred initialisation (``CenteredTransformInitializer``, GEOMETRY): the transform that
            maps the fixed image centre to the moving image centre.
        center: rotation centre (default the fixed image centre).
        fixed_mask, moving_mask: metric masks, e.g. the CBCT reconstructed field of view (``moving_mask``).
        shrink_factors, smoothing_sigmas_mm: the multi-resolution pyramid (one entry per level).
        iterations: maximum iterations per level.
        bins: Mattes MI histogram bins.
        samples: random fixed-image samples per iteration at every level (as elastix does; a percentage of the
            voxels would mean millions of samples for a 256^3 CT at full resolution).
        learning_rate: regular-step gradient descent's initial step (physical units after scaling).
        seed: the metric's sampling seed: the same inputs and seed give the same result. SimpleITK reads 0 as
            ``sitkWallClock`` (a new seed each call), so 0 is refused.

    Returns:
        a :class:`ClassicalResult` in the project convention.
    """
    if int(seed) == sitk.sitkWallClock:
        raise ValueError("register_sitk: seed 0 is SimpleITK's wall clock (a different result each call); give a "
                         "non-zero seed")
    t0 = time.perf_counter()
    fixed_f = sitk.Cast(fixed, sitk.sitkFloat32)
    moving_f = sitk.Cast(moving, sitk.sitkFloat32)
    c = Grid.from_sitk(fixed_f).center() if center is None else np.asarray(center, dtype=np.float64)
    if initial_params is None:
        init = sitk.CenteredTransformInitializer(
            fixed_f, moving_f, sitk.Euler3DTransform(), sitk.CenteredTransformInitializerFilter.GEOMETRY
        )
        start = matrix_to_params(sitk_to_matrix(init), c)
    else:
        start = np.asarray(initial_params, dtype=np.float64)
    tfm = params_to_sitk(start, c)

    reg = sitk.ImageRegistrationMethod()
    reg.SetMetricAsMattesMutualInformation(numberOfHistogramBins=bins)
    reg.SetMetricSamplingStrategy(reg.RANDOM)
    n_vox = float(np.prod(fixed_f.GetSize()))
    reg.SetMetricSamplingPercentagePerLevel(
        [float(np.clip(samples * s**3 / n_vox, 1e-4, 1.0)) for s in shrink_factors], int(seed)
    )
    if fixed_mask is not None:
        reg.SetMetricFixedMask(fixed_mask)
    if moving_mask is not None:
        reg.SetMetricMovingMask(moving_mask)
    reg.SetInterpolator(sitk.sitkLinear)
    reg.SetOptimizerAsRegularStepGradientDescent(
        learningRate=learning_rate,
        minStep=1e-4,
        numberOfIterations=int(iterations),
        relaxationFactor=0.6,
        gradientMagnitudeTolerance=1e-8,
    )
    reg.SetOptimizerScalesFromPhysicalShift()
    reg.SetShrinkFactorsPerLevel(list(shrink_factors))
    reg.SetSmoothingSigmasPerLevel(list(smoothing_sigmas_mm))
    reg.SmoothingSigmasAreSpecifiedInPhysicalUnitsOn()
    reg.SetInitialTransform(tfm, inPlace=True)
    try:
        reg.Execute(fixed_f, moving_f)
    except RuntimeError as exc:  # e.g. all samples map outside the moving image
        logger.warning("SimpleITK registration failed: %s", str(exc).strip().splitlines()[-1])
        return ClassicalResult(start, c, float("nan"), 0, time.perf_counter() - t0, f"failed: {exc}")
    params = matrix_to_params(sitk_to_matrix(tfm), c)
    return ClassicalResult(
        params,
        c,
        float(reg.GetMetricValue()),
        int(reg.GetOptimizerIteration()),
        time.perf_counter() - t0,
        reg.GetOptimizerStopConditionDescription(),
    )


def elastix_available() -> bool:
    """Whether ``itk-elastix`` (the optional ``elastix`` extra) is importable."""
    try:  # itk-elastix is an optional extra: imported where it is used, so the package works without it
        import itk  # noqa: F401

        return hasattr(itk, "ElastixRegistrationMethod")
    except ImportError:
        return False


def register_elastix(
    fixed: sitk.Image, moving: sitk.Image, center: Sequence[float] | None = None, moving_mask: sitk.Image | None = None
) -> ClassicalResult:
    """elastix's default rigid parameter map (``itk-elastix``), with the result in the project convention.

    Raises:
        ImportError: if ``itk-elastix`` is not installed (``pip install monai-rigidreg[elastix]``).
    """
    if not elastix_available():
        raise ImportError("itk-elastix is not installed: pip install 'monai-rigidreg[elastix]'")
    import itk

    t0 = time.perf_counter()
    f_itk = _sitk_to_itk(sitk.Cast(fixed, sitk.sitkFloat32))
    m_itk = _sitk_to_itk(sitk.Cast(moving, sitk.sitkFloat32))
    pobj = itk.ParameterObject.New()
    pobj.AddParameterMap(pobj.GetDefaultParameterMap("rigid"))
    # the CBCT usually covers less than the CT: sample the CT only where the CBCT (or its mask) lies, otherwise
    # elastix stops with "too many samples map outside the moving image"
    kwargs = {"fixed_mask": _sitk_to_itk(moving_footprint(fixed, moving, moving_mask))}
    c = Grid.from_sitk(fixed).center() if center is None else np.asarray(center, dtype=np.float64)
    try:
        _, result = itk.elastix_registration_method(
            f_itk, m_itk, parameter_object=pobj, log_to_console=False, **kwargs
        )
    except RuntimeError as exc:  # elastix reports its own failures (e.g. too few samples) this way
        logger.warning("elastix failed: %s", str(exc).strip().splitlines()[-1])
        return ClassicalResult(np.zeros(6), c, runtime_s=time.perf_counter() - t0, stop_condition=f"failed: {exc}")
    tp = result.GetParameterMap(0)
    p = [float(v) for v in tp["TransformParameters"]]  # rx ry rz tx ty tz (EulerTransform, radians)
    cor = [float(v) for v in tp["CenterOfRotationPoint"]]
    tfm = sitk.Euler3DTransform()
    tfm.SetCenter(cor)
    tfm.SetRotation(*p[:3])
    tfm.SetTranslation(p[3:6])
    return ClassicalResult(matrix_to_params(sitk_to_matrix(tfm), c), c, runtime_s=time.perf_counter() - t0)


def moving_footprint(fixed: sitk.Image, moving: sitk.Image, moving_mask: sitk.Image | None = None) -> sitk.Image:
    """The moving image's box (or ``moving_mask``) on the fixed grid at the identity (uint8, 0 / 1): the fixed-image
    mask the classical baselines sample the CT in, since a CBCT usually covers less than the CT."""
    footprint = moving_mask if moving_mask is not None else sitk.Image(moving.GetSize(), sitk.sitkUInt8) + 1
    if moving_mask is None:
        footprint.CopyInformation(moving)
    return sitk.Resample(sitk.Cast(footprint, sitk.sitkUInt8), fixed, sitk.Transform(), sitk.sitkNearestNeighbor, 0)


def _sitk_to_itk(image: sitk.Image):
    import itk

    arr = sitk.GetArrayFromImage(image)
    out = itk.image_view_from_array(arr.copy())
    out.SetOrigin(image.GetOrigin())
    out.SetSpacing(image.GetSpacing())
    out.SetDirection(itk.matrix_from_array(np.asarray(image.GetDirection()).reshape(3, 3)))
    return out
