"""OpenCV's hand-eye methods behind our interface, for comparison and as alternatives.

``tsai``, ``park``, ``horaud``, ``andreff``, ``daniilidis`` solve ``A X = X B`` through
``cv2.calibrateHandEye``; ``shah`` and ``li`` solve ``A X = Z B`` for hand-eye and target pose
together through ``cv2.calibrateRobotWorldHandEye``. Inputs are in the eye-in-hand form of
``docs/conventions.md`` (``P_i X C_i = Y``): ``P`` robot chain poses, ``C`` = T_cam_target.
"""

from __future__ import annotations

import cv2
import numpy as np

from calib.geometry import invert, make_transform

OPENCV_HAND_EYE_METHODS = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}
#: OpenCV's hand-eye methods form every station pair (memory ~ n^2): larger sets are solved on
#: this many evenly spread stations (200 stations = 19,900 pairs).
MAX_PEER_STATIONS = 200
OPENCV_ROBOT_WORLD_METHODS = {
    "shah": cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH,
    "li": cv2.CALIB_ROBOT_WORLD_HAND_EYE_LI,
}


def solve_opencv(P: np.ndarray, C: np.ndarray, method: str) -> tuple[np.ndarray, np.ndarray | None]:
    """X (4x4) and, for ``shah``/``li``, Y (4x4) from OpenCV.

    Parameters
    ----------
    P : shape (n, 4, 4), robot chain poses (T_base_tcp for eye-in-hand).
    C : shape (n, 4, 4), camera observations T_cam_target.
    method : a key of ``OPENCV_HAND_EYE_METHODS`` or ``OPENCV_ROBOT_WORLD_METHODS``.

    At most ``MAX_PEER_STATIONS`` stations, evenly spread over the set, are passed on.
    """
    if len(P) > MAX_PEER_STATIONS:
        keep = np.unique(np.linspace(0, len(P) - 1, MAX_PEER_STATIONS).astype(int))
        P, C = P[keep], C[keep]
    if method in OPENCV_HAND_EYE_METHODS:
        R, t = cv2.calibrateHandEye(
            list(P[:, :3, :3]), list(P[:, :3, 3:]), list(C[:, :3, :3]), list(C[:, :3, 3:]),
            method=OPENCV_HAND_EYE_METHODS[method])
        return make_transform(R, t.ravel()), None
    Pinv = invert(P)
    R_base2world, t_base2world, R_gripper2cam, t_gripper2cam = cv2.calibrateRobotWorldHandEye(
        list(C[:, :3, :3]), list(C[:, :3, 3:]), list(Pinv[:, :3, :3]), list(Pinv[:, :3, 3:]),
        method=OPENCV_ROBOT_WORLD_METHODS[method])
    X = invert(make_transform(R_gripper2cam, t_gripper2cam.ravel()))
    Y = invert(make_transform(R_base2world, t_base2world.ravel()))
    return X, Y
