"""``monai-rigidreg evaluate``: evaluate methods on a datalist with known motion (per-axis errors, TRE, success, time).

Register every case of a datalist (as written by 'simulate') with each method and write cases.csv, summary.json and
report.md (the reference paper's Tables 1 and 2) to --output-dir, and report.html: the same tables, every case
(failed and flagged first) and overlays in report_files/.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from monai_rigidreg.core.command_text import add_command

__all__ = ["add_parser", "run"]

# copies of evaluation.evaluate.METHODS and evaluation.overlays.DEFAULT_MAX_OVERLAYS (tests/evaluation check that
# they agree): those modules import torch, and `monai-rigidreg --help` builds this parser
METHODS = ("network", "network-thorough", "network-regression", "network+refine", "sitk", "elastix", "ants",
           "greedy")
DEFAULT_MAX_OVERLAYS = 20


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``evaluate`` sub-command to ``subparsers`` (``monai-rigidreg``'s); it sets ``func=run``."""
    p = add_command(subparsers, "evaluate", __doc__, run)
    p.add_argument("--datalist", required=True, type=Path, help="MONAI datalist JSON with ground truth")
    p.add_argument("--method", nargs="+", default=["network"], choices=METHODS, help="method(s) to run")
    p.add_argument("--output-dir", required=True, type=Path, metavar="DIR",
                   help="where cases.csv, summary.json and the reports go (refused where it is not empty; --overwrite "
                   "replaces an earlier report only)")
    p.add_argument("--bundle", type=Path, default=None, help="bundle directory (default: the shipped one)")
    p.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    p.add_argument("--max-cases", type=int, default=None, metavar="N", help="only the datalist's first N cases")
    p.add_argument("--key", default=None, help="datalist key (default: test, validation or training)")
    p.add_argument("--no-html", dest="html", action="store_false",
                   help="do not write report.html and its overlays (report_files/)")
    p.add_argument("--max-overlays", type=int, default=DEFAULT_MAX_OVERLAYS, metavar="N",
                   help="overlays in report.html for cases that neither failed nor were flagged (those always get "
                   "one; default: %(default)s)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing report in --output-dir")
    return p


def run(args: argparse.Namespace) -> int:
    from monai_rigidreg.evaluation.evaluate import evaluate_datalist

    # the output folder is checked first (evaluate_datalist: a non-empty folder needs --overwrite, which replaces
    # an earlier report only), and written aside and moved into place at the end
    out = evaluate_datalist(args.datalist, args.method, args.output_dir, bundle=args.bundle, device=args.device,
                            max_cases=args.max_cases, key=args.key, html=args.html, max_overlays=args.max_overlays,
                            overwrite=args.overwrite)
    print(out["report"])
    print(f"per-case results: {out['paths']['csv']}")
    if "html" in out["paths"]:
        print(f"browsable report: {out['paths']['html']}")
    return 0
