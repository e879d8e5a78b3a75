"""Random 6-DoF rigid motion of images in physical space (``RandRigid6DoF`` / ``RandRigid6DoFd``).

Semantics (see ``docs/conventions.md``): *moving an image by a motion* ``M`` means that an object point at
``p`` (LPS mm) appears at ``M(p)`` in the output, ``out(y) = in(M^-1(y))``; the output stays on the input grid
(same shape, same affine), only the content moves. If the input was a fixed image ``F`` and the output is used as
the moving image, the registration transform (fixed -> moving) is ``T = M`` and
``sitk.Resample(out, F, params_to_sitk(params, center))`` reproduces ``F``.

``M(x) = R (x - c) + c + t`` with ``R = Rz(rz) Rx(rx) Ry(ry)``: exactly ``SimpleITK.Euler3DTransform`` with
user parameters ``(tx, ty, tz, rx, ry, rz)`` in mm / degrees, built with :func:`monai_rigidreg.core.geometry`.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from monai.config import KeysCollection
from monai.data import MetaTensor
from monai.data.meta_obj import get_track_meta
from monai.transforms import InvertibleTransform, MapTransform, RandomizableTransform
from monai.utils import TraceKeys, convert_to_dst_type, convert_to_tensor, ensure_tuple, ensure_tuple_rep

from monai_rigidreg.core.geometry import Grid, compose_matrices, invert_matrix, matrix_to_params, params_to_matrix
from monai_rigidreg.transforms.utils import (
    PaddingValue,
    as_matrix,
    as_vector,
    ensure_range_pairs,
    grid_of,
    like,
    resample_physical,
)

__all__ = [
    "Rigid6DoF",
    "RandRigid6DoF",
    "RandRigid6DoFd",
    "apply_rigid_motion",
    "sample_rigid_params",
    "RIGID_KEY",
]

RIGID_KEY = "rigid_params"
"""Default key of the ground truth written by :class:`RandRigid6DoFd`."""

_CONSTRUCTOR: Any = object()
"""Default of an override whose ``None`` means something: use the constructor's value."""


def apply_rigid_motion(
    img: torch.Tensor,
    motion: Any,
    grid: Grid | None = None,
    mode: str = "bilinear",
    padding_mode: str = "zeros",
    padding_value: PaddingValue = "min",
) -> torch.Tensor:
    """Move the content of a channel-first image ``[C, x, y, z]`` by the physical motion ``motion`` (4x4, LPS mm).

    ``out(y) = img(motion^-1(y))`` on the same grid: an object point at ``p`` ends up at ``motion(p)``.

    Args:
        img: plain tensor ``[C, x, y, z]`` (any dtype/device).
        motion: 4x4 rigid matrix (LPS mm), e.g. from :func:`monai_rigidreg.core.geometry.params_to_matrix`.
        grid: grid of ``img`` (default: identity RAS affine).
        mode: ``"bilinear"`` or ``"nearest"``.
        padding_mode: ``grid_sample`` padding mode, used when ``padding_value`` is ``None``.
        padding_value: constant for voxels that come from outside the image (``"min"``: per-channel minimum).
    """
    grid = grid_of(img) if grid is None else grid
    return resample_physical(img, invert_matrix(as_matrix(motion)), grid, grid, mode, padding_mode, padding_value)


def sample_rigid_params(
    rng: np.random.RandomState,
    ranges: np.ndarray,
    axis_prob: np.ndarray,
    step: np.ndarray,
) -> np.ndarray:
    """Draw ``(tx, ty, tz, rx, ry, rz)`` (mm / degrees).

    Args:
        rng: random state.
        ranges: ``[6, 2]`` (low, high) per parameter.
        axis_prob: ``[6]`` probability that each parameter is perturbed (else it is 0).
        step: ``[6]`` discretization step per parameter (0: continuous); with a step, the value is drawn uniformly
            among the multiples of the step inside ``[low, high]``.
    """
    active = rng.uniform(size=6) < axis_prob
    u = rng.uniform(size=6)
    params = np.zeros(6)
    for i in range(6):
        lo, hi = ranges[i]
        if step[i] > 0:
            kmin = int(np.ceil(lo / step[i] - 1e-9))
            kmax = int(np.floor(hi / step[i] + 1e-9))
            value = (kmin + min(int(u[i] * (kmax - kmin + 1)), kmax - kmin)) * step[i] if kmax >= kmin else 0.0
        else:
            value = lo + u[i] * (hi - lo)
        params[i] = value if active[i] else 0.0
    return params + 0.0  # no negative zeros


