"""Exports of the camera model: OpenCV ``cv::FileStorage`` YAML and ROS ``camera_info`` YAML.

Each writer takes ``(result, names)``: a result with a camera model (``service.exports.export``
lets no other one here) and the names to write, and returns ``(content, media_type,
filename)``.
"""

from __future__ import annotations

import cv2
import numpy as np

from calib import Result
from service.exports.common import FRAMES, ExportNames, matrix, num, robot_map_note


def _camera(result: Result) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """K (3, 3), dist (n,) and (width, height) of the result's camera model (shapes checked
    by the schema)."""
    cam = result.camera
    assert cam is not None  # the format needs it: export() checked
    w, h = cam.image_size
    return np.asarray(cam.K, dtype=float), np.asarray(cam.dist, dtype=float), (w, h)


def opencv_yaml(result: Result, names: ExportNames) -> tuple[str, str, str]:
    """cv::FileStorage YAML, written by OpenCV itself so that OpenCV reads it back; the hand-eye
    and board pose as 4x4 ``!!opencv-matrix`` when the result has them."""
    K, dist, (w, h) = _camera(result)
    setup = result.setup
    fs = cv2.FileStorage("calibration.yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.writeComment(f"cellcal calibration of {names.camera_name}; metres and radians")
    fs.write("image_width", w)
    fs.write("image_height", h)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist.reshape(1, -1))
    fs.write("setup", setup)
    if result.hand_eye is not None:
        he_name, tp_name = FRAMES[setup]
        fs.writeComment(f"hand_eye = {he_name}, target_pose = {tp_name} (T_a_b maps b to a)")
        fs.write("hand_eye", matrix(result.hand_eye, "hand_eye"))
        if result.target_pose is not None:
            fs.write("target_pose", matrix(result.target_pose, "target_pose"))
        if result.robot_translation_map is not None:
            for line in robot_map_note(result):
                fs.writeComment(line)
            fs.write("robot_translation_map", np.asarray(result.robot_translation_map))
    fs.write("kappa", result.target.kappa)
    fs.write("nu", result.target.nu)
    return fs.releaseAndGetString(), "application/yaml", "camera_calibration.yaml"


def ros_camera_info(result: Result, names: ExportNames) -> tuple[str, str, str]:
    """ROS camera_info YAML; monocular, so R = I and P = [K | 0]."""
    K, dist, (w, h) = _camera(result)
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
        f"camera_name: {names.camera_name}",
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

