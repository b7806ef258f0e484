"""``cellcal robot|camera|devices`` commands: thin commands over ``drivers.registry``.

Devices are addressed by URL (``ur://HOST``, ``v4l2:///dev/videoN``, ``file:///path``,
``mock://``). Failures raise ``DeviceError`` / ``ValueError``; ``service.cli.main`` prints them
on one line and exits non-zero. ``devices check`` reports every device and exits 1 if any fails.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from collections.abc import Callable, Mapping

import cv2
import numpy as np

from calib import MIN_CONTRAST, check_ur_pose
from drivers.base import Camera, Robot
from drivers.errors import DeviceError
from drivers.registry import (
    CAMERA_URLS,
    ROBOT_URLS,
    companion_robot,
    open_camera,
    open_robot,
)
from service.cli.exit_codes import EXIT_FAILED

_URLS_HELP = (f"Device addresses: {ROBOT_URLS} for robots; {CAMERA_URLS} for cameras. "
              "mock:// simulates the cell of --scene "
              "(default: the built-in demo cell).")


def register(subparsers: argparse._SubParsersAction, help_lines: Mapping[str, str]) -> None:
    """Add the ``robot``, ``camera`` and ``devices`` commands to the ``cellcal`` parser, with
    their ``help_lines`` in ``cellcal --help``."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--scene", metavar="SCENE_JSON",
                        help="mock scene file for mock:// devices (default: built-in cell)")

    robot = subparsers.add_parser("robot", help=help_lines["robot"], description=_URLS_HELP)
    robot_sub = robot.add_subparsers(dest="robot_command", required=True, metavar="ACTION")
    pose = robot_sub.add_parser(
        "pose", parents=[common], help="print the TCP pose as JSON",
        description="Print the actual TCP pose, T_base_tcp as [x, y, z, rx, ry, rz] in metres "
                    "and radians (rotation vector, the UR convention). " + _URLS_HELP)
    pose.add_argument("--robot", required=True, metavar="URL", help=ROBOT_URLS)
    pose.set_defaults(func=_robot_pose)

    move = robot_sub.add_parser(
        "move", parents=[common], help="move the TCP in a straight line",
        description="Move the TCP in a straight line (moveL) to a pose, wait until it is at "
                    "rest and print the reached pose as JSON. " + _URLS_HELP)
    move.add_argument("--robot", required=True, metavar="URL", help=ROBOT_URLS)
    move.add_argument("--pose", required=True, metavar="X,Y,Z,RX,RY,RZ",
                      help="target T_base_tcp in metres and radians (rotation vector); "
                           "write --pose=-0.1,... when it starts with a minus sign")
    move.add_argument("--speed", type=float, default=0.1, help="m/s (default 0.1)")
    move.add_argument("--acceleration", type=float, default=0.5, help="m/s^2 (default 0.5)")
    move.add_argument("--settle-timeout", type=float, default=10.0,
                      help="seconds to wait for the robot to come to rest (default 10)")
    move.set_defaults(func=_robot_move)

    camera = subparsers.add_parser("camera", help=help_lines["camera"], description=_URLS_HELP)
    camera_sub = camera.add_subparsers(dest="camera_command", required=True, metavar="ACTION")
    grab = camera_sub.add_parser(
        "grab", parents=[common], help="save one fresh frame",
        description="Grab one frame taken after the command started and save it (the format "
                    "follows the file name: .png is lossless). A mock:// camera sees the mock "
                    "cell from the mock robot's start pose. " + _URLS_HELP)
    grab.add_argument("--camera", required=True, metavar="URL", help=CAMERA_URLS)
    grab.add_argument("--out", required=True, metavar="IMAGE", help="output image, e.g. a.png")
    grab.add_argument("--timeout", type=float, default=5.0,
                      help="seconds to wait for a frame (default 5)")
    grab.set_defaults(func=_camera_grab)

    devices = subparsers.add_parser("devices", help=help_lines["devices"],
                                    description=_URLS_HELP)
    devices_sub = devices.add_subparsers(dest="devices_command", required=True,
                                         metavar="ACTION")
    check = devices_sub.add_parser(
        "check", parents=[common], help="connect, read the pose, grab a frame",
        description="Connect to each device given, read the robot's pose and state, grab a "
                    "camera frame, and print one status line per device. Exits 1 if any "
                    "device fails. A mock:// camera needs a mock:// robot. " + _URLS_HELP)
    check.add_argument("--robot", metavar="URL", help=ROBOT_URLS)
    check.add_argument("--camera", metavar="URL", help=CAMERA_URLS)
    check.set_defaults(func=_devices_check)


