import json
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.geometry import make_transform, matrix_from_ur_pose
from service.exports import FORMATS, ExportNames, export
from tests.support.results import SCENE, full_result, pose_only_result


def read_cv_yaml(text):
    return cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY
                           | cv2.FILE_STORAGE_FORMAT_YAML)


def test_json_round_trips():
    result = full_result()
    content, media, name = export(result, "json")
    assert (media, name) == ("application/json", "calibration.json")
    assert json.loads(content) == result


def test_opencv_yaml_round_trips_through_filestorage():
    content, media, name = export(full_result(), "opencv-yaml")
    assert media == "application/yaml" and name.endswith(".yaml")
    assert content.startswith("%YAML:1.0")
    assert "hand_eye: !!opencv-matrix" in content
    fs = read_cv_yaml(content)
    assert fs.getNode("image_width").real() == 1280
    assert fs.getNode("image_height").real() == 1024
    np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), SCENE.camera.k_matrix)
    np.testing.assert_array_equal(fs.getNode("distortion_coefficients").mat().ravel(),
                                  SCENE.camera.dist)
    np.testing.assert_array_equal(fs.getNode("hand_eye").mat(), SCENE.hand_eye_matrix)
    np.testing.assert_array_equal(fs.getNode("target_pose").mat(), SCENE.target_pose_matrix)
    assert fs.getNode("setup").string() == "eye_in_hand"
    assert fs.getNode("kappa").real() == 1.005
    assert "hand_eye = T_tcp_cam" in content


def test_ros_camera_info_has_the_ros_layout():
    content, media, name = export(full_result(), "ros-camera-info",
                                  ExportNames(camera_name="cell_cam"))
    assert (media, name) == ("application/yaml", "camera_info.yaml")
    lines = content.splitlines()
    assert lines[:3] == ["image_width: 1280", "image_height: 1024", "camera_name: cell_cam"]
    assert "distortion_model: plumb_bob" in lines
    for key, shape in [("camera_matrix", (3, 3)), ("distortion_coefficients", (1, 5)),
                       ("rectification_matrix", (3, 3)), ("projection_matrix", (3, 4))]:
        i = lines.index(f"{key}:")
        assert lines[i + 1:i + 3] == [f"  rows: {shape[0]}", f"  cols: {shape[1]}"]
    # the same text read as YAML (OpenCV's parser needs its header line)
    fs = read_cv_yaml("%YAML:1.0\n" + content)
    data = {k: np.array([fs.getNode(k).getNode("data").at(i).real()
                         for i in range(fs.getNode(k).getNode("data").size())])
            for k in ("camera_matrix", "distortion_coefficients", "rectification_matrix",
                      "projection_matrix")}
    K = SCENE.camera.k_matrix
    np.testing.assert_array_equal(data["camera_matrix"].reshape(3, 3), K)
    np.testing.assert_array_equal(data["distortion_coefficients"], SCENE.camera.dist)
    np.testing.assert_array_equal(data["rectification_matrix"].reshape(3, 3), np.eye(3))
    np.testing.assert_array_equal(data["projection_matrix"].reshape(3, 4),
                                  np.hstack([K, np.zeros((3, 1))]))


def test_ros_camera_info_distortion_models():
    four = export(full_result(dist=[0.1, 0.2, 0.0, 0.0]), "ros-camera-info")[0]
    assert "data: [0.1, 0.2, 0.0, 0.0, 0.0]" in four
    eight = export(full_result(dist=[0.1] * 8), "ros-camera-info")[0]
    assert "distortion_model: rational_polynomial" in eight
    with pytest.raises(ValueError, match="no distortion model with 14 coefficients"):
        export(full_result(dist=[0.0] * 14), "ros-camera-info")


def urdf_joint(content):
    root = ET.fromstring(content)
    joint = root.find("joint")
    origin = joint.find("origin")
    xyz = np.array(origin.get("xyz").split(), dtype=float)
    rpy = np.array(origin.get("rpy").split(), dtype=float)
    return joint, xyz, rpy


@pytest.mark.parametrize(("setup", "parent"), [("eye_in_hand", "tool0"),
                                               ("eye_to_hand", "base")])
