"""Every export opens in the program that consumes it: OpenCV's FileStorage, a ROS
camera_info YAML read field by field, ``urdf_parser_py`` for the URDF, and the ROS 2 launch
file read as Python (``ast``); the numbers read back reproduce the result.

Also: results with only intrinsics export what they have and refuse the rest by name; frame
names are configurable and checked.
"""

from __future__ import annotations

import ast
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation
from urdf_parser_py.urdf import URDF

from calib.geometry import make_transform
from service.exports import CAMERA_FORMATS, TRANSFORM_FORMATS, ExportNames, export
from tests.support.results import SCENE, full_result, intrinsics_only_result, pose_only_result


def filestorage(text: str) -> cv2.FileStorage:
    return cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY
                           | cv2.FILE_STORAGE_FORMAT_YAML)


def launch_arguments(text: str) -> tuple[ast.Call, dict[str, str]]:
    """The ``Node(...)`` call of a ROS 2 launch file and its ``--key value`` arguments."""
    tree = ast.parse(text)
    funcs = [n for n in tree.body if isinstance(n, ast.FunctionDef)]
    assert [f.name for f in funcs] == ["generate_launch_description"]
    imports = {(n.module, a.name) for n in tree.body if isinstance(n, ast.ImportFrom)
               for a in n.names}
    assert imports == {("launch", "LaunchDescription"), ("launch_ros.actions", "Node")}
    nodes = [n for n in ast.walk(tree) if isinstance(n, ast.Call)
             and isinstance(n.func, ast.Name) and n.func.id == "Node"]
    assert len(nodes) == 1
    keywords = {k.arg: k.value for k in nodes[0].keywords}
    args = ast.literal_eval(keywords["arguments"])
    assert all(isinstance(a, str) for a in args) and len(args) % 2 == 0
    assert all(k.startswith("--") for k in args[::2])
    return nodes[0], {k[2:]: v for k, v in zip(args[::2], args[1::2], strict=True)}


def launch_transform(args: dict[str, str]) -> np.ndarray:
    """parent_T_child (4, 4) from static_transform_publisher arguments."""
    q = [float(args[k]) for k in ("qx", "qy", "qz", "qw")]
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-12)
    return make_transform(Rotation.from_quat(q).as_matrix(),
                          [float(args[k]) for k in ("x", "y", "z")])


# ---- camera formats -------------------------------------------------------------------------

def test_opencv_yaml_of_an_intrinsics_only_result_has_the_camera_and_no_pose() -> None:
    fs = filestorage(export(intrinsics_only_result(), "opencv-yaml")[0])
    np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), SCENE.camera.k_matrix)
    np.testing.assert_array_equal(fs.getNode("distortion_coefficients").mat().ravel(),
                                  SCENE.camera.dist)
    assert fs.getNode("hand_eye").empty() and fs.getNode("target_pose").empty()
    assert fs.getNode("nu").real() == 0.9975


@pytest.mark.parametrize("result", [full_result, intrinsics_only_result])
def test_camera_info_read_as_yaml_field_by_field(result: Any) -> None:
    info = yaml.safe_load(export(result(), "ros-camera-info", ExportNames("cell_cam"))[0])
    assert set(info) == {"image_width", "image_height", "camera_name", "camera_matrix",
                         "distortion_model", "distortion_coefficients",
                         "rectification_matrix", "projection_matrix"}
    assert (info["image_width"], info["image_height"]) == (1280, 1024)
    assert info["camera_name"] == "cell_cam"
    assert info["distortion_model"] == "plumb_bob"
    K = SCENE.camera.k_matrix
    expected = {"camera_matrix": K, "distortion_coefficients": np.reshape(SCENE.camera.dist,
                                                                          (1, 5)),
                "rectification_matrix": np.eye(3),
                "projection_matrix": np.hstack([K, np.zeros((3, 1))])}
    for key, M in expected.items():
        assert (info[key]["rows"], info[key]["cols"]) == M.shape
        assert all(isinstance(v, float) for v in info[key]["data"])
        np.testing.assert_array_equal(np.reshape(info[key]["data"], M.shape), M)


# ---- transform formats ----------------------------------------------------------------------

@pytest.mark.parametrize(("setup", "parent"), [("eye_in_hand", "tool0"),
                                               ("eye_to_hand", "base")])
