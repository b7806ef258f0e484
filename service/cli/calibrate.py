"""Calibrate a station set.

With images: corners are detected, then intrinsics with the board aspect ratio nu, hand-eye by
screw motions (SM), the board scale kappa, and by default ('joint') a maximum-likelihood estimate
over all corners and robot poses with standard deviations; images that cannot be used are listed
with the reason. Pose-only sets (stations with target_pose): by default ('refine') SM, then a
weighted least-squares refinement over all stations, kept only when it predicts held-out
stations no worse than SM. Every result carries a cross-validation (held-out stations predicted
from their robot poses), the model selection and a verdict (pass/warn/fail with findings),
printed as one line on stderr. Exit status: 0 pass or warn, 3 fail (the result is still
written), 2 refused input.
"""

# ``cellcal calibrate STATION_DIR``: a station set directory -> result JSON document.

from __future__ import annotations

import argparse
import json
import os
import sys
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from calib import (
    KAPPA_MODES,
    METHODS,
    ChecksConfiguration,
    Detection,
    SolverOptions,
    Station,
    Stations,
    board_from_target,
)
from service.cli.exit_codes import EXIT_VERDICT_FAIL
from service.stationsets.format import DEFAULT_MAX_STATIONS, load_station_set
from service.stationsets.images import DEFAULT_MAX_PIXELS, STDERR_LOCK, read_station_image

if TYPE_CHECKING:  # the result's models load with the solver, not before the images are read
    from calib import CrossValidationBlock, QualityBlock


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``calibrate`` command's arguments."""
    parser.add_argument("station_dir", help="directory holding stations.json")
    parser.add_argument("--out", help="result JSON path (default: stdout)")
    parser.add_argument("--method", choices=METHODS,
                        help="solver (default: joint with images, refine for pose-only sets)")
    parser.add_argument("--estimate-kappa", action="store_true",
                        help="the same as --kappa estimate (pose-only sets hold kappa at 1 "
                             "unless told so; estimated by refine only)")
    parser.add_argument("--kappa", default="auto", choices=KAPPA_MODES,
                        help="board scale kappa (true / entered square size): auto (default) "
                             "estimates it only when that predicts held-out stations clearly "
                             "better; estimate: always; fixed: held at exactly 1 (you measured "
                             "the board and entered its true square size); pose-only sets: auto "
                             "holds it at 1")
    parser.add_argument("--nu-method", default="images", choices=("images", "extrinsics"),
                        help="images: board aspect ratio nu from the corner residuals (Method #1, "
                             "default); extrinsics: from the hand-eye residuals (Method #2)")
    parser.add_argument("--max-stations", type=int, default=DEFAULT_MAX_STATIONS, metavar="N",
                        help=f"refuse sets of more stations (default {DEFAULT_MAX_STATIONS})")
    parser.add_argument("--max-image-pixels", type=int, default=DEFAULT_MAX_PIXELS, metavar="N",
                        help="reject images larger than this, width x height, read from the file "
                             f"header before decoding (default {DEFAULT_MAX_PIXELS})")


#: Show a detection progress bar from this many images on.
PROGRESS_MIN_IMAGES = 10


def run(args: argparse.Namespace) -> int:
    """Calibrate ``args.station_dir`` and write the result document."""
    if args.out not in (None, "-"):
        check_out_path(args.out)
    if args.estimate_kappa and args.kappa == "fixed":
        raise ValueError("--estimate-kappa and --kappa fixed contradict each other")
    stations = load_station_set(args.station_dir, max_stations=args.max_stations).model()
    options = SolverOptions(method=args.method, nu_method=args.nu_method,
                            kappa="estimate" if args.estimate_kappa else args.kappa)
    pool = ThreadPoolExecutor(min(4, os.cpu_count() or 1))
    try:
        ahead = _detect_ahead(pool, args, stations)
        from calib import calibrate  # the solver's imports (scipy, ~0.5 s) while images are read

        result = calibrate(_detected(args, stations, ahead), options)
    finally:
        pool.shutdown(cancel_futures=True)
    from service.results.document import result_of  # the writer's imports: after the solve

    written = result_of(result, command=" ".join(["cellcal", *sys.argv[1:]]))
    text = json.dumps(written.document(), indent=2)
    for rejected in written.rejected or []:
        print(f"cellcal: station {rejected.id} rejected: {rejected.reason}", file=sys.stderr)
    print(verdict_line(written.quality, written.cross_validation), file=sys.stderr)
    if args.out in (None, "-"):
        print(text)
    else:
        Path(args.out).write_text(text + "\n")
        print(f"wrote {args.out}", file=sys.stderr)
    failed = written.quality is not None and written.quality.verdict == "fail"
    return EXIT_VERDICT_FAIL if failed else 0


