"""Per-case results and the summary tables (per-axis mean absolute error +- SD, TRE, success rate, time)."""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from monai_rigidreg.core.geometry import PARAM_NAMES, parameter_errors
from monai_rigidreg.core.json_safe import json_safe

__all__ = ["CaseResult", "ReportTable", "motion_conditions", "summarize", "report_tables", "format_report",
           "write_report", "SUCCESS_TRE_MM"]

SUCCESS_TRE_MM = 2.0
"""A registration succeeds when its mean target registration error is below this (mm)."""

CONDITION_TRANSLATION = "Translation 1.5 cm"
CONDITION_ROTATION_X = "Rotation theta_x = 30 deg"
CONDITION_ALL = "All cases"


@dataclass
class CaseResult:
    """One registered case.

    Attributes:
        case_id: identifier from the datalist.
        method: registration method name (``network``, ``network+refine``, ``sitk``, ``elastix``).
        params_true, params_pred: ``(tx, ty, tz, rx, ry, rz)`` mm / degrees, about the same centre.
        tre_mm: mean target registration error over body points (mm).
        runtime_s: registration time in seconds (volumes already loaded).
        group: the datalist's motion group label, if any.
    """

    case_id: str
    method: str
    params_true: list[float]
    params_pred: list[float]
    tre_mm: float
    runtime_s: float
    group: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def abs_errors(self) -> np.ndarray:
        return parameter_errors(self.params_pred, self.params_true)

    @property
    def success(self) -> bool:
        return bool(np.isfinite(self.tre_mm) and self.tre_mm < SUCCESS_TRE_MM)


def motion_conditions(params_true: Sequence[float], atol: float = 1e-3) -> list[str]:
    """The paper's motion conditions a ground truth belongs to (always includes ``"All cases"``).

    ``"Translation 1.5 cm"``: no rotation and a 15 mm translation on at least one axis.
    ``"Rotation theta_x = 30 deg"``: ``|rx| = 30`` degrees with no other rotation or translation.
    """
    p = np.asarray(params_true, dtype=np.float64)
    out = []
    if np.all(np.abs(p[3:]) < atol) and np.isclose(np.max(np.abs(p[:3])), 15.0, atol=atol):
        out.append(CONDITION_TRANSLATION)
    if np.isclose(abs(p[3]), 30.0, atol=atol) and np.all(np.abs(p[[0, 1, 2, 4, 5]]) < atol):
        out.append(CONDITION_ROTATION_X)
    out.append(CONDITION_ALL)
    return out


def _mean_sd(values: np.ndarray) -> tuple[float, float]:
    if len(values) == 0:
        return float("nan"), float("nan")
    return float(np.mean(values, axis=0)), float(np.std(values, axis=0, ddof=1)) if len(values) > 1 else 0.0


def summarize(cases: Sequence[CaseResult]) -> dict:
    """Summary per method and per motion condition.

    Returns:
        ``{method: {"conditions": {condition: {"n": int, "mae": {tx: (mean, sd), ...}}}, "tre_mean_mm",
        "tre_median_mm", "success_rate", "n", "time_median_s", "time_mean_s"}}``.
    """
    out: dict = {}
    for method in dict.fromkeys(c.method for c in cases):
        mc = [c for c in cases if c.method == method]
        conds: dict = {}
        for cond in (CONDITION_TRANSLATION, CONDITION_ROTATION_X, CONDITION_ALL):
            sel = [c for c in mc if cond in motion_conditions(c.params_true)]
            if not sel:
                continue
            errs = np.stack([c.abs_errors for c in sel])
            conds[cond] = {
                "n": len(sel),
                "mae": {name: _mean_sd(errs[:, i]) for i, name in enumerate(PARAM_NAMES)},
            }
        tre = np.array([c.tre_mm for c in mc], dtype=np.float64)
        times = np.array([c.runtime_s for c in mc], dtype=np.float64)
        out[method] = {
            "n": len(mc),
            "conditions": conds,
            "tre_mean_mm": float(np.nanmean(tre)) if len(tre) else float("nan"),
            "tre_median_mm": float(np.nanmedian(tre)) if len(tre) else float("nan"),
            "success_rate": float(np.mean([c.success for c in mc])) if mc else float("nan"),
            "time_median_s": float(np.median(times)) if len(times) else float("nan"),
            "time_mean_s": float(np.mean(times)) if len(times) else float("nan"),
        }
        flagged = [c for c in mc if "flagged" in c.extra]
        if flagged:  # methods with a confidence check: how well the flag separates failures from successes
            fails = [c for c in flagged if not c.success]
            oks = [c for c in flagged if c.success]
            out[method]["flag"] = {
                "failures": len(fails),
                "failures_flagged": sum(bool(c.extra["flagged"]) for c in fails),
                "successes": len(oks),
                "successes_flagged": sum(bool(c.extra["flagged"]) for c in oks),
            }
    return out


