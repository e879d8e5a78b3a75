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
