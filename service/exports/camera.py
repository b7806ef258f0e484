"""Exports of the camera model: OpenCV ``cv::FileStorage`` YAML and ROS ``camera_info`` YAML.

Each writer takes ``(result_json, setup, camera_name)`` of a result that has a camera model and
returns ``(content, media_type, filename)``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from service.exports.common import FRAMES, matrix, num


def _camera(result_json: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """K (3, 3), dist (n,) and (width, height) of the result."""
    cam = result_json["camera"]
    K = np.asarray(cam["K"], dtype=float)
    dist = np.asarray(cam.get("dist") or [], dtype=float).ravel()
    size = cam.get("image_size")
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise ValueError(f"camera.K must be a finite 3x3 matrix, got shape {K.shape}")
    if size is None or len(size) != 2 or min(size) <= 0:
        raise ValueError(f"camera.image_size must be [width, height], got {size!r}")
    return K, dist, (int(size[0]), int(size[1]))


def opencv_yaml(result_json: dict[str, Any], setup: str, camera_name: str) -> tuple[str, str,
                                                                                    str]:
    """cv::FileStorage YAML, written by OpenCV itself so that OpenCV reads it back; the hand-eye
    and board pose as 4x4 ``!!opencv-matrix`` when the result has them."""
    K, dist, (w, h) = _camera(result_json)
    fs = cv2.FileStorage("calibration.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.writeComment(f"cellcal calibration of {camera_name}; metres and radians")
    fs.write("image_width", w)
    fs.write("image_height", h)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist.reshape(1, -1))
    fs.write("setup", setup)
    if result_json.get("hand_eye"):
        he_name, tp_name = FRAMES[setup]
        fs.writeComment(f"hand_eye = {he_name}, target_pose = {tp_name} (a_T_b maps b to a)")
        fs.write("hand_eye", matrix(result_json, "hand_eye"))
        if result_json.get("target_pose"):
            fs.write("target_pose", matrix(result_json, "target_pose"))
    target = result_json.get("target") or {}
    for key in ("kappa", "nu"):
        if target.get(key) is not None:
            fs.write(key, float(target[key]))
    return fs.releaseAndGetString(), "application/yaml", "camera_calibration.yaml"


def ros_camera_info(result_json: dict[str, Any], setup: str,
                    camera_name: str) -> tuple[str, str, str]:
    """ROS camera_info YAML; monocular, so R = I and P = [K | 0]."""
    K, dist, (w, h) = _camera(result_json)
    if dist.size in (4, 5):
        model, dist = "plumb_bob", np.pad(dist, (0, 5 - dist.size))
    elif dist.size == 8:
        model = "rational_polynomial"
    else:
        raise ValueError(f"ROS camera_info has no distortion model with {dist.size} "
                         "coefficients (plumb_bob takes 5, rational_polynomial 8)")
    P = np.hstack([K, np.zeros((3, 1))])
    text = "\n".join([
        f"image_width: {w}",
        f"image_height: {h}",
        f"camera_name: {camera_name}",
        _ros_matrix("camera_matrix", K),
        f"distortion_model: {model}",
        _ros_matrix("distortion_coefficients", dist.reshape(1, -1)),
        _ros_matrix("rectification_matrix", np.eye(3)),
        _ros_matrix("projection_matrix", P),
    ]) + "\n"
    return text, "application/yaml", "camera_info.yaml"


def _ros_matrix(name: str, M: np.ndarray) -> str:
    data = ", ".join(num(v) for v in M.ravel())
    return f"{name}:\n  rows: {M.shape[0]}\n  cols: {M.shape[1]}\n  data: [{data}]"


#: Format name -> writer, in the order the formats are listed.
WRITERS: dict[str, Callable[[dict[str, Any], str, str], tuple[str, str, str]]] = {
    "opencv-yaml": opencv_yaml, "ros-camera-info": ros_camera_info}
