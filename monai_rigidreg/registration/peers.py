"""Peer registration tools as baselines: ANTs (``antspyx``) and greedy (``picsl-greedy``), rigid, each result
re-expressed in the project convention (fixed -> moving, parameters about the fixed image centre;
:mod:`monai_rigidreg.core.geometry`). Both are optional (the ``bench`` extra) and imported where they are used.

Each tool's own convention, as read here (and checked by :func:`check_convention` on a pair with a known motion,
``tests/registration/test_peers.py``; a flipped sign, a swapped axis or the inverse direction fails it):

* **ANTs** (``ants.registration(fixed, moving, type_of_transform="Rigid")``): the result is an ITK transform file,
  ``<prefix>0GenericAffine.mat`` (``AffineTransform_float_3_3`` in ITK's MATLAB format), first in ANTsPy's
  ``fwdtransforms``. It is in **LPS** millimetres (ITK's physical space) and maps a point of the **fixed** image to
  the **moving** image: ITK's resampling direction, the one ``ants.apply_transforms(fixed, moving, fwdtransforms)``
  uses to bring the moving image onto the fixed grid, which is the project's direction. The rotation centre is the
  file's ``FixedParameters`` (ANTs writes ``0 0 0`` and folds the centre into the translation). Read with
  ``SimpleITK.ReadTransform``, its 4x4 is :func:`~monai_rigidreg.core.geometry.sitk_to_matrix`; nothing is flipped
  or inverted.
* **greedy** (``greedy -a -dof 6``, ``picsl_greedy.Greedy3D``): the result (``g[name]`` in Python, the ``.mat`` text
  file on the command line) is a 4x4 matrix in **RAS** millimetres (the NIfTI / ITK-SNAP convention), also mapping
  a **fixed** point to the **moving** image (``greedy -r`` reslices the moving image onto the fixed grid with it).
  It has no centre (the translation column is about the RAS origin). In LPS it is ``F @ Q @ F`` with
  ``F = diag(-1, -1, 1, 1)`` (:func:`~monai_rigidreg.core.geometry.ras_to_lps_transform`); not inverted.

Settings: each tool as its documentation runs a rigid registration, from the identity like the other baselines (ANTs'
own default would align the centres of mass, which a CBCT's smaller field of view moves), with the CBCT's reconstructed
field of view as the moving-image mask where given (``moving_mask``; :data:`PEER_FOV_MASK`, measured both ways in
``docs/results.md``). ANTs runs its ``Rigid`` defaults (Mattes MI, 32 bins, 20 % regular sampling, 2100x1200x1200x10
iterations at shrink factors 6x4x2x1); greedy runs NMI over three levels (``-n 100x50x10``). Neither gets the CT-side
mask elastix needs (:func:`~monai_rigidreg.registration.classical.moving_footprint`, the CBCT's box on the CT): with it
greedy diverged on 10 of the 42 held-out real-CT pairs that it registers without it (``-gm``: gradients over the mask
only), and ANTs on one more (``benchmarks/results/0.4.9/bench_real_ct_0.4.9_peers_2026-12-03.txt``, the first run).
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import io
import logging
import os
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from monai_rigidreg.core.geometry import (
    Grid,
    matrix_to_params,
    parameter_errors,
    params_to_matrix,
    ras_to_lps_transform,
    sitk_to_matrix,
    transform_points,
)
from monai_rigidreg.registration.classical import ClassicalResult

__all__ = ["PEER_METHODS", "ants_available", "greedy_available", "peer_available", "register_ants",
           "register_greedy", "register_peer", "known_motion_pair", "check_convention", "CONVENTION_TOLERANCE",
           "ANTS_STARTS", "PEER_FOV_MASK", "peer_uses_mask"]

logger = logging.getLogger(__name__)

PEER_METHODS = ("ants", "greedy")
"""The peer tools' method names (``evaluate``, the benchmarks' ``--methods``)."""

_DISTRIBUTIONS = {"ants": "antspyx", "greedy": "picsl-greedy"}

CONVENTION_TOLERANCE = (0.3, 1.5)
"""Largest error of :func:`check_convention`: mm for each translation, degrees for each rotation. A misread
convention misses the check's motion by 3.7 degrees or more and 6 mm or more (a rotation's sign flipped, two axes
transposed, the inverse: ``tests/registration/test_peers.py`` computes each); the tools' own stopping rules leave up
to about 1 degree. greedy stops within 0.25 degrees of the known rotations on that pair; ANTs anywhere from 0.1 to
about 1.1 degrees (the image match is best at the known motion to 0.1 degrees, and SimpleITK's Mattes MI ends within
0.1): its end point depends on its thread count (ry off by 0.42 / 0.45 / 0.62 / 0.44 degrees with
``ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS`` 1 / 2 / 4 / 8) and, multithreaded, on the run (0.12 and 0.59 degrees in two
runs with the same seed at 2 threads, about 1.0 in ``bench_speed``'s process), and more full-resolution iterations
than ANTsPy's 10 do not settle it (100 or 200: the same end points). 1.5 degrees leaves a margin larger than itself
before a misreading could pass."""


def _installed(distribution: str) -> bool:
    # by the installed distribution, without importing it: ``import ants`` alone takes seconds (pandas, statsmodels)
    try:
        importlib.metadata.distribution(distribution)
        return True
    except importlib.metadata.PackageNotFoundError:
        return False


def ants_available() -> bool:
    """Whether ``antspyx`` (ANTs for Python, the ``bench`` extra) is installed."""
    return _installed("antspyx")


def greedy_available() -> bool:
    """Whether ``picsl-greedy`` (greedy for Python, the ``bench`` extra) is installed."""
    return _installed("picsl-greedy")


def peer_available(method: str) -> bool:
    """Whether the peer tool of ``method`` (``"ants"`` or ``"greedy"``) is installed."""
    return _installed(_DISTRIBUTIONS[method])


def _missing(method: str) -> ImportError:
    return ImportError(f"method {method!r} needs {_DISTRIBUTIONS[method]}: pip install "
                       f"'monai-rigidreg[bench]' (or pip install {_DISTRIBUTIONS[method]})")


@contextlib.contextmanager
def _environ(**values: str) -> Iterator[None]:
    """Environment variables set for the duration of the block, the previous values restored after."""
    before = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def _native_stdout_discarded() -> Iterator[None]:
    """What native code writes to the process's standard output (greedy's line-search optimizer prints there
    directly, past ``execute(out=...)``) discarded for the duration of the block."""
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:  # no file descriptor 1: nothing to protect
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
            yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _rigid(matrix: np.ndarray, tool: str) -> np.ndarray:
    """``matrix`` with its 3x3 block replaced by the nearest rotation (ANTs writes single precision), refusing a
    matrix that is not a rotation to within 1e-4 (a tool that returned an affine or a reflection)."""
    m = np.array(matrix, dtype=np.float64)
    u, s, vt = np.linalg.svd(m[:3, :3])
    if np.abs(s - 1.0).max() > 1e-4 or np.linalg.det(u @ vt) <= 0:
        raise ValueError(f"{tool} returned a matrix that is not a rotation (singular values {s})")
    m[:3, :3] = u @ vt
    return m


def _failed(tool: str, exc: Exception, center: np.ndarray, t0: float) -> ClassicalResult:
    last = (str(exc).strip().splitlines() or [type(exc).__name__])[-1]
    logger.warning("%s failed: %s", tool, last)
    return ClassicalResult(np.zeros(6), center, runtime_s=time.perf_counter() - t0, stop_condition=f"failed: {last}")


ANTS_STARTS = ("identity", "mass")
"""Where :func:`register_ants` starts: the identity (as every method of the benchmarks) or ANTsPy's own default for
its linear presets, the translation that aligns the two images' centres of intensity mass (``[fixed, moving, 1]``)."""


