"""The benchmarks' ``--peer-mask`` option: what each choice hands the peer tools, and the label a report prints."""

from __future__ import annotations

import argparse

import pytest

from benchmarks.bench_common import add_peer_mask_option, peer_mask, peer_mask_line


def _parse(*argv: str) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    add_peer_mask_option(ap)
    return ap.parse_args(list(argv))


def test_each_choice_maps_to_register_peer_s_use_mask():
    assert peer_mask(_parse()) is None  # default: each tool's own PEER_FOV_MASK
    assert peer_mask(_parse("--peer-mask", "fov")) is True
    assert peer_mask(_parse("--peer-mask", "none")) is False
    with pytest.raises(SystemExit):
        _parse("--peer-mask", "ct")


def test_the_report_line_names_each_peer_s_mask_and_nothing_for_other_methods(monkeypatch):
    import monai_rigidreg.registration.peers as peers

    monkeypatch.setitem(peers.PEER_FOV_MASK, "ants", False)
    monkeypatch.setitem(peers.PEER_FOV_MASK, "greedy", True)
    lines: list[str] = []

    def say(args, methods):
        lines.clear()
        peer_mask_line(args, methods, lines.append)
        return lines

    assert say(_parse(), ["network", "elastix"]) == []
    assert say(_parse(), ["ants", "greedy"]) == [
        "peer tools' moving-image mask (--peer-mask tool): ants none, greedy the CBCT field of view"]
    assert say(_parse("--peer-mask", "none"), ["greedy"]) == [
        "peer tools' moving-image mask (--peer-mask none): greedy none"]


def test_bench_speed_labels_a_peer_with_the_mask_it_got(monkeypatch):
    import monai_rigidreg.registration.peers as peers
    from benchmarks.speed.bench_speed import baseline_label

    monkeypatch.setitem(peers.PEER_FOV_MASK, "ants", True)
    assert baseline_label("ants") == "ANTs (antspyx, Rigid preset, CBCT FOV mask)"
    assert baseline_label("ants", False) == "ANTs (antspyx, Rigid preset, no mask)"
    assert baseline_label("greedy", True) == "greedy (picsl-greedy, -a -dof 6, NMI, CBCT FOV mask)"
    assert baseline_label("elastix-nomask", True) == "elastix (default rigid map, no mask)"


def _fake_result(center=None):
    import numpy as np

    from monai_rigidreg.registration.classical import ClassicalResult

    return ClassicalResult(np.zeros(6), np.zeros(3) if center is None else np.asarray(center), runtime_s=0.0,
                           stop_condition="fake")


def test_bench_speed_hands_each_baseline_its_mask(monkeypatch, tmp_path):
    import numpy as np
    import SimpleITK as sitk

    import benchmarks.speed.bench_speed as bench_speed
    import monai_rigidreg.registration.classical as classical
    import monai_rigidreg.registration.peers as peers

    fov = sitk.Image([4, 4, 4], sitk.sitkUInt8)
    monkeypatch.setattr(bench_speed, "load_case", lambda d: ({}, sitk.Image([4, 4, 4], sitk.sitkFloat32), None))
    monkeypatch.setattr(bench_speed.sitk, "ReadImage", lambda path: fov)
    monkeypatch.setattr(bench_speed, "tre_mm", lambda *a: 0.0)
    got = []
    monkeypatch.setattr(classical, "register_elastix",
                        lambda f, m, moving_mask=None: got.append(("elastix", moving_mask is fov)) or _fake_result())
    monkeypatch.setattr(peers, "register_greedy",
                        lambda f, m, c=None, mask=None: got.append(("greedy", mask is fov)) or _fake_result())
    ct = sitk.Image([4, 4, 4], sitk.sitkFloat32)
    for method, use, expect in (("elastix", None, True), ("elastix-nomask", None, False), ("greedy", None, True),
                                ("greedy", False, False), ("greedy", True, True)):
        got.clear()
        rows = bench_speed.baseline_rows(ct, [tmp_path], method, use)
        assert got == [(method.split("-")[0], expect)] and len(rows) == 1 and np.isfinite(rows[0]["time_s"])


def test_bench_clinical_geometry_hands_the_peer_its_mask(monkeypatch):
    from types import SimpleNamespace

    import numpy as np

    import monai_rigidreg.registration.peers as peers
    from benchmarks.accuracy.bench_clinical_geometry import run_method

    fov = object()
    got = []
    monkeypatch.setattr(peers, "register_ants",
                        lambda f, m, c=None, mask=None: got.append(mask is fov) or _fake_result(c))
    ct = SimpleNamespace(center=np.zeros(3), image=None)
    case = SimpleNamespace(cbct=None, fov=fov, record={"deformation": None})
    for use, expect in ((None, True), (False, False), (True, True)):
        got.clear()
        out = run_method("ants", ct, case, None, False, use)
        assert got == [expect] and out["params"].shape == (6,)
