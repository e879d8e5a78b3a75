"""The leave-one-CT-out table: each fold's network alone on the real CT it never saw, from the result files.

``scripts/eval_loco.sh HOLD_OUT`` writes, per fold and evaluated checkpoint,
``bench_real_ct_loco_<CT>_e<epoch>_<day>.txt`` (the paper protocol, 12 cases) and
``bench_clinical_geometry_loco_<CT>_e<epoch>_<day>.txt`` (4 + 4 clinical-geometry pairs) into
``benchmarks/results/loco``; with ``SHIPPED=1`` also ``..._shipped_<day>.txt``, the shipped network on the same
cases. This script reads the newest epoch of each fold (the newest day where one epoch was measured twice) and prints
one markdown row per fold, and one per shipped-network measurement beside it, saying whether that network trained on
the CT. Samples: the fold's ``history.json`` (``training/loco/<CT>``) where present.

Columns: paper protocol, the learned network alone: mean / median TRE (mm), share under 2 mm, mean absolute error per
axis (mm, degrees); clinical geometry: share under 2 mm and, under 5 mm, ``k of n`` for motions up to 40 mm / 30 deg
and for 40-60 mm / 30-45 deg.

Usage::

    python -m benchmarks.accuracy.loco_table [--results-dir benchmarks/results/loco] [--runs-dir training/loco]
"""

from __future__ import annotations

import itertools
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

from benchmarks.bench_common import script_parser

__all__ = ["FoldResult", "collect", "format_table", "parse_clinical", "parse_paper"]

_NAME = re.compile(r"^bench_(real_ct|clinical_geometry)_loco_(?P<ct>.+)_(?P<tag>e\d+|shipped)_(?P<day>\d{4}-\d\d-\d\d)"
                   r"\.txt$")
_FAILED = re.compile(r"^\s+- \S+ (small|large)_\d+: TRE ([\d.]+) mm", re.M)
_UNDER5 = re.compile(r"^- (up to 40 mm / 30 deg|40-60 mm / 30-45 deg): (\d+) of (\d+)", re.M)
_UNDER5_HEAD = "The learned network alone (network-regression), TRE under 5 mm:"


@dataclass
class FoldResult:
    """One network on one held-out CT: ``tag`` ``e<epoch>`` (the fold's checkpoint) or ``shipped``."""

    ct: str
    tag: str
    day: str
    paper: dict[str, float] = field(default_factory=dict)
    clinical: dict[str, float | str] = field(default_factory=dict)
    samples: int | None = None


def _row_cells(text: str, first: str, second: str | None = None) -> list[str] | None:
    """The cells of the first markdown table row whose first cell is ``first`` (and second ``second``)."""
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells and cells[0] == first and (second is None or (len(cells) > 1 and cells[1] == second)):
            return cells
    return None


def parse_paper(text: str) -> dict[str, float]:
    """``bench_real_ct``'s row of ``network-regression``: ``n``, ``mean_mm``, ``median_mm``, ``success`` and
    ``under12`` (shares under 2 and 12 mm, 0-1) and the per-axis mean absolute errors ``tx ty tz`` (mm) ``rx ry rz``
    (degrees). Empty when absent."""
    cells = _row_cells(text, "network-regression")
    if cells is None:
        return {}
    keys = ["n", "mean_mm", "median_mm", "success", "under12", "tx", "ty", "tz", "rx", "ry", "rz"]
    values = [float(c.rstrip("%")) / (100.0 if c.endswith("%") else 1.0) for c in cells[1:12]]
    return dict(zip(keys, values))


def parse_clinical(text: str) -> dict[str, float | str]:
    """``bench_clinical_geometry``'s ``small+large`` row of ``network-regression`` (``n``, ``mean_mm``, ``median_mm``,
    ``success``: share under 2 mm) and, per group, how many pairs ended under 5 mm (``small_under5``,
    ``large_under5``: ``"k of n"``): the report's own count where it prints one (for CTs held out of the network's
    training), otherwise the group's pairs less its listed failures of 5 mm or more (their TRE as printed, to 0.01
    mm). Empty when absent."""
    out: dict[str, float | str] = {}
    cells = _row_cells(text, "small+large", "network-regression")
    if cells is not None:
        out.update(n=float(cells[2]), mean_mm=float(cells[3]), median_mm=float(cells[4]),
                   success=float(cells[5].rstrip("%")) / 100.0)
    failed = text.split("\nnetwork-regression: ", 1)
    misses = []
    if len(failed) == 2:  # its list: the indented lines under its header, up to the next method's header
        listed = failed[1].split("\n")[1:]
        section = "\n".join(line for line in itertools.takewhile(lambda x: x.startswith("  "), listed))
        misses = _FAILED.findall(section)
    for group in ("small", "large"):
        row = _row_cells(text, group, "network-regression")
        if row is not None:
            n = int(row[2])
            over5 = sum(1 for g, tre in misses if g == group and float(tre) >= 5.0)
            out[f"{group}_under5"] = f"{n - over5} of {n}"
    own = text.split(_UNDER5_HEAD, 1)
    if len(own) == 2:
        for label, k, n in _UNDER5.findall(own[1].lstrip("\n").split("\n\n", 1)[0]):  # its own lines only
            out["small_under5" if label.startswith("up to") else "large_under5"] = f"{k} of {n}"
    return out


