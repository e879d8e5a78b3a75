"""``monai-rigidreg evaluate`` (monai_rigidreg.evaluation.evaluate_command): an empty datalist and a bad
--max-cases refused.

Split from the former tests/test_reliability.py (same assertions).
"""

from __future__ import annotations

import json

from conftest import last_line, listing, run_cli


def test_evaluate_refuses_an_empty_datalist_and_a_bad_max_cases(pair, tmp_path, capsys):
    empty = tmp_path / "empty.json"
    empty.write_text(json.dumps({"training": []}))
    code, err = run_cli(capsys, ["evaluate", "--datalist", empty, "--output-dir", tmp_path / "eval"])
    assert code == 2 and "empty.json: datalist key 'training' holds no cases" in last_line(err)
    one = tmp_path / "one.json"
    one.write_text(json.dumps({"training": [{"fixed": pair["fixed"], "moving": pair["moving"], "params": [0] * 6}]}))
    code, err = run_cli(capsys, ["evaluate", "--datalist", one, "--output-dir", tmp_path / "eval", "--max-cases", "0"])
    assert code == 2 and "max_cases must be a whole number >= 1, got 0" in last_line(err)
    assert listing(tmp_path) == ["empty.json", "one.json"]


def test_the_command_s_copies_of_the_methods_and_the_overlay_count_agree():
    """``evaluate_command`` keeps its own copies (its parser is built by ``monai-rigidreg --help``, without torch)."""
    from monai_rigidreg.evaluation import evaluate_command
    from monai_rigidreg.evaluation.evaluate import METHODS
    from monai_rigidreg.evaluation.overlays import DEFAULT_MAX_OVERLAYS

    assert evaluate_command.METHODS == METHODS
    assert evaluate_command.DEFAULT_MAX_OVERLAYS == DEFAULT_MAX_OVERLAYS
