"""The bone-agreement signal (registration.bone_check): the CT's bone on the CBCT's brightest voxels."""

from __future__ import annotations

import math

import pytest
import torch

from monai_rigidreg.registration.bone_check import bone_agreement

WINDOW = (-1000.0, 2000.0)


def _norm(hu: torch.Tensor) -> torch.Tensor:
    return (hu - WINDOW[0]) / (WINDOW[1] - WINDOW[0])


def _head(radius: float, thickness: float, size: int = 48, shift=(0, 0, 0)) -> torch.Tensor:
    """A head-like volume in HU on a 2 mm grid: water inside a bone shell (800 HU) of ``radius`` / ``thickness`` mm,
    air outside, a small bright nodule (the inner ear) off centre; ``shift`` in voxels."""
    ax = (torch.arange(size, dtype=torch.float32) - (size - 1) / 2) * 2.0
    x, y, z = torch.meshgrid(ax - 2 * shift[0], ax - 2 * shift[1], ax - 2 * shift[2], indexing="ij")
    r = torch.sqrt(x**2 + y**2 + (z * 1.2) ** 2)
    hu = torch.full((size, size, size), -1000.0)
    hu[r < radius] = 0.0
    hu[(r < radius) & (r > radius - thickness)] = 800.0
    hu[((x - 10) ** 2 + (y + 6) ** 2 + z**2) < 25.0] = 900.0
    return hu


def _cbct(hu: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """The CBCT's view of the same anatomy: bone compressed to about 300 HU, soft tissue lifted, noise."""
    g = torch.Generator().manual_seed(seed)
    return 0.35 * hu - 120.0 + 25.0 * torch.randn(hu.shape, generator=g)


def test_the_same_anatomy_agrees_another_does_not():
    ct = _head(40.0, 6.0)
    view = torch.ones_like(ct)
    share, agree = bone_agreement(_norm(ct), _cbct(ct), view, WINDOW)
    # the bone's share of the body (0.39 before the box smoothing, which widens the body at the skin and narrows
    # the shell); a thicker shell has more
    assert 0.25 < share < 0.4
    assert bone_agreement(_norm(_head(40.0, 10.0)), _cbct(ct), view, WINDOW)[0] > share + 0.1
    assert agree > 0.95
    # another head: a smaller skull, thicker bone
    _, other = bone_agreement(_norm(ct), _cbct(_head(34.0, 9.0)), view, WINDOW)
    assert other < agree - 0.25
    # the same head 6 mm off along x: much of the shell misses
    _, shifted = bone_agreement(_norm(ct), _cbct(_head(40.0, 6.0, shift=(3, 0, 0))), view, WINDOW)
    assert shifted < agree - 0.25


def test_only_the_cbcts_ranks_count_and_a_negated_cbct_fails():
    ct = _head(40.0, 6.0)
    view = torch.ones_like(ct)
    cb = _cbct(ct)
    _, agree = bone_agreement(_norm(ct), cb, view, WINDOW)
    _, rescaled = bone_agreement(_norm(ct), 3.0 * cb + 500.0, view, WINDOW)  # any increasing scale of the CBCT
    assert rescaled == pytest.approx(agree, abs=1e-6)
    _, negated = bone_agreement(_norm(ct), -cb, view, WINDOW)  # bone darkest: the sign matters
    assert negated < 0.05


def test_outside_the_view_and_without_bone_it_is_not_measured():
    ct = _head(40.0, 6.0)
    cb = _cbct(ct)
    half = torch.zeros_like(ct)
    half[:24] = 1.0
    _, agree_half = bone_agreement(_norm(ct), cb, half, WINDOW)
    assert agree_half > 0.85  # the view restricts both sides
    share, agree = bone_agreement(_norm(ct), cb, torch.zeros_like(ct), WINDOW)
    assert math.isnan(share) and math.isnan(agree)
    water = torch.where(ct > -500, torch.zeros_like(ct), ct)  # no bone
    share, agree = bone_agreement(_norm(water), _cbct(water), torch.ones_like(ct), WINDOW)
    assert share == 0.0 and math.isnan(agree)
