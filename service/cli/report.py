"""Write one self-contained HTML file (plots embedded, no external links) to read, print and
file: the verdict and its findings, the calibration with its uncertainty, per-station and
cross-validated errors, residuals over the image, corner coverage, model selection and every
rejected station with the reason.
"""

# ``cellcal report``: the self-contained HTML report of a result file (``service.results.report``).

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``report`` command's arguments."""
    parser.add_argument("result", type=Path, metavar="RESULT_JSON",
                        help="a result written by 'cellcal calibrate --out'")
    parser.add_argument("--out", type=Path, metavar="HTML",
                        help="output file (default: RESULT_JSON with .html)")


def run(args: argparse.Namespace) -> int:
    """Write the report of ``args.result``."""
    from service.results.report import render_report

    try:
        doc = json.loads(args.result.read_text())
    except OSError as exc:
        raise ValueError(f"{args.result}: cannot read ({exc.strerror or exc})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{args.result}: not valid JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != "cellcal/result@1":
        raise ValueError(f"{args.result}: not a cellcal result (format cellcal/result@1)")
    out = args.out or args.result.with_suffix(".html")
    out.write_text(render_report(doc))
    print(f"wrote {out}", file=sys.stderr)
    return 0
