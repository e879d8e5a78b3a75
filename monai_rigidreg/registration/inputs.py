"""Stage 1 of a registration: the inputs, checked once, before any work.

:func:`check_register_inputs` checks paths, cascade steps and the output folder before anything is read (the
``register`` command and the bundle's ``inference.json``); :func:`read_inputs` reads both images, refuses a
constant image or two images that do not overlap, and warns about intensities that are not HU
(:func:`check_intensities`, :func:`not_hu`) and about a fixed image that looks like the CBCT
(:func:`swapped_reasons`: its box inside the moving one's, or a CBCT's truncated cylindrical field of view).

>>> not_hu(0.0, 255.0), not_hu(-1024.0, 3071.0)
(True, False)
>>> check_cascade_steps(2)
2
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.errors import InputError
from monai_rigidreg.core.geometry import Grid
from monai_rigidreg.export.outputs import OUTPUT_FILES
from monai_rigidreg.io.dicom_series import same_patient_ids
from monai_rigidreg.io.staging import check_replaceable
from monai_rigidreg.io.volumes import as_image, check_output_dir, grid_within, grids_overlap

__all__ = ["HU_AIR_LIMIT", "EIGHT_BIT_RANGE", "Inputs", "check_intensities", "not_hu", "check_hu",
           "check_cascade_steps", "check_register_inputs", "read_inputs", "SWAPPED_BOX_SHARE", "TRUNCATED_RIM_SHARE",
           "truncated_cylinder", "swapped_reasons", "check_same_patient", "SWAPPED_NOISE_RATIO",
           "image_noise_hu"]

logger = logging.getLogger(__name__)

HU_AIR_LIMIT = -500.0
"""A CT or CBCT in HU holds air (about -1000 HU) somewhere: an image whose minimum lies above this is probably not in
HU (or is cropped to the body)."""
EIGHT_BIT_RANGE = 256.0
"""An image whose intensities span at most this many units is an 8-bit export (or a normalized image), never a CT
in HU: tissue alone spans fat (-100 HU) to bone (several hundred HU)."""


SWAPPED_BOX_SHARE = 0.95
"""A fixed image whose box lies inside the moving one's and covers less than this share of it (any smaller share:
a CBCT inside the planning CT's box) looks like the CBCT (:func:`swapped_reasons`). Two boxes alike in size (a CBCT
resampled onto the CT's grid) do not count."""
SWAPPED_NOISE_RATIO = 1.5
"""A fixed image whose box is smaller (in volume) than the moving one's and whose noise (:func:`image_noise_hu`) is
more than this times the moving one's looks like the CBCT (:func:`swapped_reasons`, ``"noise"``): a CBCT is the
noisier of the two. Measured on this repository's pairs (``python -m benchmarks.confidence.bench_swap_noise``): CT
over CBCT 0.01-0.80 on 40 pairs of three real CTs (paper protocol and clinical geometry; the CTs measure 0.2-31 HU,
their CBCTs 20-100 HU), the swapped pairs 1.26-144."""
TRUNCATED_RIM_SHARE = 0.2
"""A cylindrical field of view cuts the body when at least this share of its rim (4-12 mm inside the cylinder's
edge) is tissue (:func:`truncated_cylinder`): a CBCT's does (0.58-0.71 on the benchmark CBCTs), a planning CT's
reconstruction circle holds the whole body (0.003-0.023 on the six CTs of ``../shared/data``)."""


def truncated_cylinder(image: sitk.Image) -> bool:
    """Whether ``image`` looks like a CBCT's reconstruction: a cylindrical field of view (the largest cylinder along
    its z index axis) with one constant value at or below air outside it, that cuts the body (tissue on at least
    :data:`TRUNCATED_RIM_SHARE` of its rim). Sampled at about 4 mm in-plane and on at most 32 slices."""
    size = np.array(image.GetSize())
    spacing = np.array(image.GetSpacing())
    step_xy = [max(1, int(4.0 / s)) for s in spacing[:2]]
    step_z = max(1, int(np.ceil(size[2] / 32)))
    arr = sitk.GetArrayViewFromImage(image)[::step_z, ::step_xy[1], ::step_xy[0]]  # [z, y, x]
    half = (size[:2] - 1) / 2.0
    radius = float(min(half[0] * spacing[0], half[1] * spacing[1]))
    yy, xx = np.meshgrid(np.arange(0, size[1], step_xy[1]), np.arange(0, size[0], step_xy[0]), indexing="ij")
    r = np.hypot((xx - half[0]) * spacing[0], (yy - half[1]) * spacing[1])
    outside = r > radius + 2.0 * float(max(spacing[:2]))
    rim = (r <= radius - 4.0) & (r > radius - 12.0)
    if outside.sum() < 10 or rim.sum() < 10:
        return False
    out_values = arr[:, outside]
    lo, hi = float(out_values.min()), float(out_values.max())
    return hi - lo < 1.0 and hi <= HU_AIR_LIMIT and float((arr[:, rim] > HU_AIR_LIMIT).mean()) >= TRUNCATED_RIM_SHARE


