"""Detection reads every board OpenCV reads: real images (``../shared/data``) and degraded
copies of them, against ``findChessboardCornersSB`` under several flag sets.

The degradations are made here: low contrast, dark and bright gamma, sensor noise, defocus
blur and uneven lighting. A board that any of OpenCV's flag sets finds must be detected, in
the same place (corners within a few px of OpenCV's, whatever their order, wherever OpenCV's
corner fits the grid of its neighbours; where it does not, ours must fit it better). The fast test
takes one image per set and two flag sets; the slow one every image and five flag sets.
"""

from __future__ import annotations

import json
from collections.abc import Callable

import cv2
import numpy as np
import pytest

from calib.boards import checkerboard, detect_checkerboard
from calib.boards.grid_check import neighbour_prediction
from tests.support.helpers import OPENCV_LEFT, SHARED

UR_SETS = [SHARED / "data" / s for s in ("ur-kinect-highR_highT", "ur-kinect-lowR_highT")]
KUKA = SHARED / "data" / "rwhe-kuka_1"
OPENCV_FLAGS = {
    "normalize": cv2.CALIB_CB_NORMALIZE_IMAGE,
    "none": 0,
    "exhaustive": cv2.CALIB_CB_EXHAUSTIVE,
    "normalize+exhaustive": cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE,
    "accuracy": cv2.CALIB_CB_ACCURACY,
}


def _ramp(grey: np.ndarray) -> np.ndarray:
    """Light falling off to 15 % across the image and 50 % down it (one lamp at a corner)."""
    h, w = grey.shape
    gain = np.linspace(0.15, 1.0, w)[None, :] * np.linspace(0.5, 1.0, h)[:, None]
    return (grey * gain).astype(np.uint8)


def _noisy(grey: np.ndarray, sigma: float) -> np.ndarray:
    rng = np.random.default_rng(int(grey.sum()) % 2**32)
    return np.clip(grey + rng.normal(0.0, sigma, grey.shape), 0, 255).astype(np.uint8)


DEGRADATIONS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "original": lambda g: g,
    "contrast 10 %": lambda g: (g * 0.1 + 100).astype(np.uint8),
    "gamma 3.5": lambda g: (255 * (g / 255.0) ** 3.5).astype(np.uint8),
    "gamma 0.3": lambda g: (255 * (g / 255.0) ** 0.3).astype(np.uint8),
    "noise 25": lambda g: _noisy(g, 25.0),
    "blur 2.5 px": lambda g: cv2.GaussianBlur(g, (0, 0), 2.5),
    "uneven light + noise": lambda g: _noisy(_ramp(g), 6.0),
}


def _ur_images(every: int) -> list[tuple[str, tuple[int, int]]]:
    out = []
    for d in UR_SETS:
        doc = json.loads((d / "stations.json").read_text())
        board = tuple(doc["target"]["inner_corners"])
        out += [(str(d / s["image"]), board) for s in doc["stations"][::every]]
    return out


def _images(every: int) -> list[tuple[str, tuple[int, int]]]:
    left = [(str(p), (9, 6)) for p in sorted(OPENCV_LEFT.glob("left*.jpg"))[::every]]
    return left + _ur_images(every)


#: Squares here are 20-70 px; blur moves SB's corners by a few.
NEAR_PX = 5.0
#: A corner farther than this fraction of a square from the place its neighbours predict
#: (``calib.boards.grid_check``) is off the board's grid; real corners are within 0.062 on
#: every set here, with sensor noise or not.
OFF_GRID = 0.07


def _same_grid(ours: np.ndarray, theirs: np.ndarray, board: tuple[int, int]) -> bool:
    """Whether two detections of a grid put the board in the same place, in one of the grid's
    flips: each of our corners within ``NEAR_PX`` of OpenCV's, or, where OpenCV's corner is
    off the grid (a Kinect's registration shadow across a row of squares), nearer the grid
    than OpenCV's."""
    cols, rows = board
    g = theirs.reshape(rows, cols, 2)
    spacing = float(np.median(np.linalg.norm(np.diff(g, axis=1), axis=-1)))
    theirs_off = np.linalg.norm(g - neighbour_prediction(g), axis=-1)
    ours_off = np.linalg.norm(ours - neighbour_prediction(ours.reshape(rows, cols, 2))
                              .reshape(-1, 2), axis=1)
    for flip in (np.s_[:, :], np.s_[::-1, ::-1], np.s_[::-1, :], np.s_[:, ::-1]):
        apart = np.linalg.norm(g[flip].reshape(-1, 2) - ours, axis=1)
        their_off = theirs_off[flip].ravel()
        nearer = (their_off > OFF_GRID * spacing) & (ours_off < their_off)
        if ((apart < NEAR_PX) | nearer).all():
            return True
    return False


