"""``report.html``: the evaluation's tables, every case, and overlays of a capped selection of cases, in one page.

The page is self-contained (inline CSS, no JavaScript, nothing fetched from a network); the overlay PNGs lie in
``report_files/`` next to it and are linked with relative paths, so the folder can be moved or zipped as a whole.
The summary tables are the cells of :func:`~monai_rigidreg.evaluation.report.report_tables`, exactly as in
``report.md``; the per-case rows list the cases that failed (TRE at or above the success threshold) or were flagged
by the confidence check first.

Overlays are drawn while the volumes are in memory (:class:`~monai_rigidreg.evaluation.overlays.OverlayGallery`, fed by
:func:`~monai_rigidreg.evaluation.evaluate.evaluate_datalist` case by case): every failed or flagged case, plus up
to ``max_others`` of the rest, so that a large evaluation writes a bounded number of images.
"""

from __future__ import annotations

import html
from collections.abc import Mapping, Sequence
from datetime import datetime
from pathlib import Path

import numpy as np

from monai_rigidreg import __version__
from monai_rigidreg.evaluation.overlays import needs_attention
from monai_rigidreg.evaluation.report import (
    SUCCESS_TRE_MM,
    CaseResult,
    ReportTable,
    motion_conditions,
    report_tables,
    summarize,
)

__all__ = ["write_html_report"]

_CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; font-size: 14px; color: #1d1d1f;
       margin: 0 auto; padding: 16px 24px 40px; max-width: 1150px; background: #fff; }
