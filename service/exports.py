"""Export a result document (``cellcal/result@1``) in the format a user's stack wants.

Formats (``FORMATS``):

* ``json`` — the result document itself;
* ``opencv-yaml`` — ``cv::FileStorage`` YAML: ``camera_matrix``, ``distortion_coefficients``,
  ``image_width``/``image_height``, and ``hand_eye``/``target_pose`` as 4x4 ``!!opencv-matrix``;
* ``ros-camera-info`` — the YAML of ROS ``camera_calibration_parsers`` (``camera_info``);
* ``urdf`` — a fixed joint from ``tool0`` (eye-in-hand) or ``base`` (eye-to-hand) to the
  camera's optical frame;
* ``ur-pose`` — the hand-eye as a UR pose ``p[x, y, z, rx, ry, rz]``.

The camera formats need the camera model and refuse pose-only results. Transforms are taken
from the ``matrix`` fields (the ``pose`` vectors are derived from them). The camera frame is
OpenCV's (x right, y down, z along the optical axis), which is ROS's *optical* frame
convention (REP 103), hence the ``*_optical_frame`` link name.
"""

from __future__ import annotations

import json
import warnings
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from calib.geometry import check_transforms, ur_pose_from_matrix
from calib.handeye import SETUPS

FORMATS = ("json", "opencv-yaml", "ros-camera-info", "urdf", "ur-pose")
#: Formats that describe the camera model and so need intrinsics in the result.
CAMERA_FORMATS = ("opencv-yaml", "ros-camera-info")

#: What ``hand_eye`` / ``target_pose`` mean in each setup (``docs/conventions.md``).
_FRAMES = {"eye_in_hand": ("tcp_T_cam", "base_T_target"),
           "eye_to_hand": ("base_T_cam", "tcp_T_target")}
#: URDF parent link of the camera (UR's ROS names) and what it must stand for.
_URDF_PARENT = {
    "eye_in_hand": ("tool0", "tool0 stands for the TCP the calibration's poses were reported "
                             "for: the flange when the TCP offset was zero"),
    "eye_to_hand": ("base", "base is the UR controller's base frame (ur_description's base, "
                            "not base_link)"),
}