def _epoch(tag: str) -> int:
    return int(tag[1:]) if tag.startswith("e") else -1


def collect(results_dir: Path, runs_dir: Path | None = None) -> list[FoldResult]:
    """Per held-out CT: its fold's newest measured epoch, then the shipped network's newest measurement (if any)."""
    found: dict[tuple[str, str, str], FoldResult] = {}
    for path in sorted(results_dir.glob("bench_*_loco_*.txt")):
        m = _NAME.match(path.name)
        if m is None:
            continue
        key = (m["ct"], m["tag"], m["day"])
        res = found.setdefault(key, FoldResult(m["ct"], m["tag"], m["day"]))
        text = path.read_text()
        if m.group(1) == "real_ct":
            res.paper = parse_paper(text)
        else:
            res.clinical = parse_clinical(text)
    rows: list[FoldResult] = []
    for ct in sorted({k[0] for k in found}):
        mine = [r for k, r in found.items() if k[0] == ct]
        folds = sorted((r for r in mine if r.tag != "shipped"), key=lambda r: (_epoch(r.tag), r.day))
        shipped = sorted((r for r in mine if r.tag == "shipped"), key=lambda r: r.day)
        if folds:
            fold = folds[-1]
            fold.samples = _samples(runs_dir, ct, _epoch(fold.tag))
            rows.append(fold)
        if shipped:
            rows.append(shipped[-1])
    return rows


def _samples(runs_dir: Path | None, ct: str, epoch: int) -> int | None:
    """Samples seen at ``epoch`` by the fold's run (its ``history.json``), or ``None``."""
    path = None if runs_dir is None else runs_dir / ct / "history.json"
    if path is None or not path.is_file():
        return None
    for entry in json.loads(path.read_text()):
        if int(entry.get("epoch", -1)) == epoch and "train_samples" in entry:
            return int(entry["train_samples"])
    return None


def _fmt(value: float | str | None, spec: str = ".2f") -> str:
    if value is None or value == "":
        return "-"
    return value if isinstance(value, str) else format(value, spec)


def format_table(rows: list[FoldResult], training_cts: tuple[str, ...] = ()) -> str:
    """Markdown: one row per fold (the network trained without the CT) and per shipped measurement (``training_cts``:
    the CTs the shipped network trained on, so that its row says whether it saw this one)."""
    head = ("| held-out CT | network | samples | paper TRE mean / median (mm) | paper < 2 mm | "
            "paper error tx/ty/tz (mm) | paper error rx/ry/rz (deg) | clinical < 2 mm | "
            "clinical < 5 mm, <= 40 mm / 30 deg | "
            "clinical < 5 mm, 40-60 mm / 30-45 deg |")
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        if r.tag == "shipped":
            who = f"shipped ({'trained on it' if r.ct in training_cts else 'held out'}; {r.day})"
        else:
            who = f"fold, epoch {_epoch(r.tag)} ({r.day})"
        p, c = r.paper, r.clinical
        paper_t = "/".join(_fmt(p.get(k)) for k in ("tx", "ty", "tz")) if p else "-"
        paper_r = "/".join(_fmt(p.get(k)) for k in ("rx", "ry", "rz")) if p else "-"
        lines.append(
            f"| {r.ct} | {who} | {_fmt(r.samples, 'd')} | "
            f"{_fmt(p.get('mean_mm'))} / {_fmt(p.get('median_mm'))} | {_fmt(p.get('success'), '.0%')} | "
            f"{paper_t} | {paper_r} | {_fmt(c.get('success'), '.0%')} | {_fmt(c.get('small_under5'))} | "
            f"{_fmt(c.get('large_under5'))} |")
    return "\n".join(lines)


def main() -> None:
    ap = script_parser(__doc__)
    ap.add_argument("--results-dir", type=Path, default=Path("benchmarks/results/loco"))
    ap.add_argument("--runs-dir", type=Path, default=Path("training/loco"))
    args = ap.parse_args()
    if not args.results_dir.is_dir():
        raise SystemExit(f"loco_table: no folder {args.results_dir} (run scripts/eval_loco.sh HOLD_OUT first)")
    from monai_rigidreg.io.shared_data import TRAINING_CTS

    rows = collect(args.results_dir, args.runs_dir)
    if not rows:
        raise SystemExit(f"loco_table: no leave-one-CT-out results in {args.results_dir}")
    print(format_table(rows, tuple(TRAINING_CTS)))


if __name__ == "__main__":
    main()
