"""Exports of the hand-eye transform: a URDF joint, a UR pose line and a ROS 2 launch file
publishing it as a static transform.

Each writer takes ``(result, names)``: a result with a hand-eye (``service.exports.export``
lets no other one here) and the names to write, and returns ``(content, media_type,
filename)``. The transform is taken from ``hand_eye.matrix`` (the ``pose`` vector is derived
from it). The camera frame is
OpenCV's (x right, y down, z along the optical axis), which is ROS's *optical* frame convention
(REP 103), hence the default ``*_optical_frame`` child name.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial.transform import Rotation

from calib import Result, ur_pose_from_matrix
from service.exports.common import FRAMES, ExportNames, matrix, num, robot_map_note

#: What the default parent frame must stand for, per setup.
_PARENT_NOTE = {
    "eye_in_hand": "tool0 stands for the TCP the calibration's poses were reported for: the "
                   "flange when the TCP offset was zero",
    "eye_to_hand": "base is the UR controller's base frame (ur_description's base, not "
                   "base_link)",
}


def _hand_eye(result: Result) -> np.ndarray:
    """The result's hand-eye, (4, 4), checked to be rigid."""
    assert result.hand_eye is not None  # the format needs it: export() checked
    return matrix(result.hand_eye, "hand_eye")


def urdf(result: Result, names: ExportNames) -> tuple[str, str, str]:
    """A URDF with the camera joint; ``rpy`` is URDF's fixed-axis roll-pitch-yaw."""
    X, setup = _hand_eye(result), result.setup
    parent, child = names.frames(setup)
    with warnings.catch_warnings():  # at pitch = ±90 deg any split of roll and yaw is exact
        warnings.simplefilter("ignore", UserWarning)
        rpy = Rotation.from_matrix(X[:3, :3]).as_euler("xyz")
    xyz = " ".join(num(v) for v in X[:3, 3])
    camera = names.camera_name
    note = "".join(f"\n     {line}" for line in robot_map_note(result))
    text = f"""<?xml version="1.0"?>
<!-- cellcal hand-eye ({setup}): {FRAMES[setup][0]} as a fixed joint, metres and radians.
     rpy is URDF's fixed-axis roll-pitch-yaw: R = Rz(yaw) Ry(pitch) Rx(roll).
     {child}: OpenCV / ROS optical frame, x right, y down, z along the optical axis.
     {_PARENT_NOTE[setup]}.{note}
     Copy the joint and the camera link into your robot description. -->
<robot name="cellcal_{camera}">
  <link name="{parent}"/>
  <link name="{child}"/>
  <joint name="{camera}_joint" type="fixed">
    <parent link="{parent}"/>
    <child link="{child}"/>
    <origin xyz="{xyz}" rpy="{" ".join(num(v) for v in rpy)}"/>
  </joint>
</robot>
"""
    return text, "application/xml", f"{camera}_joint.urdf"


def ur_pose(result: Result, names: ExportNames) -> tuple[str, str, str]:
    """The hand-eye as a UR pose line with a comment saying what it is and how to use it."""
    pose = ", ".join(num(v) for v in ur_pose_from_matrix(_hand_eye(result)))
    setup = result.setup
    if setup == "eye_in_hand":
        what = ("T_tcp_cam: the camera's optical frame relative to the TCP used during "
                "calibration (the flange if its TCP offset was zero); set it as the TCP offset "
                "to make the camera the TCP")
    else:
        what = "T_base_cam: the camera's optical frame in the robot base frame"
    text = (f"# cellcal hand-eye ({setup}), {what}; metres, rotation vector in radians\n"
            + "".join(f"# {line}\n" for line in robot_map_note(result)) + f"p[{pose}]\n")
    return text, "text/plain", "hand_eye_ur_pose.txt"


def ros2_static_tf(result: Result, names: ExportNames) -> tuple[str, str, str]:
    """A ROS 2 Python launch file running ``tf2_ros static_transform_publisher`` with the
    hand-eye as T_parent_child (translation in m, unit quaternion x, y, z, w with w >= 0)."""
    X, setup = _hand_eye(result), result.setup
    parent, child = names.frames(setup)
    q = Rotation.from_matrix(X[:3, :3]).as_quat(canonical=True)
    values = dict(zip(("x", "y", "z", "qx", "qy", "qz", "qw"), (*X[:3, 3], *q), strict=True))
    args = [f'"--{k}", "{num(v)}",' for k, v in values.items()]
    args += [f'"--frame-id", "{parent}",', f'"--child-frame-id", "{child}",']
    lines = "\n".join(f"                {a}" for a in args)
    node = f"{names.camera_name}_static_tf"
    note = "".join(f"{line}\n" for line in robot_map_note(result))
    text = f'''"""cellcal hand-eye ({setup}): {FRAMES[setup][0]} as the static transform
{parent} -> {child} (metres; quaternion x, y, z, w).

{child}: OpenCV / ROS optical frame, x right, y down, z along the optical axis.
{note}Run it with: ros2 launch ./{node}.launch.py
"""

from launch import LaunchDescription
from launch_ros.actions import Node


def generate_launch_description():
    return LaunchDescription([
        Node(
            package="tf2_ros",
            executable="static_transform_publisher",
            name="{node}",
            arguments=[
{lines}
            ],
        ),
    ])
'''
    return text, "text/x-python", f"{node}.launch.py"