def export(result_json: dict[str, Any], fmt: str, *,
           camera_name: str = "camera") -> tuple[str, str, str]:
    """Render a result document as ``fmt``.

    Parameters
    ----------
    result_json : the result document (``product.md``, "Result").
    fmt : one of ``FORMATS``.
    camera_name : ROS ``camera_name`` and the prefix of the URDF camera link and joint.

    Returns
    -------
    content, media_type, filename : str
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format '{fmt}': choose one of {', '.join(FORMATS)}")
    if fmt == "json":
        return json.dumps(result_json, indent=2) + "\n", "application/json", "calibration.json"
    setup = result_json.get("setup")
    if setup not in SETUPS:
        raise ValueError(f"result has unknown setup {setup!r}: expected eye_in_hand or "
                         "eye_to_hand")
    if fmt in CAMERA_FORMATS:
        K, dist, (w, h) = _camera(result_json, fmt)
        if fmt == "opencv-yaml":
            return (_opencv_yaml(result_json, setup, K, dist, w, h), "application/yaml",
                    "camera_calibration.yaml")
        return _ros_camera_info(K, dist, w, h, camera_name), "application/yaml", "camera_info.yaml"
    X = _matrix(result_json, "hand_eye")
    if fmt == "urdf":
        return _urdf(X, setup, camera_name), "application/xml", f"{camera_name}_joint.urdf"
    return _ur_pose(X, setup), "text/plain", "hand_eye_ur_pose.txt"


def _matrix(result_json: dict[str, Any], key: str) -> np.ndarray:
    """The validated 4x4 ``result_json[key]['matrix']``."""
    try:
        T = result_json[key]["matrix"]
    except (KeyError, TypeError):
        raise ValueError(f"result has no {key}.matrix") from None
    return check_transforms(T, key)[0]


def _camera(result_json: dict[str, Any], fmt: str) -> tuple[np.ndarray, np.ndarray,
                                                           tuple[int, int]]:
    """K (3, 3), dist (n,) and (width, height) of the result, or a ValueError naming fmt."""
    cam = result_json.get("camera")
    if not cam or cam.get("K") is None:
        others = ", ".join(f for f in FORMATS if f not in CAMERA_FORMATS)
        raise ValueError(f"format '{fmt}' needs a camera model, but this result has none "
                         f"(pose-only hand-eye calibration): export it as {others}")
    K = np.asarray(cam["K"], dtype=float)
    dist = np.asarray(cam.get("dist") or [], dtype=float).ravel()
    size = cam.get("image_size")
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise ValueError(f"camera.K must be a finite 3x3 matrix, got shape {K.shape}")
    if size is None or len(size) != 2 or min(size) <= 0:
        raise ValueError(f"camera.image_size must be [width, height], got {size!r}")
    return K, dist, (int(size[0]), int(size[1]))


def _opencv_yaml(result_json: dict[str, Any], setup: str, K: np.ndarray, dist: np.ndarray,
                 w: int, h: int) -> str:
    """cv::FileStorage YAML, written by OpenCV itself so that OpenCV reads it back."""
    he_name, tp_name = _FRAMES[setup]
    fs = cv2.FileStorage("calibration.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.writeComment("cellcal calibration; metres and radians")
    fs.write("image_width", w)
    fs.write("image_height", h)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist.reshape(1, -1))
    fs.write("setup", setup)
    fs.writeComment(f"hand_eye = {he_name}, target_pose = {tp_name} (a_T_b maps b to a)")
    fs.write("hand_eye", _matrix(result_json, "hand_eye"))
    if result_json.get("target_pose"):
        fs.write("target_pose", _matrix(result_json, "target_pose"))
    target = result_json.get("target") or {}
    for key in ("kappa", "nu"):
        if key in target:
            fs.write(key, float(target[key]))
    return fs.releaseAndGetString()


def _ros_camera_info(K: np.ndarray, dist: np.ndarray, w: int, h: int, camera_name: str) -> str:
    """ROS camera_info YAML; monocular, so R = I and P = [K | 0]."""
    if dist.size in (4, 5):
        model, dist = "plumb_bob", np.pad(dist, (0, 5 - dist.size))
    elif dist.size == 8:
        model = "rational_polynomial"
    else:
        raise ValueError(f"ROS camera_info has no distortion model with {dist.size} "
                         "coefficients (plumb_bob takes 5, rational_polynomial 8)")
    P = np.hstack([K, np.zeros((3, 1))])
    return "\n".join([
        f"image_width: {w}",
        f"image_height: {h}",
        f"camera_name: {camera_name}",
        _ros_matrix("camera_matrix", K),
        f"distortion_model: {model}",
        _ros_matrix("distortion_coefficients", dist.reshape(1, -1)),
        _ros_matrix("rectification_matrix", np.eye(3)),
        _ros_matrix("projection_matrix", P),
    ]) + "\n"


def _ros_matrix(name: str, M: np.ndarray) -> str:
    data = ", ".join(_num(v) for v in M.ravel())
    return f"{name}:\n  rows: {M.shape[0]}\n  cols: {M.shape[1]}\n  data: [{data}]"


def _urdf(X: np.ndarray, setup: str, camera_name: str) -> str:
    """A URDF with the camera joint; ``rpy`` is URDF's fixed-axis roll-pitch-yaw."""
    (parent, parent_note), child = _URDF_PARENT[setup], f"{camera_name}_optical_frame"
    with warnings.catch_warnings():  # at pitch = ±90 deg any split of roll and yaw is exact
        warnings.simplefilter("ignore", UserWarning)
        rpy = Rotation.from_matrix(X[:3, :3]).as_euler("xyz")
    xyz = " ".join(_num(v) for v in X[:3, 3])
    return f"""<?xml version="1.0"?>
<!-- cellcal hand-eye ({setup}): {_FRAMES[setup][0]} as a fixed joint, metres and radians.
     rpy is URDF's fixed-axis roll-pitch-yaw: R = Rz(yaw) Ry(pitch) Rx(roll).
     {child}: OpenCV / ROS optical frame, x right, y down, z along the optical axis.
     {parent_note}.
     Copy the joint and the camera link into your robot description. -->
<robot name="cellcal_{camera_name}">
  <link name="{parent}"/>
  <link name="{child}"/>
  <joint name="{camera_name}_joint" type="fixed">
    <parent link="{parent}"/>
    <child link="{child}"/>
    <origin xyz="{xyz}" rpy="{" ".join(_num(v) for v in rpy)}"/>
  </joint>
</robot>
"""


def _ur_pose(X: np.ndarray, setup: str) -> str:
    """The hand-eye as a UR pose line with a comment saying what it is and how to use it."""
    pose = ", ".join(_num(v) for v in ur_pose_from_matrix(X))
    if setup == "eye_in_hand":
        what = ("tcp_T_cam: the camera's optical frame relative to the TCP used during "
                "calibration (the flange if its TCP offset was zero); set it as the TCP offset "
                "to make the camera the TCP")
    else:
        what = "base_T_cam: the camera's optical frame in the robot base frame"
    return f"# cellcal hand-eye ({setup}), {what}; metres, rotation vector in radians\n" \
           f"p[{pose}]\n"


def _num(v: float) -> str:
    """Shortest text that reads back as the same float."""
    return repr(float(v))
