"""The OpenCV pipeline a user writes without cellcal, as one script: the peer of
``cellcal calibrate`` in ``benchmarks/end_to_end.py``.

    python benchmarks/opencv_pipeline.py STATION_DIR

Reads ``stations.json`` (checkerboard, UR pose vectors), finds the corners with
``findChessboardCornersSB`` (default flags), calibrates the camera (``calibrateCamera``) and
the hand-eye (``calibrateHandEye``, Park; eye-in-hand) and prints X = T_tcp_cam. Imports only
OpenCV and numpy, as such a script would.
"""

import json
import sys
from pathlib import Path

import cv2
import numpy as np


def main(directory: Path) -> np.ndarray:
    doc = json.loads((directory / "stations.json").read_text())
    cols, rows = doc["target"]["inner_corners"]
    grid = np.zeros((cols * rows, 3), np.float32)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * doc["target"]["square_size_m"]
    corners, poses, size = [], [], None
    for station in doc["stations"]:
        grey = cv2.imread(str(directory / station["image"]), cv2.IMREAD_GRAYSCALE)
        size = grey.shape[::-1]
        found, c = cv2.findChessboardCornersSB(grey, (cols, rows))
        if found:
            corners.append(c)
            poses.append(np.asarray(station["tcp_pose"], dtype=float))
    _, _, _, rvecs, tvecs = cv2.calibrateCamera([grid] * len(corners), corners, size, None, None)
    R, t = cv2.calibrateHandEye([cv2.Rodrigues(p[3:])[0] for p in poses],
                                [p[:3].reshape(3, 1) for p in poses],
                                [cv2.Rodrigues(r)[0] for r in rvecs], list(tvecs),
                                method=cv2.CALIB_HAND_EYE_PARK)
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R, t.ravel()
    return X


if __name__ == "__main__":
    print(np.array2string(main(Path(sys.argv[1])), precision=6))
