"""The benchmarks' registrar options (``benchmarks/bench_common.py``): ``--fine-stage-choice-mm`` and
``--native-final-norm-mm`` parsed and set on a registrar, and the fine-stage choice's one-line summary."""

from __future__ import annotations

import argparse
import types

import pytest

from benchmarks.bench_common import (
    add_registrar_options,
    apply_registrar_options,
    fine_stage_choice_summary,
    registrar_options_line,
)


def _parse(*argv: str) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    add_registrar_options(ap)
    return ap.parse_args(list(argv))


def test_the_options_set_what_was_given_and_leave_the_rest():
    registrar = types.SimpleNamespace(fine_stage_choice_mm=5.0, native_final_norm_mm=None)
    apply_registrar_options(registrar, _parse())
    assert (registrar.fine_stage_choice_mm, registrar.native_final_norm_mm) == (5.0, None)
    apply_registrar_options(registrar, _parse("--fine-stage-choice-mm", "off", "--native-final-norm-mm", "8"))
    assert (registrar.fine_stage_choice_mm, registrar.native_final_norm_mm) == (None, 8.0)
    apply_registrar_options(registrar, _parse("--fine-stage-choice-mm", "2.5"))
    assert registrar.fine_stage_choice_mm == 2.5
    assert registrar_options_line(registrar) == "registrar: fine_stage_choice_mm 2.5, native_final_norm_mm 8.0"
    for bad in ("-1", "many"):
        with pytest.raises(SystemExit):
            _parse("--fine-stage-choice-mm", bad)


def test_the_summary_counts_the_moves_the_runs_and_the_regressions_kept():
    choices = [{"move_mm": 0.5}, None, {"move_mm": 31.0, "kept": "regression"},
               {"move_mm": 7.0, "kept": "fine stage"}, {"move_mm": 1.5}]
    line = fine_stage_choice_summary(choices)
    assert line == ("fine-stage choice: the fine stage moved the regression's estimate median 4.25 mm, max 31.00 mm "
                    "over 4 cases; the choice ran on 2, the regression's end pose kept on 1")
    assert fine_stage_choice_summary([None, None]) == "fine-stage choice: not recorded"