def register_ants(fixed: sitk.Image, moving: sitk.Image, center: Sequence[float] | None = None,
                  moving_mask: sitk.Image | None = None, type_of_transform: str = "Rigid",
                  seed: int = 1, start: str = "identity") -> ClassicalResult:
    """ANTs' rigid registration (``antspyx``) from the identity or ANTsPy's own start, in the project convention.

    Args:
        fixed: planning CT; moving: CBCT.
        center: the centre the parameters are given about (default the fixed image centre).
        moving_mask: the CBCT's field of view (left out of the metric outside it).
        type_of_transform: ``"Rigid"`` (ANTsPy's defaults) or another rigid preset of ``ants.registration``
            (``"DenseRigid"``: every voxel sampled).
        seed: ANTs' sampling seed (``ANTS_RANDOM_SEED`` for the call; not 0, which samples anew each run), so
            that a run repeats.
        start: ``"identity"`` or ``"mass"`` (:data:`ANTS_STARTS`; the result includes the start either way).

    ANTs takes its thread count from ``ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS``, read once per process on its first
    registration (the benchmarks' ``--threads`` sets it before).

    Returns:
        a :class:`~monai_rigidreg.registration.classical.ClassicalResult`; ``extra["native_matrix"]``: the tool's own
        4x4 (LPS, fixed -> moving, as read from its ``.mat``). A registration ANTs fails returns the identity with
        ``stop_condition`` ``"failed: ..."``.

    Raises:
        ValueError: ``start`` is not one of :data:`ANTS_STARTS`.
        ImportError: ``antspyx`` is not installed.
    """
    if start not in ANTS_STARTS:
        raise ValueError(f"start must be one of {ANTS_STARTS}, got {start!r}")
    if not ants_available():
        raise _missing("ants")
    t0 = time.perf_counter()
    c = Grid.from_sitk(fixed).center() if center is None else np.asarray(center, dtype=np.float64)
    import ants  # optional, and seconds to import: only here

    f = ants.from_sitk(sitk.Cast(fixed, sitk.sitkFloat32))
    m = ants.from_sitk(sitk.Cast(moving, sitk.sitkFloat32))
    masks = {} if moving_mask is None else {"moving_mask": ants.from_sitk(sitk.Cast(moving_mask, sitk.sitkFloat32))}
    with tempfile.TemporaryDirectory(prefix="rigidreg_ants_") as tmp, _environ(ANTS_RANDOM_SEED=str(int(seed))):
        try:
            out = ants.registration(f, m, type_of_transform=type_of_transform,
                                    initial_transform="Identity" if start == "identity" else None,
                                    outprefix=str(Path(tmp) / "ants_"), **masks)
            files = [p for p in out["fwdtransforms"] if p.endswith("GenericAffine.mat")]
            if len(out["fwdtransforms"]) != 1 or not files:
                raise RuntimeError(f"expected one affine transform file, got {out['fwdtransforms']}")
            native = sitk_to_matrix(sitk.ReadTransform(files[0]))
        except (RuntimeError, ValueError) as exc:
            return _failed("ANTs", exc, c, t0)
    params = matrix_to_params(_rigid(native, "ANTs"), c)
    return ClassicalResult(params, c, runtime_s=time.perf_counter() - t0, stop_condition=type_of_transform,
                           extra={"native_matrix": native.tolist(), "native_space": "LPS", "start": start})


