"""Evaluation of registration methods on datalists with known motion: the reference paper's Tables 1 and 2.

The names below are exported here on first use (PEP 562): importing the ``evaluate`` command's module imports no
torch (``monai-rigidreg --help`` builds its parser).
"""

from monai_rigidreg.core.lazy_exports import lazy_exports

_MODULES = {
    "report": ("CaseResult", "format_report", "motion_conditions", "summarize", "write_report"),
    "evaluate": ("METHODS", "evaluate_datalist", "load_datalist"),
    "html_report": ("write_html_report",),
}
_NAMES = {name: f"monai_rigidreg.evaluation.{module}" for module, names in _MODULES.items() for name in names}
__all__ = list(_NAMES)
__getattr__, __dir__ = lazy_exports(__name__, _NAMES)
