"""Evaluation of registration methods on datalists with known motion: the reference paper's Tables 1 and 2."""

from monai_rigidreg.evaluation.report import (
    CaseResult,
    format_report,
    motion_conditions,
    summarize,
    write_report,
)

__all__ = ["CaseResult", "format_report", "motion_conditions", "summarize", "write_report"]

from monai_rigidreg.evaluation.evaluate import METHODS, evaluate_datalist, load_datalist  # noqa: E402
from monai_rigidreg.evaluation.html_report import write_html_report  # noqa: E402

__all__ += ["METHODS", "evaluate_datalist", "load_datalist", "write_html_report"]