def _parse_pose(text: str) -> np.ndarray:
    """``x,y,z,rx,ry,rz`` -> shape (6,), validated (finite, metres)."""
    try:
        pose = np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise ValueError(f"--pose {text!r}: expected six numbers x,y,z,rx,ry,rz") from None
    if pose.shape != (6,):
        raise ValueError(f"--pose {text!r}: expected six numbers x,y,z,rx,ry,rz, "
                         f"got {pose.size}")
    check_ur_pose(pose, "--pose")
    return pose


def _pose_json(pose: np.ndarray) -> str:
    return json.dumps({"tcp_pose": [round(float(v), 9) for v in pose]})


def _quiet_opencv() -> None:
    """Keep OpenCV's own warnings (e.g. the end of an image sequence) off the terminal."""
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


def _robot_pose(args: argparse.Namespace) -> int:
    with contextlib.closing(open_robot(args.robot, config=args.scene)) as robot:
        print(_pose_json(robot.tcp_pose()))
    return 0


def _robot_move(args: argparse.Namespace) -> int:
    target = _parse_pose(args.pose)
    if args.speed <= 0 or args.acceleration <= 0:
        raise ValueError("--speed and --acceleration must be positive")
    with contextlib.closing(open_robot(args.robot, config=args.scene)) as robot:
        robot.move_linear(target, speed=args.speed, acceleration=args.acceleration)
        robot.wait_settled(timeout=args.settle_timeout)
        print(_pose_json(robot.tcp_pose()))
    return 0


def _camera_grab(args: argparse.Namespace) -> int:
    _quiet_opencv()
    if not cv2.haveImageWriter(args.out):
        raise ValueError(f"--out {args.out}: unknown image format; use .png, .jpg, .bmp or .tif")
    with contextlib.ExitStack() as stack:
        robot = None
        if (companion := companion_robot(args.camera)) is not None:
            robot = stack.enter_context(contextlib.closing(
                open_robot(companion, config=args.scene)))
        camera = stack.enter_context(contextlib.closing(open_camera(args.camera, robot=robot)))
        frame = camera.grab(timeout=args.timeout)
    if not cv2.imwrite(args.out, frame):
        raise OSError(f"could not write {args.out}")
    kind = "grey" if frame.ndim == 2 else "colour"
    print(f"wrote {args.out} ({frame.shape[1]}x{frame.shape[0]} {kind})", file=sys.stderr)
    return 0


def _devices_check(args: argparse.Namespace) -> int:
    if args.robot is None and args.camera is None:
        raise ValueError("devices check: give --robot URL and/or --camera URL")
    _quiet_opencv()
    failed = False
    with contextlib.ExitStack() as stack:
        robot: Robot | None = None
        if args.robot is not None:
            def check_robot() -> str:
                nonlocal robot
                robot = stack.enter_context(contextlib.closing(open_robot(args.robot,
                                                                          config=args.scene)))
                return _describe_robot(robot)

            failed |= not _report("robot", args.robot, check_robot)
        if args.camera is not None:
            def check_camera() -> str:
                companion = companion_robot(args.camera)
                if companion is not None and robot is None:
                    raise ValueError(f"a {args.camera} camera needs a working {companion} "
                                     f"robot (--robot {companion})")
                camera = stack.enter_context(contextlib.closing(
                    open_camera(args.camera, robot=robot, config=args.scene)))
                return _describe_camera(camera)

            failed |= not _report("camera", args.camera, check_camera)
    return EXIT_FAILED if failed else 0


def _report(kind: str, url: str, check: Callable[[], str]) -> bool:
    """Run one device check and print its status line; True if it passed."""
    try:
        detail = check()
    except (DeviceError, ValueError, OSError) as exc:
        print(f"{kind:<6}  {url}  FAILED  {exc}")
        return False
    print(f"{kind:<6}  {url}  ok  {detail}")
    return True


def _describe_robot(robot: Robot) -> str:
    pose = robot.tcp_pose()
    st = robot.status()
    x, y, z = (pose[:3] * 1e3).round(1)
    state = ("protective stop" if st.protective_stop else
             "emergency stop" if st.emergency_stop else st.mode)
    angle = np.rad2deg(np.linalg.norm(pose[3:]))
    return (f"TCP at x={x:g} y={y:g} z={z:g} mm, rotation {angle:.1f} deg; state: {state}"
            f"{'' if st.ready else ' (not ready to move)'}")


def _describe_camera(camera: Camera) -> str:
    frame = camera.grab(timeout=5.0)
    kind = "grey" if frame.ndim == 2 else "colour"
    lo, hi = np.percentile(frame, [1, 99])
    return (f"{frame.shape[1]}x{frame.shape[0]} {kind} frame, grey levels {lo:.0f}..{hi:.0f}"
            f"{' (blank: lens cap or lighting?)' if hi - lo < MIN_CONTRAST else ''}")