def register_greedy(fixed: sitk.Image, moving: sitk.Image, center: Sequence[float] | None = None,
                    moving_mask: sitk.Image | None = None, iterations: Sequence[int] = (100, 50, 10),
                    metric: str = "NMI", threads: int | None = None, seed: int = 1) -> ClassicalResult:
    """greedy's rigid registration (``picsl-greedy``, ``-a -dof 6``) from the identity, in the project convention.

    Args:
        fixed: planning CT; moving: CBCT.
        center: the centre the parameters are given about (default the fixed image centre).
        moving_mask: the CBCT's field of view (``-mm``: left out of the metric outside it).
        iterations: per level, coarsest first (``-n``).
        metric: greedy's ``-m`` (``NMI``, ``MI``, ``SSD``, ``NCC 2x2x2``...).
        threads: greedy's ``-threads`` (default SimpleITK's global default number of threads).
        seed: greedy's ``-seed`` (its default, 0, samples differently on every run).

    Returns:
        a :class:`~monai_rigidreg.registration.classical.ClassicalResult`; ``extra["native_matrix"]``: greedy's own
        4x4 (RAS, fixed -> moving). A registration greedy fails returns the identity with ``stop_condition``
        ``"failed: ..."``.

    Raises:
        ImportError: ``picsl-greedy`` is not installed.
    """
    if not greedy_available():
        raise _missing("greedy")
    t0 = time.perf_counter()
    c = Grid.from_sitk(fixed).center() if center is None else np.asarray(center, dtype=np.float64)
    from picsl_greedy import Greedy3D  # optional: only here

    n_threads = int(threads) if threads is not None else sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
    levels = "x".join(str(int(i)) for i in iterations)
    images = {"ct": sitk.Cast(fixed, sitk.sitkFloat32), "cbct": sitk.Cast(moving, sitk.sitkFloat32)}
    cmd = (f"-d 3 -a -dof 6 -i ct cbct -m {metric} -n {levels} -ia-identity -threads {max(1, n_threads)} "
           f"-seed {int(seed)} -V 0 -o rigid")
    if moving_mask is not None:
        images["cbct_mask"] = sitk.Cast(moving_mask, sitk.sitkFloat32)
        cmd += " -mm cbct_mask"
    log = io.StringIO()
    try:
        g = Greedy3D()
        with _native_stdout_discarded():
            g.execute(cmd, out=log, err=log, rigid=None, **images)
        native = np.asarray(g["rigid"], dtype=np.float64)
        if native.shape != (4, 4):
            raise RuntimeError(f"greedy returned no 4x4 matrix ({log.getvalue()[-300:]!r})")
    except (RuntimeError, ValueError) as exc:
        return _failed("greedy", exc, c, t0)
    params = matrix_to_params(_rigid(ras_to_lps_transform(native), "greedy"), c)
    return ClassicalResult(params, c, runtime_s=time.perf_counter() - t0, stop_condition=f"{metric} -n {levels}",
                           extra={"native_matrix": native.tolist(), "native_space": "RAS"})