def image_noise_hu(image: sitk.Image, spacing_mm: float = 2.0, window: tuple[float, float] = (-250.0, 250.0)
                   ) -> float:
    """Noise of ``image`` (HU) in soft tissue, as at voxels of ``spacing_mm`` cubed.

    The image is block-averaged by whole factors towards ``spacing_mm`` (``BinShrink``); the second difference along
    x of three neighbours all inside ``window`` (soft tissue: no air, no bone edge) has, for white noise of standard
    deviation ``s``, the standard deviation ``sqrt(6) s``, taken robustly (1.4826 x the median absolute deviation);
    ``s`` is then scaled to a voxel of ``spacing_mm`` cubed (``s * sqrt(voxel volume / spacing_mm^3)``), so that
    images of different spacings compare. NaN where fewer than 1 000 such triples exist.

    >>> import numpy as np, SimpleITK as sitk
    >>> noisy = sitk.GetImageFromArray(np.random.default_rng(0).normal(0.0, 20.0, (40, 40, 40)).astype("float32"))
    >>> round(image_noise_hu(noisy, spacing_mm=1.0))
    20
    """
    factors = [max(1, int(spacing_mm / s + 1e-6)) for s in image.GetSpacing()]
    small = sitk.Cast(image, sitk.sitkFloat32)
    if max(factors) > 1:
        small = sitk.BinShrink(small, factors)
    a = sitk.GetArrayViewFromImage(small)  # [z, y, x]
    inside = (a > window[0]) & (a < window[1])
    both = inside[:, :, 2:] & inside[:, :, 1:-1] & inside[:, :, :-2]
    second = (a[:, :, 2:] - 2.0 * a[:, :, 1:-1] + a[:, :, :-2])[both]
    if second.size < 1000:
        return float("nan")
    sigma = 1.4826 * float(np.median(np.abs(second - np.median(second)))) / np.sqrt(6.0)
    return sigma * float(np.sqrt(np.prod(small.GetSpacing()) / spacing_mm ** 3))


def swapped_reasons(fixed: sitk.Image, moving: sitk.Image) -> list[str]:
    """Why the fixed image looks like the CBCT and the moving one like the CT: ``"box"`` (the fixed box lies inside
    the moving one's, any share below :data:`SWAPPED_BOX_SHARE`), ``"cylinder"`` (the fixed image has a CBCT's
    truncated cylindrical field of view with air outside, :func:`truncated_cylinder`, and the moving one has not),
    ``"noise"`` (where the box test does not fire: the fixed box is smaller in volume than the moving one's and the
    fixed image more than :data:`SWAPPED_NOISE_RATIO` times as noisy, :func:`image_noise_hu`; a CBCT's box reaching
    past a short CT's, e.g. a head). Empty where none holds. The noise is measured only where the fixed box is the
    smaller, so a planning CT larger than the CBCT costs nothing."""
    reasons = []
    f_grid, m_grid = Grid.from_sitk(fixed), Grid.from_sitk(moving)
    if grid_within(f_grid, m_grid, max_share=SWAPPED_BOX_SHARE):
        reasons.append("box")
    if truncated_cylinder(fixed) and not truncated_cylinder(moving):
        reasons.append("cylinder")
    if "box" not in reasons and _box_volume(f_grid) < _box_volume(m_grid):
        noise_f, noise_m = image_noise_hu(fixed), image_noise_hu(moving)
        if noise_f > SWAPPED_NOISE_RATIO * noise_m:  # False where either is NaN
            reasons.append("noise")
    return reasons


