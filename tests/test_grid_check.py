"""Corners checked against their neighbours (``calib.boards.grid_check``): the place a grid's
neighbours predict for each corner, and the refinement's strays sent back to their start."""

from __future__ import annotations

import cv2
import numpy as np

from calib.boards.grid_check import (
    MOVE_CHECKED,
    keep_consistent,
    neighbour_prediction,
    stray_corners,
)

COLS, ROWS = 11, 8


def _board_image(k1: float = 0.0) -> np.ndarray:
    """An 11x8 grid of corners (rows, cols, 2) as a tilted camera sees it: a homography, then
    radial distortion ``k1`` about the image centre (640, 360)."""
    jj, ii = np.mgrid[0:ROWS, 0:COLS]
    grid = np.stack([ii, jj], -1).astype(np.float64).reshape(-1, 1, 2)
    H = np.array([[36.0, 4.0, 420.0], [-3.0, 34.0, 220.0], [2e-3, 6e-3, 1.0]])
    px = cv2.perspectiveTransform(grid, H).reshape(-1, 2)
    r = (px - [640, 360]) / 640
    px = [640, 360] + r * (1 + k1 * (r ** 2).sum(axis=1, keepdims=True)) * 640
    return px.reshape(ROWS, COLS, 2)


def test_a_perspective_grid_is_predicted_exactly_and_a_distorted_one_closely() -> None:
    exact = _board_image()
    assert np.abs(neighbour_prediction(exact) - exact).max() < 1e-6
    bent = _board_image(k1=-0.25)  # strong barrel distortion, as the OpenCV left*.jpg show
    spacing = np.median(np.linalg.norm(np.diff(bent, axis=1), axis=-1))
    assert np.linalg.norm(neighbour_prediction(bent) - bent, axis=-1).max() < 0.03 * spacing


def test_a_bad_corner_does_not_move_its_neighbours_predictions() -> None:
    grid = _board_image(k1=-0.1)
    spacing = np.median(np.linalg.norm(np.diff(grid, axis=1), axis=-1))
    bad = grid.copy()
    bad[0, 0] += [2.0, 6.0]  # a board corner and its neighbour off by a sixth of a square
    bad[0, 1] += [0.0, 4.0]
    off = np.linalg.norm(neighbour_prediction(bad) - bad, axis=-1)
    assert off[0, 0] > 0.12 * spacing and off[0, 1] > 0.08 * spacing
    others = np.ones_like(off, dtype=bool)
    others[0, :2] = False
    assert off[others].max() < 0.02 * spacing


def test_a_stray_refinement_keeps_its_start_and_a_good_one_its_place() -> None:
    truth = _board_image(k1=-0.1).reshape(-1, 2)
    spacing = float(np.median(np.linalg.norm(np.diff(truth.reshape(ROWS, COLS, 2), axis=1),
                                             axis=-1)))
    rng = np.random.default_rng(3)
    start = truth + rng.normal(0.0, 0.1, truth.shape)  # the grid search's corners
    refined = truth + rng.normal(0.0, 0.02, truth.shape)
    refined[2] = truth[2] + [0.0, 3.0]  # pulled off by an edge that is not the corner's
    start[40] = truth[40] + [3.0, 0.0]  # a poor start the refinement corrected
    assert np.linalg.norm(refined[[2, 40]] - start[[2, 40]], axis=1).min() > (
        MOVE_CHECKED * spacing)
    kept = keep_consistent(start, refined, (COLS, ROWS), spacing)
    assert np.array_equal(kept[2], start[2])
    assert np.array_equal(kept[40], refined[40])
    others = np.setdiff1d(np.arange(len(truth)), [2])
    assert np.array_equal(kept[others], refined[others])
    # nothing moved that far: the refinement is returned as it is
    assert keep_consistent(refined, refined, (COLS, ROWS), spacing) is refined


def test_only_a_corner_a_third_of_a_square_off_is_a_stray() -> None:
    grid = _board_image(k1=-0.25).reshape(-1, 2)  # distorted as the real OpenCV set
    assert not stray_corners(grid, (COLS, ROWS)).any()
    spacing = np.median(np.linalg.norm(np.diff(grid.reshape(ROWS, COLS, 2), axis=1), axis=-1))
    misread = grid.copy()
    misread[6] += [0.0, 0.35 * spacing]  # the demo's misplaced corner, on the board's edge
    assert np.flatnonzero(stray_corners(misread, (COLS, ROWS))).tolist() == [6]
    assert not stray_corners(grid[:22], (COLS, 2)).any()  # too thin to check