def _fmt(ms: tuple[float, float]) -> str:
    return f"{ms[0]:.2f} ± {ms[1]:.2f}"


@dataclass
class ReportTable:
    """One table of the report, its cells already formatted (shared by ``report.md`` and ``report.html``).

    Attributes:
        key: short identifier (``translations``, ``rotations``, ``overall``, ``flag``).
        title: the caption line; header: column names; rows: one list of cell texts per row.
    """

    key: str
    title: str
    header: list[str]
    rows: list[list[str]]


def report_tables(summary: dict) -> list[ReportTable]:
    """Table 1 (translations, mm), Table 2 (rotations, degrees), the overall figures and, where a method has a
    confidence check, the failure flag, from :func:`summarize`'s output."""
    t1 = ReportTable("translations", "Table 1. Mean absolute translational errors (mean ± SD, mm)",
                     ["method", "motion condition", "n", "Δtx", "Δty", "Δtz"], [])
    t2 = ReportTable("rotations", "Table 2. Mean absolute rotational errors (mean ± SD, degrees)",
                     ["method", "motion condition", "n", "Δθx", "Δθy", "Δθz"], [])
    for method, s in summary.items():
        for cond, c in s["conditions"].items():
            if cond != CONDITION_ROTATION_X:
                t1.rows.append([method, cond, str(c["n"]), *(_fmt(c["mae"][k]) for k in PARAM_NAMES[:3])])
            if cond != CONDITION_TRANSLATION:
                t2.rows.append([method, cond, str(c["n"]), *(_fmt(c["mae"][k]) for k in PARAM_NAMES[3:])])
    overall = ReportTable("overall", f"Overall (success: mean TRE < {SUCCESS_TRE_MM:g} mm)",
                          ["method", "n", "mean TRE (mm)", "median TRE (mm)", "success rate", "median time (s)"],
                          [[method, str(s["n"]), f"{s['tre_mean_mm']:.2f}", f"{s['tre_median_mm']:.2f}",
                            f"{100 * s['success_rate']:.0f}%", f"{s['time_median_s']:.2f}"]
                           for method, s in summary.items()])
    tables = [t1, t2, overall]
    flags = {m: s["flag"] for m, s in summary.items() if "flag" in s}
    if flags:
        tables.append(ReportTable(
            "flag", "Failure flag (confidence < 0.5): failures caught and false alarms",
            ["method", "failures", "flagged failures", "successes", "flagged successes"],
            [[method, str(f["failures"]), str(f["failures_flagged"]), str(f["successes"]),
              str(f["successes_flagged"])] for method, f in flags.items()]))
    return tables


def format_report(summary: dict) -> str:
    """Markdown text of :func:`report_tables`: Table 1 (translations, mm), Table 2 (rotations, degrees), the
    overall figures and the failure flag."""
    blocks = []
    for t in report_tables(summary):
        lines = [t.title, "", "| " + " | ".join(t.header) + " |", "|" + "---|" * len(t.header)]
        lines += ["| " + " | ".join(row) + " |" for row in t.rows]
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks) + "\n"


def write_report(cases: Sequence[CaseResult], output_dir: str | Path) -> dict[str, Path]:
    """Write ``cases.csv`` (one row per case and method), ``summary.json`` and ``report.md``; returns the paths."""
    d = Path(output_dir)
    d.mkdir(parents=True, exist_ok=True)
    summary = summarize(cases)
    paths = {"csv": d / "cases.csv", "json": d / "summary.json", "report": d / "report.md"}
    with open(paths["csv"], "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["case_id", "method", "group", *[f"true_{n}" for n in PARAM_NAMES],
                    *[f"pred_{n}" for n in PARAM_NAMES], *[f"abs_err_{n}" for n in PARAM_NAMES],
                    "tre_mm", "success", "runtime_s", "confidence", "flagged"])
        for c in cases:
            conf = c.extra.get("confidence")
            w.writerow([c.case_id, c.method, c.group, *[f"{v:.4f}" for v in c.params_true],
                        *[f"{v:.4f}" for v in c.params_pred], *[f"{v:.4f}" for v in c.abs_errors],
                        f"{c.tre_mm:.4f}", int(c.success), f"{c.runtime_s:.4f}",
                        "" if conf is None else f"{float(conf):.4f}",
                        "" if "flagged" not in c.extra else int(bool(c.extra["flagged"]))])
    paths["json"].write_text(json.dumps(json_safe({"summary": summary, "cases": [asdict(c) for c in cases]}),
                                        indent=1, allow_nan=False), encoding="utf-8")
    paths["report"].write_text(format_report(summary), encoding="utf-8")
    return paths
