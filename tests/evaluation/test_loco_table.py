"""The leave-one-CT-out table reads the evaluation reports as ``scripts/eval_loco.sh`` writes them."""

import json

import pytest

from benchmarks.accuracy.loco_table import collect, format_table, parse_clinical, parse_paper

PAPER = """command: python -m benchmarks.accuracy.bench_real_ct ...
| method | n | mean TRE (mm) | median TRE (mm) | success (<2 mm) | <12 mm | ... (per axis, time) |
|---|---|---|---|---|---|---|---|---|---|---|---|---|---|
| network-regression | 12 | {mean} | 0.23 | 92% | 100% | 0.11 | 0.05 | 0.07 | 0.07 | 0.08 | 0.14 | 1.41 | - |
| identity (no registration) | 12 | 20.52 | 18.11 | 0% | 42% | 4.17 | 3.33 | 1.67 | 7.08 | 5.42 | 3.75 | - | - |
"""

CLINICAL = """| group | method | n | mean TRE (mm) | median TRE (mm) | success (<2 mm) | ... (landmarks, flags, time) |
|---|---|---|---|---|---|---|---|---|---|---|---|
| small | network-regression | 4 | 1.52 | 1.50 | 50% | 1.14 / 1.17 | - | - | - | 2.20 | - |
| small | identity | 4 | 34.16 | 34.29 | 0% | 24.38 / 26.35 | - | - | - | - | - |
| large | network-regression | 4 | 13.55 | 0.54 | 75% | 16.16 / 0.49 | - | - | - | 2.01 | - |
| small+large | network-regression | 8 | 7.54 | 0.78 | 62% | 8.65 / 0.51 | - | - | - | 2.07 | - |
| small+large | identity | 8 | 53.33 | 52.94 | 0% | 40.47 / 40.98 | - | - | - | - | - |

Failed cases per method (rigid groups: TRE >= 2 mm; ...)

network-regression: 3 of 8 failed
  - ct_a small_002: TRE 2.13 mm (identity 26.97), confidence 0.49 flagged; isocentre 72 mm
  - ct_a small_003: TRE 7.60 mm (identity 32.33), confidence 0.49 flagged; isocentre 55 mm
  - ct_a large_002: TRE 52.81 mm (identity 64.78), confidence 0.49 flagged; isocentre 90 mm

Run
"""


def test_the_paper_row_is_the_network_s_with_shares_as_fractions_and_axes_in_order():
    p = parse_paper(PAPER.format(mean="0.25"))
    assert p["n"] == 12 and p["mean_mm"] == 0.25 and p["median_mm"] == 0.23
    assert p["success"] == pytest.approx(0.92)
    assert [p[k] for k in ("tx", "ty", "tz", "rx", "ry", "rz")] == [0.11, 0.05, 0.07, 0.07, 0.08, 0.14]
    assert parse_paper("no table here") == {}


def test_the_clinical_counts_under_5_mm_leave_out_only_the_failures_of_5_mm_or_more_of_each_group():
    c = parse_clinical(CLINICAL)
    assert c["success"] == pytest.approx(0.62) and c["mean_mm"] == 7.54 and c["n"] == 8
    assert c["small_under5"] == "3 of 4"  # 2.13 mm is a failure under 2 mm's rule, still under 5 mm
    assert c["large_under5"] == "3 of 4"
    # no failures listed: every pair under 5 mm
    clean = CLINICAL.split("Failed cases")[0] + "network-regression: 0 of 8 failed\n\nRun\n"
    assert parse_clinical(clean)["small_under5"] == "4 of 4"
    # the report's own count, where it prints one (a held-out CT), wins over the rounded failure list
    own = CLINICAL.replace("Failed cases", "The learned network alone (network-regression), TRE under 5 mm:\n\n"
                           "- up to 40 mm / 30 deg: 4 of 4 = 100% (target >= 95 %): MET\n"
                           "- 40-60 mm / 30-45 deg: 2 of 4 = 50% (target >= 80 %): NOT MET\n\nFailed cases")
    c = parse_clinical(own)
    assert c["small_under5"] == "4 of 4" and c["large_under5"] == "2 of 4"


def test_the_clinical_counts_read_the_network_alone_s_lines_in_a_report_of_several_methods():
    """A report of ``--methods network-regression network``: the next method's failure list follows without a blank
    line, and the default path's targets repeat the same labels below the network's own count; neither is read as
    the network alone's."""
    own = ("The learned network alone (network-regression), TRE under 5 mm:\n\n"
           "- up to 40 mm / 30 deg: 2 of 4 = 50% (target >= 95 %): NOT MET\n"
           "- 40-60 mm / 30-45 deg: 1 of 4 = 25% (target >= 80 %): NOT MET\n\n"
           "Targets of issue 15 (held-out CTs, network = the default path):\n\n"
           "- up to 40 mm / 30 deg: 0 of 4 under 2 mm TRE (target 100 %): NOT MET\n\n")
    both = CLINICAL.replace("Failed cases", own + "Failed cases").replace(
        "\nRun\n", "network: 2 of 8 failed\n  - ct_a small_000: TRE 40.00 mm (identity 26.97)\n"
        "  - ct_a large_000: TRE 60.00 mm (identity 64.78)\n\nRun\n")
    c = parse_clinical(both)
    assert c["small_under5"] == "2 of 4" and c["large_under5"] == "1 of 4"
    listed = both.replace(own, "")  # without the report's own count: the network alone's failures only
    c = parse_clinical(listed)
    assert c["small_under5"] == "3 of 4" and c["large_under5"] == "3 of 4"


def test_the_table_takes_each_fold_s_newest_epoch_and_says_whether_the_shipped_network_saw_the_ct(tmp_path):
    res, runs = tmp_path / "loco", tmp_path / "runs"
    res.mkdir()
    # epochs compared as numbers (e9 sorts after e50 as text), the shipped network's newest day
    for tag, mean, day in (("e9", "0.40", "2026-12-06"), ("e50", "0.25", "2026-12-06"),
                           ("shipped", "0.55", "2026-12-05"), ("shipped", "0.30", "2026-12-06")):
        (res / f"bench_real_ct_loco_ct_a_{tag}_{day}.txt").write_text(PAPER.format(mean=mean))
        (res / f"bench_clinical_geometry_loco_ct_a_{tag}_{day}.txt").write_text(CLINICAL)
    (res / "bench_real_ct_loco_ct_b_e7_2026-12-05.txt").write_text(PAPER.format(mean="0.90"))
    (res / "notes.txt").write_text("ignored")
    (runs / "ct_a").mkdir(parents=True)
    (runs / "ct_a" / "history.json").write_text(json.dumps([{"epoch": 50.0, "train_samples": 20000.0}]))
    rows = collect(res, runs)
    assert [(r.ct, r.tag) for r in rows] == [("ct_a", "e50"), ("ct_a", "shipped"), ("ct_b", "e7")]
    assert rows[0].paper["mean_mm"] == 0.25 and rows[0].samples == 20000 and rows[2].samples is None
    table = format_table(rows, training_cts=("ct_a",)).splitlines()
    assert len(table) == 5 and all(line.count("|") == 11 for line in table)
    assert "fold, epoch 50" in table[2] and "| 20000 |" in table[2] and "0.25 / 0.23" in table[2]
    assert "shipped (trained on it" in table[3] and "0.30 / 0.23" in table[3]
    assert "ct_b | fold, epoch 7" in table[4] and table[4].endswith("| 0.07/0.08/0.14 | - | - | - |")