def test_urdf_origin_reproduces_the_hand_eye(setup, parent):
    X = SCENE.hand_eye_matrix
    content, media, name = export(full_result(setup), "urdf")
    assert (media, name) == ("application/xml", "camera_joint.urdf")
    joint, xyz, rpy = urdf_joint(content)
    assert joint.get("type") == "fixed"
    assert joint.find("parent").get("link") == parent
    assert joint.find("child").get("link") == "camera_optical_frame"
    np.testing.assert_array_equal(xyz, X[:3, 3])
    # URDF rpy: fixed axes x, y, z, i.e. R = Rz(yaw) Ry(pitch) Rx(roll)
    Rz, Ry, Rx = (Rotation.from_euler(a, v).as_matrix() for a, v in zip("zyx", rpy[::-1],
                                                                          strict=True))
    np.testing.assert_allclose(Rz @ Ry @ Rx, X[:3, :3], atol=1e-14)
    np.testing.assert_allclose(Rotation.from_euler("xyz", rpy).as_matrix(), X[:3, :3],
                               atol=1e-14)
    assert "R = Rz(yaw) Ry(pitch) Rx(roll)" in content


def test_urdf_at_gimbal_lock_still_reproduces_the_matrix():
    X = make_transform(Rotation.from_euler("xyz", [0.3, np.pi / 2, -0.2]).as_matrix(),
                       [0.0, 0.0, 0.1])
    _, _, rpy = urdf_joint(export(full_result(hand_eye=X), "urdf")[0])
    np.testing.assert_allclose(Rotation.from_euler("xyz", rpy).as_matrix(), X[:3, :3],
                               atol=1e-12)


def test_ur_pose_is_the_hand_eye_as_a_pose_vector():
    content, media, name = export(pose_only_result(), "ur-pose")
    assert media == "text/plain" and name.endswith(".txt")
    comment, line = content.splitlines()
    assert comment.startswith("# ") and "T_tcp_cam" in comment and "TCP offset" in comment
    assert line.startswith("p[") and line.endswith("]")
    pose = np.array(line[2:-1].split(","), dtype=float)
    np.testing.assert_allclose(matrix_from_ur_pose(pose), SCENE.hand_eye_matrix, atol=1e-15)


def test_pose_formats_work_for_pose_only_results():
    assert export(pose_only_result(), "urdf")[0].startswith("<?xml")
    assert json.loads(export(pose_only_result(), "json")[0])["camera"] is None


@pytest.mark.parametrize("fmt", ["opencv-yaml", "ros-camera-info"])
def test_camera_formats_refuse_pose_only_results(fmt):
    with pytest.raises(ValueError, match=f"format '{fmt}' needs a camera model.*pose-only.*"
                                         "json, urdf, ur-pose"):
        export(pose_only_result(), fmt)


def test_unknown_format_lists_the_choices():
    with pytest.raises(ValueError, match="unknown export format 'csv': choose one of "
                                         + ", ".join(FORMATS)):
        export(full_result(), "csv")


def test_bad_hand_eye_is_refused():
    result = full_result()
    result["hand_eye"]["matrix"][0][0] = 2.0
    with pytest.raises(ValueError, match=r"hand_eye.*not orthonormal"):
        export(result, "ur-pose")


def test_a_result_with_a_robot_translation_map_carries_it_into_every_hand_eye_export():
    """The hand-eye holds for readings mapped by S (the model selection's robot-scale term):
    each export with the hand-eye says so and carries S; without a map nothing is added."""
    S = [[0.003, 0.0005, 0.0], [0.0, -0.002, 0.0], [0.0, 0.0, 0.001]]
    finding = {"code": "robot_translation_map", "severity": "info", "message": "...",
               "largest_entry": 0.003, "largest_shift_m": 0.0021}
    result = full_result() | {"robot_translation_map": S,
                              "quality": {"verdict": "pass", "findings": [finding]}}
    for fmt in ("urdf", "ur-pose", "ros2-static-tf", "opencv-yaml"):
        content = export(result, fmt)[0]
        assert "robot_translation_map S = [0.003, 0.0005, 0.0; 0.0, -0.002, 0.0;" in content, fmt
        assert "corrected to t + S t" in content and "2.1 mm" in content, fmt
        assert "robot_translation_map" not in export(full_result(), fmt)[0], fmt
    urdf_joint(export(result, "urdf")[0])  # still well-formed XML
    assert export(result, "ur-pose")[0].splitlines()[-1].startswith("p[")
    compile(export(result, "ros2-static-tf")[0], "launch.py", "exec")
    fs = read_cv_yaml(export(result, "opencv-yaml")[0])
    np.testing.assert_array_equal(fs.getNode("robot_translation_map").mat(), S)
