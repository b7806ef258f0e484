"""ArUco markers in an image: which dictionary, and which ChArUco board they suggest.

Used when a board is not found, to say what *is* in view: a checkerboard configuration
pointed at a ChArUco board, or a ChArUco configuration with the wrong dictionary. Each
marker family is searched once with its largest OpenCV dictionary (the smaller ones,
``DICT_5X5_100`` and so on, are its first ids), and the answer names the smallest standard
dictionary that holds every id seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: Families searched, each as (largest dictionary, standard sizes in increasing order).
_FAMILIES = (
    ("DICT_4X4", (50, 100, 250, 1000)),
    ("DICT_5X5", (50, 100, 250, 1000)),
    ("DICT_6X6", (50, 100, 250, 1000)),
    ("DICT_7X7", (50, 100, 250, 1000)),
    ("DICT_APRILTAG_36h11", ()),
)
#: Fewest markers of one family that count as a sighting (one alone can be a false match).
_MIN_MARKERS = 2
#: Fewest markers needed to guess the board layout (a homography needs four, one spare).
_MIN_FOR_LAYOUT = 5
#: Widest board (squares) a layout guess considers.
_MAX_COLS = 40


@dataclass(frozen=True)
class Sighting:
    """ArUco markers of one dictionary found in an image."""

    dictionary: str
    ids: np.ndarray  # (M,) int
    centres: np.ndarray  # (M, 2) px
    corners: np.ndarray  # (M, 4, 2) px


def dictionary(name: str) -> cv2.aruco.Dictionary:
    """OpenCV's predefined dictionary ``name`` (e.g. ``"DICT_5X5_100"``); ValueError if unknown."""
    if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise ValueError(f"unknown ArUco dictionary {name!r}: use OpenCV's name, "
                         "e.g. DICT_5X5_100 or DICT_APRILTAG_36h11")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def find_markers(grey: np.ndarray, name: str) -> Sighting | None:
    """Markers of dictionary ``name`` in a grey image; None when fewer than two."""
    corners, ids, _ = cv2.aruco.ArucoDetector(dictionary(name)).detectMarkers(grey)
    if ids is None or len(ids) < _MIN_MARKERS:
        return None
    quads = np.asarray(corners, dtype=float).reshape(-1, 4, 2)
    return Sighting(name, ids.ravel().astype(int), quads.mean(axis=1), quads)


def scan_markers(grey: np.ndarray) -> Sighting | None:
    """The family with the most markers in view, named by its smallest standard dictionary
    holding all ids seen; None when no family shows two markers."""
    best: Sighting | None = None
    for family, sizes in _FAMILIES:
        name = f"{family}_{sizes[-1]}" if sizes else family
        seen = find_markers(grey, name)
        if seen is None or (best is not None and len(seen.ids) <= len(best.ids)):
            continue
        fits = [n for n in sizes if n > seen.ids.max()]
        best = Sighting(f"{family}_{fits[0]}" if sizes else family, seen.ids, seen.centres,
                        seen.corners)
    return best


def guess_charuco_layout(seen: Sighting) -> tuple[int, int, bool] | None:
    """(cols, rows, legacy_pattern) of the ChArUco board that best explains the markers.

    Each candidate width places the seen ids on OpenCV's layout (rows: the fewest that hold
    the largest id); the one whose marker centres map onto the image by a homography with the
    smallest residual, relative to the marker size, wins. None with fewer than five markers.
    """
    if len(seen.ids) < _MIN_FOR_LAYOUT:
        return None
    size_px = np.median(np.linalg.norm(np.diff(seen.corners, axis=1), axis=-1))
    best, best_err = None, np.inf
    n_markers = int(seen.ids.max()) + 1
    for cols in range(3, _MAX_COLS + 1):
        rows = max(3, -(-2 * n_markers // cols))
        while (cols * rows) // 2 < n_markers:
            rows += 1
        for legacy in (False, True):
            board = cv2.aruco.CharucoBoard((cols, rows), 1.0, 0.5, dictionary(seen.dictionary))
            board.setLegacyPattern(legacy)
            obj = np.asarray(board.getObjPoints(), dtype=float)[:, :, :2].mean(axis=1)
            H, _ = cv2.findHomography(obj[seen.ids], seen.centres, 0)
            if H is None:
                continue
            mapped = cv2.perspectiveTransform(obj[seen.ids].reshape(-1, 1, 2), H).reshape(-1, 2)
            err = float(np.sqrt(np.mean(np.sum((mapped - seen.centres) ** 2, axis=1))))
            if err < best_err - 1e-3 * size_px:
                best, best_err = (cols, rows, legacy), err
    return best if best_err < 0.5 * size_px else None


def markers_seen_reason(grey: np.ndarray, wanted: str) -> str | None:
    """Why ``wanted`` (e.g. "11x8-corner checkerboard") was not found when ArUco markers are
    in view: which dictionary and which ChArUco board they suggest. None without markers."""
    seen = scan_markers(grey)
    if seen is None:
        return None
    layout = guess_charuco_layout(seen)
    head = (f"no {wanted} found, but {len(seen.ids)} ArUco markers of {seen.dictionary} are "
            f"in view (ids {seen.ids.min()}..{seen.ids.max()}): this looks like a ChArUco board")
    if layout is None:
        return f"{head}; use a charuco target with dictionary {seen.dictionary}"
    cols, rows, legacy = layout
    legacy_text = ", legacy_pattern true" if legacy else ""
    return (f"{head}, e.g. type charuco, squares [{cols}, {rows}] (rows at least), dictionary "
            f"{seen.dictionary}{legacy_text}: check the target configuration")