def test_urdf_parses_with_urdf_parser_py(setup: str, parent: str) -> None:
    X = SCENE.hand_eye_matrix
    robot = URDF.from_xml_string(export(full_result(setup), "urdf")[0])
    assert sorted(link.name for link in robot.links) == sorted([parent,
                                                               "camera_optical_frame"])
    (joint,) = robot.joints
    assert (joint.name, joint.type) == ("camera_joint", "fixed")
    assert (joint.parent, joint.child) == (parent, "camera_optical_frame")
    assert robot.get_root() == parent
    np.testing.assert_array_equal(joint.origin.xyz, X[:3, 3])
    np.testing.assert_allclose(Rotation.from_euler("xyz", joint.origin.rpy).as_matrix(),
                               X[:3, :3], atol=1e-14)


def test_urdf_takes_the_configured_frame_names() -> None:
    names = ExportNames("wrist_cam", parent_frame="ur10e_tool0", child_frame="wrist_cam_optical")
    robot = URDF.from_xml_string(export(full_result(), "urdf", names)[0])
    (joint,) = robot.joints
    assert (joint.name, joint.parent, joint.child) == ("wrist_cam_joint", "ur10e_tool0",
                                                       "wrist_cam_optical")


@pytest.mark.parametrize(("setup", "parent"), [("eye_in_hand", "tool0"),
                                               ("eye_to_hand", "base")])
def test_ros2_launch_file_publishes_the_hand_eye(setup: str, parent: str) -> None:
    content, media, name = export(full_result(setup), "ros2-static-tf")
    assert (media, name) == ("text/x-python", "camera_static_tf.launch.py")
    node, args = launch_arguments(content)
    keywords = {k.arg: ast.literal_eval(k.value) for k in node.keywords if k.arg != "arguments"}
    assert keywords == {"package": "tf2_ros", "executable": "static_transform_publisher",
                        "name": "camera_static_tf"}
    assert set(args) == {"x", "y", "z", "qx", "qy", "qz", "qw", "frame-id", "child-frame-id"}
    assert (args["frame-id"], args["child-frame-id"]) == (parent, "camera_optical_frame")
    assert float(args["qw"]) >= 0.0
    T = launch_transform(args)
    np.testing.assert_array_equal(T[:3, 3], SCENE.hand_eye_matrix[:3, 3])
    np.testing.assert_allclose(T, SCENE.hand_eye_matrix, atol=1e-14)


def test_ros2_launch_file_takes_the_configured_frames_and_pose_only_results() -> None:
    names = ExportNames("cam2", parent_frame="robot/flange", child_frame="cam2_link")
    content, _, name = export(pose_only_result(), "ros2-static-tf", names)
    assert name == "cam2_static_tf.launch.py"
    _, args = launch_arguments(content)
    assert (args["frame-id"], args["child-frame-id"]) == ("robot/flange", "cam2_link")
    np.testing.assert_allclose(launch_transform(args), SCENE.hand_eye_matrix, atol=1e-14)


# ---- what a result cannot give, and bad names ------------------------------------------------

@pytest.mark.parametrize("fmt", TRANSFORM_FORMATS)
def test_intrinsics_only_results_refuse_transform_formats_by_name(fmt: str) -> None:
    with pytest.raises(ValueError, match=f"format '{fmt}' needs a hand-eye transform, but this "
                                         r"result has none \(intrinsics-only calibration\): "
                                         "export it as json, opencv-yaml, ros-camera-info$"):
        export(intrinsics_only_result(), fmt)


@pytest.mark.parametrize("fmt", CAMERA_FORMATS)
def test_pose_only_results_list_every_transform_format(fmt: str) -> None:
    with pytest.raises(ValueError, match=r"export it as json, urdf, ur-pose, ros2-static-tf$"):
        export(pose_only_result(), fmt)


@pytest.mark.parametrize(("fields", "match"), [
    ({"camera_name": "my cam"}, "camera name 'my cam'"),
    ({"camera_name": "3d"}, "camera name '3d'"),
    ({"parent_frame": "tool0\"/><x"}, "parent frame"),
    ({"child_frame": "/camera"}, "child frame '/camera'"),
    ({"child_frame": "a//b"}, "child frame 'a//b'"),
])
def test_names_that_cannot_be_written_are_refused(fields: dict[str, str], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ExportNames(**fields)