def _param_config(
    translate_range: Any, rotate_range: Any, axis_prob: Any, step: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    ranges = np.concatenate(
        [ensure_range_pairs(translate_range, 3, "translate_range"), ensure_range_pairs(rotate_range, 3, "rotate_range")]
    )
    ap = np.asarray(ensure_tuple_rep(axis_prob, 6) if np.ndim(axis_prob) == 0 else axis_prob, dtype=np.float64)
    if ap.shape != (6,) or np.any(ap < 0) or np.any(ap > 1):
        raise ValueError(f"axis_prob must be a probability or 6 probabilities, got {axis_prob!r}")
    if step is None:
        st = np.zeros(6)
    elif np.ndim(step) == 0:
        st = np.full(6, float(step))
    elif len(step) == 2:
        st = np.repeat(np.asarray(step, dtype=np.float64), 3)
    else:
        st = np.asarray(step, dtype=np.float64)
    if st.shape != (6,) or np.any(st < 0):
        raise ValueError(f"step must be None, a number, (mm, degrees) or 6 non-negative numbers, got {step!r}")
    return ranges, ap, st


class Rigid6DoF(InvertibleTransform):
    """Apply a given 6-DoF rigid motion to a channel-first image ``[C, x, y, z]`` in physical space.

    The content moves, the grid does not: an object point at ``p`` (LPS mm) appears at ``M(p)`` with
    ``M = params_to_matrix(params, center)``. Anisotropic spacing and oblique directions are handled through the
    ``MetaTensor`` affine (RAS by default, LPS if ``meta["space"] == "LPS"``); a plain tensor has an identity RAS
    affine.

    Args:
        params: ``(tx, ty, tz, rx, ry, rz)`` in mm / degrees (Euler3D convention), or ``None`` with ``matrix``.
        center: rotation centre (LPS mm). Default: the physical centre of each image.
        matrix: a 4x4 motion (LPS mm) instead of ``params``/``center``.
        mode: ``"bilinear"`` (trilinear) or ``"nearest"`` (masks, labels).
        padding_mode: ``grid_sample`` padding used when ``padding_value`` is ``None``.
        padding_value: value of voxels moved in from outside the image: a number (e.g. ``-1000.0`` HU), ``"min"``
            (per-channel minimum of the input, default) or ``None``.
    """

    def __init__(
        self,
        params: Sequence[float] | None = None,
        center: Sequence[float] | None = None,
        matrix: Any = None,
        mode: str = "bilinear",
        padding_mode: str = "zeros",
        padding_value: PaddingValue = "min",
    ) -> None:
        if (params is None) == (matrix is None):
            raise ValueError("give exactly one of params and matrix")
        self.params = None if params is None else as_vector(params, 6)
        self.center = None if center is None else as_vector(center, 3)
        self.matrix = None if matrix is None else as_matrix(matrix)
        self.mode = mode
        self.padding_mode = padding_mode
        self.padding_value = padding_value

    def motion_for(self, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
        """The 4x4 motion (LPS mm) and the centre used for an image on ``grid``."""
        c = grid.center() if self.center is None else self.center
        if self.matrix is not None:
            return self.matrix, c
        return params_to_matrix(self.params, c), c

    def __call__(self, img: Any, mode: str | None = None, padding_mode: str | None = None) -> torch.Tensor:
        """
        Args:
            img: channel-first image ``[C, x, y, z]`` (``MetaTensor``, tensor or array).
            mode, padding_mode: override the constructor's.

        Returns:
            the moved image, same type, shape, affine, dtype and device.
        """
        img = convert_to_tensor(img, track_meta=get_track_meta())
        motion, _ = self.motion_for(grid_of(img))
        return _move_and_push(
            self,
            img,
            motion,
            mode or self.mode,
            padding_mode or self.padding_mode,
            self.padding_value,
            do_transform=True,
        )

    def inverse(self, data: torch.Tensor) -> torch.Tensor:
        """Undo :meth:`__call__` (apply the inverse motion; content moved out of the grid is lost)."""
        transform = self.pop_transform(data)
        return _undo(data, transform, self.padding_value)


def _move_and_push(
    xform: InvertibleTransform,
    img: torch.Tensor,
    motion: np.ndarray,
    mode: str,
    padding_mode: str,
    padding_value: PaddingValue,
    do_transform: bool,
) -> torch.Tensor:
    """Move ``img`` (if ``do_transform``) and push the motion to its ``applied_operations``."""
    if do_transform:
        raw = img.as_tensor() if isinstance(img, MetaTensor) else img
        out = resample_physical(
            raw, invert_matrix(motion), grid_of(img), grid_of(img), mode, padding_mode, padding_value
        )
        out = convert_to_dst_type(out, img)[0]
    else:
        out = img.clone() if isinstance(img, torch.Tensor) else img
    extra = {"matrix": torch.as_tensor(motion, dtype=torch.float64), "mode": mode, "padding_mode": padding_mode}
    return xform.push_transform(out, extra_info=extra)


def _undo(data: torch.Tensor, transform: Mapping, padding_value: PaddingValue) -> torch.Tensor:
    if not transform.get(TraceKeys.DO_TRANSFORM, True):
        return data
    info = transform[TraceKeys.EXTRA_INFO]
    motion = as_matrix(info["matrix"])
    raw = data.as_tensor() if isinstance(data, MetaTensor) else data
    out = resample_physical(
        raw, motion, grid_of(data), grid_of(data), info["mode"], info["padding_mode"], padding_value
    )
    return convert_to_dst_type(out, data)[0]


class RandRigid6DoF(RandomizableTransform, InvertibleTransform):
    """Random 6-DoF rigid motion of a channel-first image ``[C, x, y, z]`` in physical space (LPS mm).

    With probability ``prob`` draws ``(tx, ty, tz, rx, ry, rz)``: each parameter is perturbed with probability
    ``axis_prob`` (so single-axis and multi-axis perturbations both occur), uniformly in its range, optionally on
    a grid of ``step``. The image content is then moved by ``M = params_to_matrix(params, center)`` (see
    :class:`Rigid6DoF`): a point at ``p`` appears at ``M(p)``. Used as the moving image against the unmoved
    input as the fixed image, ``M`` is the registration ground truth (fixed -> moving).

    The last draw is kept in ``last_params`` (``[6]``, mm / degrees, zeros when not applied), ``last_center``
    (``[3]``, LPS mm) and ``last_matrix`` (4x4, LPS mm).

    Args:
        prob: probability of moving the image at all.
        translate_range: translation range in mm: ``a`` (``[-a, a]`` on every axis), ``(ax, ay, az)`` or three
            ``(low, high)`` pairs (LPS axes). Default +-15 mm.
        rotate_range: rotation range in degrees about the LPS axes, same forms. Default +-30 degrees.
        axis_prob: probability that each parameter is non-zero: one number or six (``tx..rz``).
        step: ``None`` (continuous), one number (mm and degrees), ``(mm, degrees)`` or six numbers: draw only
            multiples of the step (e.g. ``(5.0, 5.0)`` reproduces a 5 mm / 5 degree grid of offsets).
        center: rotation centre (LPS mm). Default: the physical centre of the image.
        mode: ``"bilinear"`` or ``"nearest"``.
        padding_mode: ``grid_sample`` padding used when ``padding_value`` is ``None``.
        padding_value: value of voxels moved in from outside: number (e.g. ``-1000.0`` HU), ``"min"`` or ``None``.
    """

    def __init__(
        self,
        prob: float = 1.0,
        translate_range: Any = 15.0,
        rotate_range: Any = 30.0,
        axis_prob: float | Sequence[float] = 1.0,
        step: float | Sequence[float] | None = None,
        center: Sequence[float] | None = None,
        mode: str = "bilinear",
        padding_mode: str = "zeros",
        padding_value: PaddingValue = "min",
    ) -> None:
        RandomizableTransform.__init__(self, prob)
        self.ranges, self.axis_prob, self.step = _param_config(translate_range, rotate_range, axis_prob, step)
        self.center = None if center is None else as_vector(center, 3)
        self.mode = mode
        self.padding_mode = padding_mode
        self.padding_value = padding_value
        self._params = np.zeros(6)
        self.last_params = np.zeros(6)
        self.last_center = np.zeros(3)
        self.last_matrix = np.eye(4)

    def randomize(self, data: Any = None) -> None:
        super().randomize(None)
        self._params = (
            sample_rigid_params(self.R, self.ranges, self.axis_prob, self.step) if self._do_transform else np.zeros(6)
        )

    def record_motion(self, center: Sequence[float]) -> np.ndarray:
        """The motion of the current draw about ``center`` (LPS mm), kept in ``last_params``, ``last_center`` and
        ``last_matrix``; returns ``last_matrix`` (4x4)."""
        self.last_params = self._params.copy()
        self.last_center = np.asarray(center, dtype=np.float64)
        self.last_matrix = params_to_matrix(self._params, center)
        return self.last_matrix

    def __call__(
        self,
        img: Any,
        randomize: bool = True,
        mode: str | None = None,
        padding_mode: str | None = None,
        center: Sequence[float] | None = None,
        padding_value: PaddingValue | object = _CONSTRUCTOR,
    ) -> torch.Tensor:
        """
        Args:
            img: channel-first image ``[C, x, y, z]`` (``MetaTensor``, tensor or array).
            randomize: draw new parameters (else reuse the last draw).
            mode, padding_mode: override the constructor's.
            center: rotation centre (LPS mm) instead of the constructor's (or the image centre).
            padding_value: override the constructor's (``None`` is a value here: use ``padding_mode``).

        Returns:
            the moved image: same type, shape, affine, dtype and device.
        """
        img = convert_to_tensor(img, track_meta=get_track_meta())
        if randomize:
            self.randomize()
        if center is None:
            center = grid_of(img).center() if self.center is None else self.center
        return _move_and_push(
            self,
            img,
            self.record_motion(center),
            mode or self.mode,
            padding_mode or self.padding_mode,
            self.padding_value if padding_value is _CONSTRUCTOR else padding_value,
            do_transform=self._do_transform,
        )

    def inverse(self, data: torch.Tensor) -> torch.Tensor:
        """Undo :meth:`__call__` (apply the inverse motion; content moved out of the grid is lost)."""
        transform = self.pop_transform(data)
        return _undo(data, transform, self.padding_value)


class RandRigid6DoFd(RandomizableTransform, MapTransform, InvertibleTransform):
    """Dictionary version of :class:`RandRigid6DoF`: one draw moves every key, and the ground truth is recorded.

    ``keys`` (e.g. ``"moving"``) are moved with ``mode``; ``mask_keys`` (labels, masks) with the same motion,
    ``"nearest"`` and padding 0. Keys not listed (e.g. ``"fixed"``) are untouched.

    Recorded ground truth, always written to ``data[output_key]`` (default ``"rigid_params"``)::

        {"params": Tensor[6]   (tx, ty, tz, rx, ry, rz) in mm / degrees, about "center",
         "matrix": Tensor[4, 4] registration transform fixed -> moving (LPS mm),
         "center": Tensor[3]   rotation centre (LPS mm): the fixed image centre}

    (``gt_dtype``, float32 by default.) MONAI's ``list_data_collate`` turns it into ``[B, 6]``, ``[B, 4, 4]`` and
    ``[B, 3]`` tensors, and ``params_to_sitk(params[b], center[b])`` is the ``Euler3DTransform`` for which
    ``sitk.Resample(moving, fixed, T)`` puts the moved image back onto the fixed one.

    Composition with an existing ground truth ``T0`` (the item already is a pair): if ``data[output_key]`` exists
    (a dict with ``"matrix"``, or ``"params"`` and ``"center"``), or else the simulator's top-level keys
    ``prior_keys`` (``"params"`` / ``"matrix"`` / ``"center"``) exist, the new motion ``M`` is applied after it:
    ``T = M o T0`` (matrix ``M @ T0``), re-expressed about the recorded centre. With ``update_prior=True`` the
    top-level prior keys are overwritten with the new total (same container type) so the item stays consistent.

    Centre (rotation centre of ``M`` and recorded centre): ``center`` if given; else the physical centre of
    ``data[center_key]`` (e.g. ``"fixed"``) if given; else the centre of the prior ground truth; else the centre of
    the first moved key (the fixed image, when moving starts as a copy of it).

    The last motion alone (without the prior) is kept in ``last_params``, ``last_center`` and ``last_matrix``.

    Args:
        keys: keys of the images to move.
        center_key: key of the fixed image whose physical centre is the rotation centre.
        mode: interpolation for ``keys``, one or one per key.
        padding_mode: ``grid_sample`` padding for ``keys`` when ``padding_value`` is ``None``.
        padding_value: padding for ``keys``, one or one per key (default ``"min"``: the image minimum).
        mask_keys: keys moved with nearest-neighbour interpolation and padding 0.
        output_key: where the ground truth is written.
        prior_keys: top-level keys of an existing ground truth ``(params, matrix, center)``; ``None`` to ignore.
        update_prior: overwrite those top-level keys with the new total.
        gt_dtype: dtype of the recorded tensors.
        allow_missing_keys: don't raise if a key is missing.
        kwargs: the motion, as :class:`RandRigid6DoF`: ``prob``, ``translate_range``, ``rotate_range``,
            ``axis_prob``, ``step`` and ``center`` (rotation centre, LPS mm).
    """

    def __init__(
        self,
        keys: KeysCollection,
        *,
        center_key: Hashable | None = None,
        mode: str | Sequence[str] = "bilinear",
        padding_mode: str | Sequence[str] = "zeros",
        padding_value: PaddingValue | Sequence[PaddingValue] = "min",
        mask_keys: KeysCollection | None = None,
        output_key: Hashable = RIGID_KEY,
        prior_keys: Sequence[Hashable] | None = ("params", "matrix", "center"),
        update_prior: bool = True,
        gt_dtype: torch.dtype = torch.float32,
        allow_missing_keys: bool = False,
        **kwargs: Any,
    ) -> None:
        self.image_keys = ensure_tuple(keys)
        self.mask_keys = ensure_tuple(mask_keys) if mask_keys is not None else ()
        MapTransform.__init__(self, self.image_keys + self.mask_keys, allow_missing_keys)
        self.rigid = RandRigid6DoF(**kwargs)  # draws the motion and moves each key
        RandomizableTransform.__init__(self, self.rigid.prob)
        self.center = self.rigid.center
        self.center_key = center_key
        n_img, n_mask = len(self.image_keys), len(self.mask_keys)
        pv = (
            [padding_value] * n_img
            if padding_value is None or isinstance(padding_value, (str, int, float))
            else list(padding_value)
        )
        if len(pv) != n_img:
            raise ValueError(f"padding_value needs one value or {n_img}, got {padding_value!r}")
        self.mode = ensure_tuple_rep(mode, n_img) + ("nearest",) * n_mask
        self.padding_mode = ensure_tuple_rep(padding_mode, n_img) + ("zeros",) * n_mask
        self.padding_value = tuple(pv) + (0.0,) * n_mask
        self.output_key = output_key
        self.prior_keys = tuple(prior_keys) if prior_keys is not None else None
        if self.prior_keys is not None and len(self.prior_keys) != 3:
            raise ValueError(f"prior_keys must name (params, matrix, center), got {prior_keys!r}")
        self.update_prior = update_prior
        self.gt_dtype = gt_dtype

    def set_random_state(self, seed: int | None = None, state: np.random.RandomState | None = None) -> RandRigid6DoFd:
        super().set_random_state(seed, state)
        self.rigid.set_random_state(seed, state)
        return self

    def randomize(self, data: Any = None) -> None:
        self.rigid.randomize(None)
        self._do_transform = self.rigid._do_transform

    last_params = property(lambda self: self.rigid.last_params, doc="``[6]`` last motion alone (mm / degrees).")
    last_center = property(lambda self: self.rigid.last_center, doc="``[3]`` centre of the last motion (LPS mm).")
    last_matrix = property(lambda self: self.rigid.last_matrix, doc="4x4 last motion alone (LPS mm).")

    # -- ground truth ------------------------------------------------------------------------------------------
    def _prior(self, d: Mapping) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(T0 matrix, T0 centre) of an existing ground truth, or (None, None)."""
        rec = d.get(self.output_key)
        if isinstance(rec, Mapping):
            c0 = as_vector(rec["center"], 3) if "center" in rec else None
            if "matrix" in rec:
                return as_matrix(rec["matrix"]), c0
            if "params" in rec:
                return params_to_matrix(as_vector(rec["params"], 6), c0), c0
        if self.prior_keys is not None:
            kp, km, kc = self.prior_keys
            c0 = as_vector(d[kc], 3) if kc in d else None
            if km in d:
                return as_matrix(d[km]), c0
            if kp in d:
                return params_to_matrix(as_vector(d[kp], 6), c0), c0
        return None, None

    def _center(self, d: Mapping, prior_center: np.ndarray | None) -> np.ndarray:
        if self.center is not None:
            return self.center
        if self.center_key is not None and self.center_key in d:
            return grid_of(d[self.center_key]).center()
        if prior_center is not None:
            return prior_center
        for key in self.key_iterator(d):
            return grid_of(d[key]).center()
        raise KeyError(f"none of {self.keys} in the data, and no centre given")

    def __call__(self, data: Mapping[Hashable, Any]) -> dict[Hashable, Any]:
        """
        Args:
            data: dictionary with channel-first images ``[C, x, y, z]`` under ``keys``/``mask_keys``.

        Returns:
            a new dictionary with the moved images and the ground truth under ``output_key``.
        """
        d = dict(data)
        self.randomize()
        t0, c0 = self._prior(d)
        c = self._center(d, c0)
        motion = self.rigid.record_motion(c)
        for key, mode, pmode, pval in self.key_iterator(d, self.mode, self.padding_mode, self.padding_value):
            d[key] = self.rigid(d[key], False, mode, pmode, center=c, padding_value=pval)
        total = motion if t0 is None else compose_matrices(motion, t0)
        params = matrix_to_params(total, c)
        d[self.output_key] = {
            "params": torch.as_tensor(params, dtype=self.gt_dtype),
            "matrix": torch.as_tensor(total, dtype=self.gt_dtype),
            "center": torch.as_tensor(c, dtype=self.gt_dtype),
        }
        if self.update_prior and self.prior_keys is not None:
            for name, value in zip(self.prior_keys, (params, total, c)):
                if name in d:
                    d[name] = like(value, d[name])
        return d

    def inverse(self, data: Mapping[Hashable, Any]) -> dict[Hashable, Any]:
        """Undo the motion on every moved key (the recorded ground truth is left as is)."""
        d = dict(data)
        for key, pval in self.key_iterator(d, self.padding_value):
            transform = self.rigid.pop_transform(d[key])
            d[key] = _undo(d[key], transform, pval)
        return d