def _check(path: str, board: tuple[int, int], degrade: str, flag_sets: list[str]) -> bool:
    """Assert our detection where OpenCV reads the board with any of ``flag_sets``; return
    whether it did."""
    grey = DEGRADATIONS[degrade](cv2.imread(path, cv2.IMREAD_GRAYSCALE))
    found = {}
    for name in flag_sets:
        flags = OPENCV_FLAGS[name]
        ok, corners = cv2.findChessboardCornersSB(grey, board, flags=flags)
        if ok:
            found[name] = corners.reshape(-1, 2).astype(float)
    if not found:
        return False
    det = detect_checkerboard(grey, board)
    assert det.ok, f"{path} ({degrade}): OpenCV reads it with {sorted(found)}; " \
                   f"we say: {det.reason}"
    assert any(_same_grid(det.corners, c, board) for c in found.values()), \
        f"{path} ({degrade}): not where OpenCV reads the board with {sorted(found)}"
    return True


@pytest.mark.parametrize("degrade", DEGRADATIONS)
def test_every_board_opencv_reads_is_read(degrade: str) -> None:
    images = _images(every=100)  # the first image of each set
    flag_sets = ["normalize", "none"]
    compared = sum(_check(path, board, degrade, flag_sets) for path, board in images)
    assert compared >= len(images) - 1  # OpenCV reads (almost) all: the test compares


@pytest.mark.slow
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("degrade", DEGRADATIONS)
def test_every_board_opencv_reads_is_read_on_every_image(degrade: str) -> None:
    images = _images(every=1)
    compared = sum(_check(path, board, degrade, list(OPENCV_FLAGS)) for path, board in images)
    assert compared >= 0.8 * len(images)


def test_a_registration_shadow_does_not_pull_a_corner_off() -> None:
    """On ur-kinect-lowR_highT's snapshot_8 a Kinect depth-registration shadow (a black wedge)
    cuts across the board's first row. The sub-pixel refinement pulled the third corner 2.7 px
    along the wedge's edge: 3.3 px from where its neighbours put it, 3.8 px from
    ``findChessboardCornersSB``'s. It keeps the grid search's place
    (``calib.boards.grid_check.keep_consistent``)."""
    board = (11, 8)
    path = SHARED / "data" / "ur-kinect-lowR_highT" / "snapshot_8.png"
    for degrade in ("original", "noise 25"):
        grey = DEGRADATIONS[degrade](cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
        grid = detect_checkerboard(grey, board).corners.reshape(8, 11, 2)
        spacing = np.median(np.linalg.norm(np.diff(grid, axis=1), axis=-1))
        off = np.linalg.norm(neighbour_prediction(grid) - grid, axis=-1)
        assert off[0, 2] < 0.03 * spacing, (degrade, off[0, 2])
        _, sb = cv2.findChessboardCornersSB(grey, board)
        assert np.linalg.norm(sb.reshape(-1, 2) - grid[0, 2], axis=1).min() < 2.0, degrade


def test_low_contrast_board_is_read_and_a_flat_image_is_blank() -> None:
    """A board in 20 grey levels is read (OpenCV reads it); an image of under 20 levels
    without a board is still called blank."""
    path, board = _ur_images(100)[0]
    faint = (cv2.imread(path, cv2.IMREAD_GRAYSCALE) * 0.08 + 100).astype(np.uint8)
    assert np.percentile(faint, 99) - np.percentile(faint, 1) < 20
    assert cv2.findChessboardCornersSB(faint, board, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)[0]
    assert detect_checkerboard(faint, board).ok
    flat = _noisy(np.full((720, 1280), 110, np.uint8), 3.0)
    det = detect_checkerboard(flat, board)
    assert not det.ok and det.reason.startswith("image is blank")


@pytest.mark.parametrize("station", [0, 17])
def test_a_quarter_size_find_gives_the_corners_of_the_half_size_search(monkeypatch, station):
    """Large images are searched at quarter size first (``calib.boards.checkerboard``); a
    board found there ends at the corners the half-size search gives (1928x1208 KUKA)."""
    doc = json.loads((KUKA / "stations.json").read_text())
    board = tuple(doc["target"]["inner_corners"])
    grey = cv2.imread(str(KUKA / doc["stations"][station]["image"]), cv2.IMREAD_GRAYSCALE)
    refined_at_half = []
    sub_pixel = checkerboard.sub_pixel
    monkeypatch.setattr(checkerboard, "sub_pixel",
                        lambda *a: refined_at_half.append(1) or sub_pixel(*a))
    quick = detect_checkerboard(grey, board)
    assert refined_at_half  # the quarter-size search found it
    monkeypatch.setattr(checkerboard, "_QUARTER_MIN_SIZE", 10**6)
    half = detect_checkerboard(grey, board)
    assert quick.ok and half.ok
    assert np.abs(quick.corners - half.corners).max() < 1e-3

