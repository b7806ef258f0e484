"""Write one self-contained HTML file (plots embedded, no external links) to read, print and
file: the verdict and its findings, the calibration with its uncertainty, per-station and
cross-validated errors, residuals over the image, corner coverage, model selection and every
rejected station with the reason.
"""

# ``cellcal report``: the self-contained HTML report of a result file (``service.results.report``).

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from service.cli.files import read_json
from service.results.identity import ReportIdentity

if TYPE_CHECKING:
    from service.stationsets.format import StationSet


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``report`` command's arguments."""
    parser.add_argument("result", type=Path, metavar="RESULT_JSON",
                        help="a result written by 'cellcal calibrate --out'")
    parser.add_argument("--out", type=Path, metavar="HTML",
                        help="output file (default: RESULT_JSON with .html)")
    parser.add_argument("--stations", type=Path, metavar="DIR",
                        help="the station set the result was calibrated from: adds a "
                             "thumbnail of every station with its detected and reprojected "
                             "corners")
    parser.add_argument("--pdf", action="store_true",
                        help="also print the report to a PDF (A4) beside the HTML, through "
                             "headless chromium")


def run(args: argparse.Namespace) -> int:
    """Write the report of ``args.result``."""
    from service.results.report import render_report

    try:
        doc = read_json(args.result)
    except OSError as exc:
        raise ValueError(f"{args.result}: cannot read ({exc.strerror or exc})") from None
    match doc:
        case {"format": "cellcal/result@1"}:
            pass
        case _:
            raise ValueError(f"{args.result}: not a cellcal result (format cellcal/result@1)")
    out = args.out or args.result.with_suffix(".html")
    if args.pdf and not chromium():
        print("cellcal: error: --pdf needs chromium (Debian/Ubuntu: apt install chromium); "
              "the HTML report prints on A4 from any browser", file=sys.stderr)
        return 1
    images = identity = None
    if args.stations:
        from service.stationsets.format import load_station_set

        stations = load_station_set(args.stations)
        images = station_images(args.stations, stations)
        identity = station_set_identity(args.stations, stations, images)
    out.write_text(render_report(doc, images, identity))
    print(f"wrote {out}", file=sys.stderr)
    if args.pdf:
        pdf = out.with_suffix(".pdf")
        print_pdf(out, pdf)
        print(f"wrote {pdf}", file=sys.stderr)
    return 0


def station_images(directory: Path, stations: StationSet) -> dict[str, Path]:
    """Station id -> image file of the station set ``stations`` in ``directory``."""
    return {s.id: directory / s.image for s in stations.stations if s.image is not None}


def station_set_identity(directory: Path, stations: StationSet,
                         images: dict[str, Path]) -> ReportIdentity:
    """The board, the station count and the input checksum of the station set in
    ``directory`` (see :func:`station_set_sha256`), whose ``images`` are in the order
    stations.json names them."""
    from calib import TargetAdapter
    from service.stationsets.format import station_set_sha256

    index = directory / "stations.json"
    board = None if stations.target is None else TargetAdapter.dump_python(stations.target,
                                                                           mode="json")
    return ReportIdentity(board=json.dumps(board, sort_keys=True),
                          stations=f"{len(stations.stations)} in {directory.resolve()}",
                          input_sha256=station_set_sha256(index.read_bytes(), images.values()))


def chromium() -> str | None:
    """The chromium executable on PATH, if any."""
    return next(filter(None, map(shutil.which, ("chromium", "chromium-browser",
                                                "google-chrome"))), None)


def print_pdf(html: Path, pdf: Path) -> None:
    """Print ``html`` to ``pdf`` with chromium's headless print (A4 from the report's
    ``@page``); ValueError (one line) when chromium fails."""
    exe = chromium()
    assert exe is not None
    with tempfile.TemporaryDirectory(prefix="cellcal-pdf-") as profile:
        done = subprocess.run(
            [exe, "--headless", "--no-sandbox", "--disable-gpu", "--no-pdf-header-footer",
             f"--user-data-dir={profile}", f"--print-to-pdf={pdf.resolve()}",
             html.resolve().as_uri()],
            capture_output=True, text=True, timeout=300, check=False)
    if done.returncode != 0 or not pdf.exists() or pdf.stat().st_size == 0:
        last = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise ValueError(f"chromium could not print {html} to PDF: {last}")