h1 { font-size: 22px; margin: 4px 0 8px; }
h2 { font-size: 17px; margin: 28px 0 8px; border-bottom: 1px solid #d0d4da; padding-bottom: 3px; }
header dl { display: grid; grid-template-columns: max-content 1fr; gap: 2px 14px; margin: 0; }
header dt { color: #5a6270; } header dd { margin: 0; word-break: break-all; }
nav { margin: 10px 0 0; } nav a { margin-right: 14px; }
a { color: #0b57b0; }
table { border-collapse: collapse; margin: 6px 0 14px; }
caption { text-align: left; font-weight: 600; padding: 4px 0 6px; }
th, td { border: 1px solid #d0d4da; padding: 3px 8px; text-align: right; white-space: nowrap; }
th { background: #eef1f5; } tbody tr:nth-child(even) { background: #f8f9fb; }
td.text, th.text { text-align: left; }
tr.fail td { background: #fde2e1; } tr.flag td { background: #fff2cc; }
tr.fail.flag td { background: #f9d0c4; }
.badge { display: inline-block; padding: 0 6px; border-radius: 3px; font-size: 12px; font-weight: 600; }
.no { background: #c62828; color: #fff; } .yes { background: #2e7d32; color: #fff; }
.warn { background: #f9a825; color: #000; }
.note { color: #5a6270; margin: 4px 0 8px; }
.legend span { display: inline-block; width: 12px; height: 12px; vertical-align: -1px; margin: 0 4px 0 10px; }
.gallery { display: flex; flex-wrap: wrap; gap: 14px; }
figure { margin: 0; padding: 6px; border: 1px solid #d0d4da; border-radius: 4px; background: #fafbfc; }
figure.attention { border-color: #c62828; border-width: 2px; }
figure img { display: block; background: #000; image-rendering: auto; }
figcaption { font-size: 12px; margin-top: 4px; max-width: 520px; }
footer { margin-top: 30px; color: #5a6270; font-size: 12px; }
"""

_OVERLAY_DISPLAY_ROWS = 170
"""Overlays are shown at least this tall (CSS pixels), scaled up from small display grids."""


def _e(text: object) -> str:
    return html.escape(str(text), quote=True)


_TEXT = ' class="text"'
_TEXT_HEADERS = ("method", "motion condition", "case id", "group", "overlay")
"""Columns whose cells are left-aligned text (the others are numbers, right-aligned)."""


def _cell(text: str, left: bool = False, raw: bool = False) -> str:
    return f"<td{_TEXT if left else ''}>{text if raw else _e(text)}</td>"


def _head(header: Sequence[str]) -> str:
    return "<tr>" + "".join(f"<th{_TEXT if h in _TEXT_HEADERS else ''}>{_e(h)}</th>" for h in header) + "</tr>"


def _badge(text: str, cls: str) -> str:
    return f'<span class="badge {cls}">{_e(text)}</span>'


def _summary_table_html(table: ReportTable) -> str:
    head = _head(table.header)
    body = "\n".join("<tr>" + "".join(_cell(v, left=h in _TEXT_HEADERS) for h, v in zip(table.header, row))
                     + "</tr>" for row in table.rows)
    return (f'<table id="table-{_e(table.key)}" class="summary">\n<caption>{_e(table.title)}</caption>\n'
            f"<thead>{head}</thead>\n<tbody>\n{body}\n</tbody>\n</table>")


def _case_order(cases: Sequence[CaseResult]) -> list[int]:
    """Indices of ``cases``: failed or flagged first (worst TRE first), then the rest in evaluation order."""
    problem = [i for i, c in enumerate(cases) if needs_attention(c)]
    problem.sort(key=lambda i: -cases[i].tre_mm if np.isfinite(cases[i].tre_mm) else -np.inf)
    return problem + [i for i, c in enumerate(cases) if not needs_attention(c)]


def _conditions(case: CaseResult) -> str:
    return "; ".join(c for c in motion_conditions(case.params_true) if c != "All cases") or "–"


def _rel(path: Path, base: Path) -> str:
    try:
        rel = path.resolve().relative_to(base.resolve())
    except ValueError:
        rel = Path(path)
    return rel.as_posix()


def _cases_table_html(cases: Sequence[CaseResult], order: Sequence[int], overlays: Mapping[int, Path],
                      base: Path) -> str:
    header = ["#", "case id", "method", "group", "motion condition", "TRE (mm)", "success", "confidence",
              "flagged", "runtime (s)", "overlay"]
    rows = []
    for i in order:
        c = cases[i]
        flagged = c.extra.get("flagged")
        conf = c.extra.get("confidence")
        classes = " ".join(k for k, on in (("fail", not c.success), ("flag", bool(flagged))) if on)
        link = (f'<a href="{_e(_rel(overlays[i], base))}">view</a> · <a href="#overlay-{i}">below</a>'
                if i in overlays else "–")
        cells = [
            _cell(str(i)),
            _cell(c.case_id, left=True),
            _cell(c.method, left=True),
            _cell(c.group or "–", left=True),
            _cell(_conditions(c), left=True),
            _cell(f"{c.tre_mm:.2f}"),
            _cell(_badge("yes", "yes") if c.success else _badge("no", "no"), raw=True),
            _cell("–" if conf is None else f"{float(conf):.2f}"),
            _cell("–" if flagged is None else _badge("yes", "warn") if flagged else "no", raw=True),
            _cell(f"{c.runtime_s:.2f}"),
            _cell(link, left=True, raw=True),
        ]
        row_class = f' class="{classes}"' if classes else ""
        rows.append(f'<tr id="case-{i}"{row_class}>' + "".join(cells) + "</tr>")
    return (f'<table id="table-cases">\n<thead>{_head(header)}</thead>\n<tbody>\n' + "\n".join(rows)
            + "\n</tbody>\n</table>")


def _png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's header, or ``None`` if it is not a readable PNG."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def _gallery_html(cases: Sequence[CaseResult], order: Sequence[int], overlays: Mapping[int, Path],
                  base: Path) -> str:
    figures = []
    for i in order:
        if i not in overlays:
            continue
        c = cases[i]
        src = _e(_rel(overlays[i], base))
        size = _png_size(overlays[i])
        dims = ""
        if size is not None:
            scale = max(1.0, _OVERLAY_DISPLAY_ROWS / max(size[1], 1))
            dims = f' width="{round(size[0] * scale)}" height="{round(size[1] * scale)}"'
        state = []
        if not c.success:
            state.append("failed")
        if c.extra.get("flagged"):
            state.append("flagged")
        caption = (f"<b>{_e(c.case_id)}</b> · {_e(c.method)} · TRE {c.tre_mm:.2f} mm"
                   + (f" · <b>{_e(', '.join(state))}</b>" if state else "")
                   + f' · <a href="#case-{i}">row</a>')
        frame = ' class="attention"' if state else ""
        alt = _e(f"overlay of {c.case_id}, {c.method}")
        figures.append(f'<figure id="overlay-{i}"{frame}>'
                       f'<a href="{src}"><img src="{src}" alt="{alt}"{dims}>'
                       f"</a><figcaption>{caption}</figcaption></figure>")
    return '<div class="gallery">\n' + "\n".join(figures) + "\n</div>" if figures else ""


def write_html_report(
    cases: Sequence[CaseResult],
    path: str | Path,
    summary: dict | None = None,
    overlays: Mapping[int, str | Path] | None = None,
    datalist: str | Path | None = None,
    omitted_overlays: int = 0,
    title: str = "Rigid CBCT-to-CT registration: evaluation",
) -> Path:
    """Write ``report.html``.

    Args:
        cases: the per-case results, as evaluated (all methods).
        path: the HTML file (its folder must exist).
        summary: :func:`~monai_rigidreg.evaluation.report.summarize` of ``cases`` (computed if ``None``).
        overlays: result index -> overlay PNG (:attr:`OverlayGallery.images`), linked relative to ``path``.
        datalist: the evaluated datalist (shown in the header).
        omitted_overlays: how many results were left without an overlay by the cap (shown under the gallery).
        title: page title.

    Returns:
        ``path``.
    """
    p = Path(path)
    base = p.parent
    summary = summarize(cases) if summary is None else summary
    overlays = {int(k): Path(v) for k, v in (overlays or {}).items()}
    order = _case_order(cases)
    n_problem = sum(needs_attention(c) for c in cases)
    methods = list(dict.fromkeys(c.method for c in cases))
    n_cases = len(dict.fromkeys(c.case_id for c in cases))
    date = datetime.now().astimezone().strftime("%Y-%m-%d %H:%M:%S %Z")
    meta = [("datalist", "–" if datalist is None else str(Path(datalist).resolve())), ("date", date),
            ("monai-rigidreg", __version__), ("methods", ", ".join(methods) or "–"),
            ("cases", f"{n_cases} ({len(cases)} results; {n_problem} failed or flagged)")]
    tables = "\n".join(_summary_table_html(t) for t in report_tables(summary))
    gallery = _gallery_html(cases, order, overlays, base)
    cap_note = (f" {omitted_overlays} further result(s) without an overlay (the cap on cases that neither failed "
                "nor were flagged)." if omitted_overlays else "")
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        "<head>",
        '<meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{_e(title)}</title>",
        f"<style>{_CSS}</style>",
        "</head>",
        "<body>",
        "<header>",
        f"<h1>{_e(title)}</h1>",
        "<dl>" + "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in meta) + "</dl>",
        '<nav><a href="#summary">Summary tables</a><a href="#cases">Per-case results</a>'
        '<a href="#overlays">Overlays</a></nav>',
        "</header>",
        '<section id="summary">',
        "<h2>Summary</h2>",
        f'<p class="note">Success: mean target registration error (TRE) over the CT body below '
        f"{SUCCESS_TRE_MM:g} mm. The same numbers as report.md and summary.json.</p>",
        tables,
        "</section>",
        '<section id="cases">',
        "<h2>Per-case results</h2>",
        f'<p class="note">{n_problem} of {len(cases)} results failed or were flagged by the confidence check; they '
        "come first (worst TRE first, red: failed, amber: flagged), then the rest in evaluation order. "
        "Full parameters: cases.csv.</p>",
        _cases_table_html(cases, order, overlays, base),
        "</section>",
        '<section id="overlays">',
        "<h2>Overlays</h2>",
        '<p class="note legend">Axial, coronal and sagittal views through the CBCT centre as registered:'
        '<span style="background:#f00"></span>CT<span style="background:#0f0"></span>CBCT resampled with the '
        'estimate<span style="background:#ff0"></span>both. Failed or flagged cases are framed in red.'
        f"{_e(cap_note)}</p>",
        gallery or '<p class="note">No overlays were drawn.</p>',
        "</section>",
        f"<footer>Written by monai-rigidreg {_e(__version__)} on {_e(date)}.</footer>",
        "</body>",
        "</html>",
    ]
    p.write_text("\n".join(parts) + "\n", encoding="utf-8")
    return p