PEER_FOV_MASK = {"ants": True, "greedy": True}
"""Whether :func:`register_peer` gives each tool the CBCT's field of view (``moving_mask``) by default."""


def peer_uses_mask(method: str, use_mask: bool | None = None) -> bool:
    """Whether :func:`register_peer` hands ``method``'s tool the CBCT's field of view: ``use_mask`` where given, the
    tool's :data:`PEER_FOV_MASK` otherwise.

    >>> peer_uses_mask("ants"), peer_uses_mask("ants", False)
    (True, False)
    """
    if method not in PEER_METHODS:
        raise ValueError(f"unknown peer method {method!r}; choose from {PEER_METHODS}")
    return PEER_FOV_MASK[method] if use_mask is None else bool(use_mask)


def register_peer(method: str, fixed: sitk.Image, moving: sitk.Image, center: Sequence[float] | None = None,
                  moving_mask: sitk.Image | None = None, use_mask: bool | None = None) -> ClassicalResult:
    """:func:`register_ants` or :func:`register_greedy` by method name, with the benchmarks' settings.

    ``moving_mask`` (the CBCT's field of view) reaches the tool where ``use_mask`` says so (``None``: the tool's
    :data:`PEER_FOV_MASK`); ``False`` runs it on the whole images, as elastix's default rigid map runs."""
    mask = moving_mask if peer_uses_mask(method, use_mask) else None
    if method == "ants":
        return register_ants(fixed, moving, center, mask)
    return register_greedy(fixed, moving, center, mask)


# ---------------------------------------------------------------------------------------------------------------
# The convention check: a pair with a known motion
# ---------------------------------------------------------------------------------------------------------------
KNOWN_MOTION = (7.0, -4.0, 2.5, 5.0, -3.0, 2.0)
"""The check's motion ``(tx, ty, tz, rx, ry, rz)`` about the CT centre: every axis moved, by distinct amounts, so a
flipped sign, a swapped axis or the inverse transform each miss it by millimetres or degrees."""


def _volume(size: int, spacing: float, origin: Sequence[float], direction: np.ndarray, values) -> sitk.Image:
    """A float32 image of ``values(points)`` evaluated at its voxel centres (LPS mm)."""
    idx = np.stack(np.meshgrid(*[np.arange(size)] * 3, indexing="ij"), -1).reshape(-1, 3) * spacing
    pts = np.asarray(origin, dtype=np.float64) + idx @ direction.T
    arr = values(pts).reshape((size,) * 3).transpose(2, 1, 0)  # [x, y, z] -> SimpleITK's [z, y, x]
    img = sitk.GetImageFromArray(np.ascontiguousarray(arr, dtype=np.float32))
    img.SetSpacing((spacing,) * 3)
    img.SetOrigin(tuple(float(v) for v in origin))
    img.SetDirection(tuple(direction.ravel()))
    return img


