"""The distributed evaluation's pieces (``monai_rigidreg.evaluation.distributed``): the ranks' shares of a datalist
under MONAI's ``DistributedSampler``, the merge that takes every case exactly once, and one pass through the
collective calls in a one-process gloo group. Two processes under ``torchrun``: ``tests/bundle/test_bundle.py``
(``slow``)."""

from __future__ import annotations

import json

import pytest
import torch.distributed as dist
from monai.data import DistributedSampler

from monai_rigidreg.evaluation.distributed import DistributedEvaluationError, _merge, evaluate_distributed, rank_share
from monai_rigidreg.evaluation.report import CaseResult


def _shares(n: int, world: int, even_divisible: bool) -> list[list[int]]:
    return [rank_share(n, r, world, DistributedSampler(list(range(n)), even_divisible=even_divisible,
                                                       num_replicas=world, rank=r, shuffle=False))
            for r in range(world)]


def test_sampler_without_padding_shares_every_case_once():
    for n, world in ((3, 2), (5, 3), (4, 4)):
        shares = _shares(n, world, even_divisible=False)
        assert sorted(i for s in shares for i in s) == list(range(n))
    with pytest.raises(ValueError, match="less than the number"):  # MONAI's: fewer cases than processes
        _shares(2, 4, even_divisible=False)
    assert _shares(3, 2, even_divisible=False) == [[0, 2], [1]]
    assert rank_share(5, 1, 2) == [1, 3]  # no sampler: every world-th case
    assert rank_share(3, 0, 2, sampler=[0, 2, 4]) == [0, 2]  # max_cases cuts the sampler's indices


def _case(i: int, method: str = "m") -> CaseResult:
    return CaseResult(f"c{i}", method, [0.0] * 6, [float(i)] + [0.0] * 5, float(i), 0.1)


def _gathered(shares: list[list[int]]) -> list[dict]:
    return [{"share": s, "cases": [_case(i) for i in s], "images": {}, "omitted": 0} for s in shares]


def test_merge_orders_the_cases_and_refuses_padding_or_gaps():
    items = [{"case_id": f"c{i}"} for i in range(3)]
    merged = _merge(_gathered([[0, 2], [1]]), 3, 1, items, "d.json", None, html=False)
    assert [c.case_id for c in merged["cases"]] == ["c0", "c1", "c2"] and merged["paths"] == {}
    padded = _shares(3, 2, even_divisible=True)  # MONAI pads the last rank with a case of the first
    with pytest.raises(DistributedEvaluationError, match="two ranks.*even_divisible=False"):
        _merge(_gathered(padded), 3, 1, items, "d.json", None, html=False)
    with pytest.raises(DistributedEvaluationError, match="no rank.*c1"):
        _merge(_gathered([[0, 2], []]), 3, 1, items, "d.json", None, html=False)


@pytest.fixture
def one_process_group(tmp_path):
    dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'rendezvous'}", rank=0, world_size=1)
    try:
        yield
    finally:
        dist.destroy_process_group()


def test_one_process_group_writes_the_report_of_a_plain_evaluation(one_process_group, tiny_dataset, tmp_path):
    """Through the broadcast, the exchange and the staged report folder: the same cases and numbers as
    ``evaluate_datalist``, the report files and overlays in place, no staging folder left."""
    from monai_rigidreg.evaluation.evaluate import evaluate_datalist

    out = evaluate_distributed(tiny_dataset, ["sitk"], tmp_path / "report", max_cases=2, max_overlays=1)
    plain = evaluate_datalist(tiny_dataset, ["sitk"], None, max_cases=2, progress=False)
    assert [c.case_id for c in out["cases"]] == [c.case_id for c in plain["cases"]]
    assert {p.name for p in (tmp_path / "report").iterdir()} == {"cases.csv", "summary.json", "report.md",
                                                               "report.html", "report_files"}
    assert out["paths"]["html"] == tmp_path / "report" / "report.html"
    assert json.loads((tmp_path / "report" / "summary.json").read_text())["summary"]["sitk"]["n"] == 2
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_failing_rank_raises_and_leaves_no_report(one_process_group, tiny_dataset, tmp_path):
    class Broken:
        def __call__(self, *args, **kwargs):
            raise RuntimeError("out of memory")

    with pytest.raises(DistributedEvaluationError, match="rank 0: RuntimeError: out of memory"):
        evaluate_distributed(tiny_dataset, ["network"], tmp_path / "report", registrar=Broken())
    assert not (tmp_path / "report").exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