def _box_volume(grid: Grid) -> float:
    """Physical volume of a grid's voxel box (mm^3)."""
    return float(np.prod(np.asarray(grid.size, dtype=np.float64) * np.asarray(grid.spacing, dtype=np.float64)))


def check_intensities(image: sitk.Image, name: str, hu_range: tuple[float, float] = (-1000.0, 2000.0)) -> list[str]:
    """Check that ``image`` can be registered as a CT/CBCT in Hounsfield units.

    Returns:
        warnings (also logged): an intensity range that is not HU, or may not be (no air: e.g. a uint8 or int8
        export, a normalized or raw-detector image, or a CT cropped to the body), which the network, trained on
        HU, reads as something else. See :func:`not_hu` for the ranges that are certainly not HU.

    Raises:
        InputError: the image is constant (every voxel the same value, e.g. all zero): nothing to register.
    """
    return check_hu(image, name, hu_range)[0]


def not_hu(lo: float, hi: float) -> bool:
    """Whether an intensity range ``[lo, hi]`` is certainly not a CT or CBCT in HU: no negative value (an unsigned
    export, raw detector units, or HU stored without the rescale intercept) or a span of at most
    :data:`EIGHT_BIT_RANGE`. A range from about -100 HU up, without air, may be a CT cropped to the body: not this."""
    return lo >= 0.0 or hi - lo <= EIGHT_BIT_RANGE


def check_hu(image: sitk.Image, name: str, hu_range: tuple[float, float]) -> tuple[list[str], bool]:
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


def check_cascade_steps(steps: Any) -> int:
    """``steps`` (network applications of a cascade) as an int >= 1, else
    :class:`~monai_rigidreg.core.errors.InputError` naming the value."""
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or int(steps) < 1:
        raise InputError(f"cascade_steps must be a whole number >= 1, got {steps!r}")
    return int(steps)


def check_register_inputs(
    fixed: str | Path | None,
    moving: str | Path | None,
    output_dir: str | Path,
    overwrite: bool = False,
    cascade_steps: Any = None,
) -> Path:
    """The checks of a registration run, done once before anything is loaded: both inputs given and present, the
    cascade steps (if given) a whole number >= 1, and an output folder that may be written
    (:func:`~monai_rigidreg.io.volumes.check_output_dir`). The ``register`` command and the bundle's
    ``inference.json`` both go through it.

    Returns:
        ``output_dir`` as a ``Path``.

    Raises:
        InputError: a missing input (naming it), a bad ``cascade_steps``, an output folder that cannot be made.
        OutputExistsError: the output folder is a file, or not empty and ``overwrite`` is False.
    """
    for name, path in (("fixed", fixed), ("moving", moving)):
        if path is None or not str(path).strip():
            raise InputError(f"no {name} image given: both 'fixed' (the CT) and 'moving' (the CBCT) are needed "
                             "(e.g. --fixed CT.nii.gz --moving CBCT.nii.gz)")
        if not Path(path).exists():
            raise InputError(f"no such file or directory (the {name} image)", path)
    if cascade_steps is not None:
        check_cascade_steps(cascade_steps)
    out = check_output_dir(output_dir, overwrite)
    if overwrite:
        check_replaceable(out, OUTPUT_FILES)  # never delete what this package did not write, e.g. the inputs
    return out