def check_out_path(out: str) -> None:
    """``ValueError`` if the result could not be written to ``out`` (told before the solve,
    not after it): its directory must exist and be writable, and ``out`` not be a directory."""
    path = Path(out)
    directory = path.parent
    if path.is_dir():
        raise ValueError(f"--out {out}: is a directory; name the result file, e.g. "
                         f"{path / 'result.json'}")
    if not directory.is_dir():
        raise ValueError(f"--out {out}: no directory {directory}; create it first "
                         f"(mkdir -p {directory})")
    if not os.access(directory, os.W_OK):
        raise ValueError(f"--out {out}: the directory {directory} is not writable")


def verdict_line(quality: QualityBlock | None, cv: CrossValidationBlock | None) -> str:
    """One line for people: the verdict (pass when there is none), the cross-validated error
    and the findings' codes."""
    from calib import QualityBlock

    quality = quality or QualityBlock(verdict="pass")
    if cv is None:
        figure = "no cross-validation (no robot poses)"
    elif cv.rms_px is not None:
        figure = (f"cross-validated error {cv.rms_px:.2f} px ({cv.rms_mm:.2f} mm at the "
                  f"board), {cv.kind} over {len(cv.stations)} stations" + cv.dropped_clause())
    else:
        figure = (f"cross-validated error {cv.trans_mm:.2f} mm / {cv.rot_deg:.3f} deg, "
                  f"{cv.kind} over {len(cv.stations)} stations")
    codes = [f.code for f in quality.findings]
    return (f"cellcal: verdict {quality.verdict}: {figure}"
            + (f"; findings: {', '.join(codes)}" if codes else ""))


#: What reading and detecting one station's image gives: its detection, the image size
#: (width, height; None when it could not be read) and, for the first image, the grid it shows
#: instead of the configured board (``ChecksConfiguration.mismatch``) or None.
Seen = tuple[Detection, tuple[int, int] | None, str | None]


def _detect_ahead(pool: ThreadPoolExecutor, args: argparse.Namespace, stations: Stations
                  ) -> list[Future[Seen] | None]:
    """Start reading and detecting every image station on ``pool``'s threads (OpenCV releases
    the GIL), the first image first; None for stations without an image file."""
    if stations.target is None:  # refused by the solver
        return [None] * len(stations.stations)
    board = board_from_target(stations.target)
    directory = Path(args.station_dir)

    def seen(name: str, first: bool) -> Seen:
        image = read_station_image(directory, name, max_pixels=args.max_image_pixels)
        if isinstance(image, Detection):
            return image, None, None
        mismatch = (board.mismatch(image) if first and isinstance(board, ChecksConfiguration)
                    else None)
        return board.detect(image), (image.shape[1], image.shape[0]), mismatch

    return [pool.submit(seen, s.image, k == 0) if isinstance(s.image, str) else None
            for k, s in enumerate(stations.stations)]


class _BarStream:
    """stderr for the progress bar, written only while no image decoder captures it
    (``STDERR_LOCK``)."""

    def write(self, text: str) -> int:
        with STDERR_LOCK:
            sys.stderr.write(text)
            sys.stderr.flush()
        return len(text)

    def flush(self) -> None:
        """Every write is flushed already."""


def _detected(args: argparse.Namespace, stations: Stations,
              ahead: list[Future[Seen] | None]) -> Stations:
    """``stations`` with the detections and image sizes of ``ahead``, waited for in order
    behind a progress bar (from ``PROGRESS_MIN_IMAGES`` images on). A checkerboard of
    another size than the configured one is told from the first image, before the solve."""
    from tqdm import tqdm

    done: list[Station] = []
    with tqdm(total=len(ahead), desc="detecting corners", unit="image", file=_BarStream(),
              disable=len(ahead) < PROGRESS_MIN_IMAGES, leave=False) as bar:
        for station, task in zip(stations.stations, ahead, strict=True):
            if task is not None:
                detection, size, mismatch = task.result()
                if mismatch is not None:
                    raise ValueError(f"{args.station_dir}: station {station.id}: {mismatch}: "
                                     "correct the target in stations.json")
                station = replace(station, detection=detection, image_size=size)
            done.append(station)
            bar.update()
    return replace(stations, stations=tuple(done))
