"""A benchmark's simulated or recorded stations as :func:`calib.calibrate` takes them.

Benchmarks hold what the camera saw as detections (corners with their point ids) or as the
corners (N, 2) of the whole board in point-id order (simulated corners). :func:`station_set`
makes one :class:`calib.Stations` of them, so every benchmark goes into the solver by the same
entry as the command line and the service.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calib import Board, Detection, Station, Stations
from calib.stations import whole_board_detection


def station_set(observations: Sequence[np.ndarray | Detection],
                tcp_poses: Sequence[Sequence[float]] | np.ndarray | None, board: Board, *,
                image_size: Sequence[int], setup: str = "eye_in_hand") -> Stations:
    """Stations ``000``, ``001``, ... of ``board`` seen as ``observations`` at the UR pose
    vectors ``tcp_poses`` (None: an intrinsics-only set), in images of ``image_size``
    (width, height)."""
    size = (int(image_size[0]), int(image_size[1]))
    poses = [None] * len(observations) if tcp_poses is None else tcp_poses
    return Stations(setup, tuple(
        Station(id=f"{k:03d}",
                T_base_tcp=None if pose is None else np.asarray(pose, dtype=float),
                image_size=size, detection=seen if isinstance(seen, Detection)
                else whole_board_detection(np.asarray(seen), board))
        for k, (seen, pose) in enumerate(zip(observations, poses, strict=True))),
        board.target())