def known_motion_pair(motion: Sequence[float] = KNOWN_MOTION, seed: int = 0, size: int = 64,
                      spacing: float = 3.0) -> tuple[sitk.Image, sitk.Image]:
    """A small CT-like pair whose moving image shows the fixed image's content moved by ``motion`` (about the fixed
    centre; the registration's answer is ``motion`` itself, ``docs/conventions.md``).

    The content is analytic (an ellipsoidal body at -1000 HU outside, soft-tissue blobs of 5-10 mm and six bright
    "bones"), evaluated on each grid rather than resampled, so neither image carries interpolation blur. The fixed
    image: ``size``^3 voxels of ``spacing`` mm (64^3 of 3 mm), axes flipped in x and y (as a NIfTI CT reads); the
    moving image: 0.8 of its voxels at 0.9 of its spacing (the body cut off at the sides, as a CBCT's field of
    view does), its own origin and a 10-degree oblique direction, so that a tool reading voxel grids instead of
    physical space also fails.
    """
    rng = np.random.default_rng(seed)
    flip = np.diag([-1.0, -1.0, 1.0])
    origin = np.array([90.0, 100.0, -60.0])
    center = origin + flip @ np.full(3, (size - 1) * spacing / 2)
    semi = np.array([85.0, 55.0, 70.0])
    blobs = center + rng.uniform(-0.8, 0.8, (60, 3)) * semi
    sigma, amp = rng.uniform(5.0, 10.0, 60), rng.uniform(-250.0, 250.0, 60)
    bones = center + np.array([[20.0, 10.0, -25.0], [-30.0, 15.0, 30.0], [10.0, -35.0, 40.0], [45.0, -10.0, 5.0],
                               [-40.0, -20.0, -20.0], [0.0, 30.0, 10.0]])
    bone_sigma = np.array([6.0, 5.0, 7.0, 5.0, 6.0, 7.0])

    def hu(p: np.ndarray) -> np.ndarray:
        inside = 1.0 / (1.0 + np.exp((np.sqrt((((p - center) / semi) ** 2).sum(1)) - 1.0) * 20.0))
        tissue = 40.0 + sum(a * np.exp(-((p - b) ** 2).sum(1) / (2 * s * s)) for a, b, s in zip(amp, blobs, sigma))
        tissue = tissue + sum(900.0 * np.exp(-((p - b) ** 2).sum(1) / (2 * s * s)) for b, s in zip(bones, bone_sigma))
        return -1000.0 + inside * (tissue + 1000.0)

    fixed = _volume(size, spacing, origin, flip, hu)
    motion_matrix = params_to_matrix(motion, Grid.from_sitk(fixed).center())
    back = np.linalg.inv(motion_matrix)  # a moving point y shows the fixed content at M^-1 y
    oblique = flip @ np.array([[np.cos(0.17), -np.sin(0.17), 0.0], [np.sin(0.17), np.cos(0.17), 0.0], [0, 0, 1.0]])
    moving = _volume(round(size * 0.8), spacing * 0.9, origin + np.array([-12.0, -18.0, 14.0]), oblique,
                     lambda p: hu(transform_points(back, p)))
    return fixed, moving


def check_convention(method: str, motion: Sequence[float] = KNOWN_MOTION, **kwargs) -> dict:
    """Register :func:`known_motion_pair` with a peer tool and compare with the known motion: what a tool's numbers
    must pass before they count (the benchmarks run it first).

    ``kwargs`` go to :func:`register_ants` / :func:`register_greedy`; ANTs runs ``DenseRigid`` here unless told
    otherwise (its default 20 % sampling leaves degrees of rotation noise on a pair this small; the transform and
    its file are the same).

    Returns:
        ``{"method", "truth", "params", "errors" (per axis, mm / degrees), "ok", "result"}``.
    """
    fixed, moving = known_motion_pair(motion)
    if method == "ants":
        res = register_ants(fixed, moving, **{"type_of_transform": "DenseRigid", **kwargs})
    elif method == "greedy":
        res = register_greedy(fixed, moving, **kwargs)
    else:
        raise ValueError(f"unknown peer method {method!r}; choose from {PEER_METHODS}")
    errors = parameter_errors(res.params, motion)
    ok = bool(np.all(errors[:3] <= CONVENTION_TOLERANCE[0]) and np.all(errors[3:] <= CONVENTION_TOLERANCE[1]))
    return {"method": method, "truth": list(map(float, motion)), "params": res.params.tolist(),
            "errors": errors.tolist(), "ok": ok and not res.stop_condition.startswith("failed"), "result": res}