def check_same_patient(fixed_record: dict[str, Any], moving_record: dict[str, Any],
                       allow_other_patient: bool = False) -> str:
    """Refuse a CT and a CBCT whose DICOM headers name different patients, before anything is registered.

    A rigid transform between two patients' images is never a setup correction, and the image signals cannot always
    tell (another patient's head CBCT on a head CT matched with confidence 0.82 in the calibration's negative set,
    ``docs/trust.md``); DICOM inputs say it outright. The DICOM node's rule,
    :func:`~monai_rigidreg.io.dicom_series.same_patient_ids`: the same Patient ID (0010,0020), and the same Issuer of
    Patient ID (0010,0021) where both name one.

    Args:
        fixed_record, moving_record: the inputs' :func:`~monai_rigidreg.export.provenance.input_record` (``format``,
            ``patient_id``, ``issuer_of_patient_id``).
        allow_other_patient: the user says the two are one patient under different IDs (e.g. a phantom, or data
            pseudonymised per series): registered, with the returned warning.

    Returns:
        ``""``, or the warning to record where ``allow_other_patient`` let different IDs through.

    Raises:
        InputError: both inputs are DICOM series naming different patients and ``allow_other_patient`` is False.
        Where either is not DICOM or lacks a Patient ID nothing is known, and nothing is said.

    >>> check_same_patient({"format": "dicom", "patient_id": "P1"}, {"format": ".nii.gz"})
    ''
    """
    if fixed_record.get("format") != "dicom" or moving_record.get("format") != "dicom":
        return ""
    ids = [str(r.get("patient_id") or "").strip() for r in (fixed_record, moving_record)]
    issuers = [str(r.get("issuer_of_patient_id") or "").strip() for r in (fixed_record, moving_record)]
    if not all(ids) or same_patient_ids(*ids, *issuers):
        return ""
    who = [f"{i!r}" + (f" (issuer {s!r})" if s else "") for i, s in zip(ids, issuers)]
    text = f"the CT (fixed) and the CBCT (moving) name different patients: Patient ID {who[0]} and {who[1]}"
    if not allow_other_patient:
        raise InputError(f"{text}; nothing was registered. If they are one patient under two IDs (a phantom, "
                         "pseudonymised series), pass --allow-other-patient (allow_other_patient=True in Python)")
    return f"{text}; registered because --allow-other-patient was given"


@dataclass
class Inputs:
    """Both images of a registration as :func:`read_inputs` returns them: float32 ``SimpleITK.Image`` s, their
    grids, the warnings about them, the names of those whose intensities are certainly not HU, and why the fixed
    image looks like the CBCT (:func:`swapped_reasons`; empty: it does not)."""

    fixed: sitk.Image
    moving: sitk.Image
    fixed_grid: Grid
    moving_grid: Grid
    warnings: list[str]
    not_hu: list[str]
    swapped: list[str] = field(default_factory=list)


SWAPPED_WARNING = {
    "box": "the fixed image lies inside the moving one and is smaller, as a CBCT would the planning CT",
    "cylinder": "the fixed image has a CBCT's cylindrical field of view that cuts the body, with air outside it, and "
                "the moving one has not",
    "noise": "the fixed image is the smaller and much the noisier of the two, as a CBCT would be beside the "
             "planning CT",
}


def read_inputs(fixed: sitk.Image | str | Path, moving: sitk.Image | str | Path,
                hu_range: tuple[float, float], allow_swapped: bool = False) -> Inputs:
    """Read (or take) the CT (``fixed``) and the CBCT (``moving``) and check them as a pair.

    A fixed image that looks like the CBCT (:func:`swapped_reasons`) gets a warning; the registrar flags the result
    unless ``allow_swapped`` (the user says the fixed image really is the smaller one).

    Raises:
        InputError: an unreadable or constant image, or two images that do not overlap in physical space (their
            boxes share less than 5 % of the smaller one).
    """
    fixed_img = as_image(fixed, "fixed")
    moving_img = as_image(moving, "moving")
    checked = {name: check_hu(img, name, hu_range)
               for img, name in ((fixed_img, "fixed (CT)"), (moving_img, "moving (CBCT)"))}
    warnings = [w for found, _ in checked.values() for w in found]
    fixed_grid, moving_grid = Grid.from_sitk(fixed_img), Grid.from_sitk(moving_img)
    if not grids_overlap(fixed_grid, moving_grid):
        raise InputError(
            "the CT (fixed) and CBCT (moving) do not overlap in physical space: check that both are in the "
            "same patient coordinate system (origins and directions)"
        )
    swapped = swapped_reasons(fixed_img, moving_img)
    if swapped:
        msg = (f"{'; '.join(SWAPPED_WARNING[r] for r in swapped)}: check that fixed (--fixed) is the CT and moving "
               "(--moving) the CBCT (swapped, the transform and the couch shifts come out inverted); "
               + ("--allow-swapped: not flagged" if allow_swapped else
                  "the result is flagged (--allow-swapped if the fixed image really is the planning CT)"))
        logger.warning("%s", msg)
        warnings.append(msg)
    return Inputs(fixed_img, moving_img, fixed_grid, moving_grid, warnings,
                  [name for name, (_, certain) in checked.items() if certain], swapped)
