"""An emulated Universal Robots e-Series controller that the real ``ur-rtde`` client talks to.

Tests run the unmodified ``rtde_control`` / ``rtde_receive`` client (PyPI ur-rtde 1.6.5) against
this process over loopback, so the UR driver is exercised on the wire, not through a Python
stand-in. The wire behaviour it reproduces is written down in ``/work/shared/docs/ur-rtde-wire.md``.

Run it as its own process (the client's constructors hold the GIL while they block)::

    python -m mocks.ur_emulator --host 127.0.0.2 [--instant] [--fault NAME[=VALUE] ...]

``--host auto`` serves on the first loopback address from 127.0.0.2 whose ports are free and
prints it as the first line on stdout; the ports stay bound until the process exits, so test
sessions running side by side never share an address.

It serves, on that one address, the dashboard (29999), the script port (30003, where the client
uploads its ``def rtde_control(): ... end`` program) and RTDE (30004). Instead of interpreting
URScript it runs a native twin of that program's main loop: the register handshake on
``output_int_register_<offset>`` (1 ready, 2 done) and the commands MOVEJ, MOVEJ_IK, MOVEL,
MOVEL_FK and STOP_SCRIPT; other commands are acknowledged and ignored.

Robot model: a UR5e (``mocks.ur_kinematics``), TCP = flange. moveJ interpolates joints and the
TCP pose follows by forward kinematics. moveL interpolates the pose along a straight line (slerp
for the rotation) and sets it directly; the joints follow by numerical IK seeded with the previous
joints, and are held where IK has no solution. Motions take the time of a trapezoidal velocity
profile from speed and acceleration, or no time with ``--instant``; after a timed motion the
reported TCP speed decays for ``--settle-time`` seconds, like a real arm ringing out.

Faults (``--fault`` at start, or at run time over the dashboard as
``emulator fault NAME[=VALUE]``; ``emulator clear`` removes them all and resets safety):

- ``protective_stop_during_move``: the next move stops half way; safety bit 2, program stopped.
- ``emergency_stop_during_move``: the same with an emergency stop (safety bit 7).
- ``program_never_starts``: uploaded programs never reach PLAYING.
- ``drop_during_move[=SECONDS]``: the next move closes every connection and resets new ones
  for SECONDS (default 1). ``emulator drop [SECONDS]`` does the same at once.
- ``slow_replies=SECONDS``: every RTDE and dashboard reply is delayed.
- ``local_control``: ``is in remote control`` answers ``false``.
- ``program_status_lag=SECONDS``: ``robot_status_bits`` shows a started program running only
  SECONDS later (``runtime_state`` at once), like a receive stream that lags the control one.

The dashboard commands ``unlock protective stop`` and ``close safety popup`` clear a protective
stop as on a real controller. ``emulator state`` answers one JSON line (process id, joints,
pose, runtime state, safety bits, faults).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import os
import re
import selectors
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from calib import matrix_from_ur_pose, ur_pose_from_matrix
from mocks import ur_kinematics as kin

DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003
RTDE_PORT = 30004

#: Controller version reported on RTDE ``v`` and dashboard ``PolyscopeVersion`` (e-Series 5.11).
CONTROLLER_VERSION = (5, 11, 1, 108318)

# RTDE message types (ASCII letters).
RTDE_VERSION, RTDE_CONTROLLER_VERSION = ord("V"), ord("v")
RTDE_DATA, RTDE_SETUP_OUTPUTS, RTDE_SETUP_INPUTS = ord("U"), ord("O"), ord("I")
RTDE_START, RTDE_PAUSE = ord("S"), ord("P")

#: struct codes of the RTDE types; the client decodes with this same table.
TYPE_FORMATS = {
    "VECTOR6D": "6d", "VECTOR3D": "3d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I",
    "DOUBLE": "d", "UINT64": "Q", "UINT32": "I", "INT32": "i", "BOOL": "?", "UINT8": "B",
}

_V6 = "VECTOR6D"
#: RTDE field names (outputs and inputs) with their real types, from the UR RTDE guide.
FIELD_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE", "target_q": _V6, "target_qd": _V6, "target_qdd": _V6,
    "target_current": _V6, "target_moment": _V6, "actual_q": _V6, "actual_qd": _V6,
    "actual_current": _V6, "actual_current_window": _V6, "actual_current_as_torque": _V6,
    "joint_control_output": _V6, "actual_TCP_pose": _V6, "actual_TCP_speed": _V6,
    "actual_TCP_force": _V6, "target_TCP_pose": _V6, "target_TCP_speed": _V6,
    "actual_digital_input_bits": "UINT64", "joint_temperatures": _V6,
    "actual_execution_time": "DOUBLE", "robot_mode": "INT32", "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32", "safety_status": "INT32", "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE",
    "actual_robot_current": "DOUBLE", "actual_joint_voltage": _V6,
    "actual_digital_output_bits": "UINT64", "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D", "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32", "analog_io_types": "UINT32",
    "standard_analog_input0": "DOUBLE", "standard_analog_input1": "DOUBLE",
    "standard_analog_output0": "DOUBLE", "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE", "euromap67_input_bits": "UINT32", "euromap67_output_bits": "UINT32",
    "euromap67_24V_voltage": "DOUBLE", "euromap67_24V_current": "DOUBLE",
    "tool_mode": "UINT32", "tool_analog_input_types": "UINT32", "tool_analog_input0": "DOUBLE",
    "tool_analog_input1": "DOUBLE", "tool_output_voltage": "INT32",
    "tool_output_current": "DOUBLE", "tool_temperature": "DOUBLE", "tcp_force_scalar": "DOUBLE",
    "output_bit_registers0_to_31": "UINT32", "output_bit_registers32_to_63": "UINT32",
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "tool_output_mode": "UINT8", "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8", "payload": "DOUBLE", "payload_cog": "VECTOR3D",
    "payload_inertia": _V6, "script_control_line": "UINT32", "ft_raw_wrench": _V6,
    "joint_position_deviation_ratio": "DOUBLE", "collision_detection_ratio": "DOUBLE",
    "time_scale_source": "UINT32",
    # Inputs (written by the client).
    "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
    "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
    "external_force_torque": _V6,
}
_REGISTER = re.compile(r"^(input|output)_(int|double|bit)_register_(\d+)$")
_REGISTER_TYPES = {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}

# Runtime states, robot modes and status bits as the controller reports them.
RUNTIME_STOPPED, RUNTIME_PLAYING = 1, 2
ROBOT_MODE_RUNNING = 7
SAFETY_MODE_NORMAL, SAFETY_MODE_PROTECTIVE_STOP, SAFETY_MODE_ROBOT_ESTOP = 1, 3, 7
ROBOT_STATUS_POWER_ON, ROBOT_STATUS_PROGRAM_RUNNING = 1 << 0, 1 << 1
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP, SAFETY_EMERGENCY_STOP = 1 << 0, 1 << 2, 1 << 7

# Commands of the control script's register protocol.
CMD_NONE, CMD_MOVEJ, CMD_MOVEJ_IK, CMD_MOVEL, CMD_MOVEL_FK = 0, 1, 2, 3, 4
CMD_STOP_SCRIPT = 255
SCRIPT_READY, SCRIPT_DONE = 1, 2

TICK = 0.008  # 125 Hz: motion update period and maximum RTDE stream rate
MIN_STREAM_PERIOD = TICK
#: Last octets of the loopback addresses ``--host auto`` tries, in order (127.0.0.200 and up
#: stay free for tests that need an address where nothing listens).
AUTO_HOSTS = range(2, 200)
FAULT_NAMES = ("protective_stop_during_move", "emergency_stop_during_move",
               "program_never_starts", "drop_during_move", "slow_replies", "local_control",
               "program_status_lag")
#: Faults whose value is a time in seconds (default 1).
TIMED_FAULTS = ("drop_during_move", "slow_replies", "program_status_lag")


def field_type(name: str) -> str | None:
    """The real RTDE type name of field ``name``, or None if the controller has no such field."""
    if name in FIELD_TYPES:
        return FIELD_TYPES[name]
    m = _REGISTER.match(name)
    if m and int(m.group(3)) < (128 if m.group(2) == "bit" else 48):
        if m.group(2) == "bit" and int(m.group(3)) < 64:
            return None
        return _REGISTER_TYPES[m.group(2)]
    return None


def trapezoid_profile(distance: float, speed: float,
                      acceleration: float) -> tuple[float, float, float]:
    """(duration, time spent accelerating, peak speed) of a rest-to-rest trapezoidal move."""
    speed, acceleration = max(speed, 1e-6), max(acceleration, 1e-6)
    if distance <= speed * speed / acceleration:  # triangle: never reaches ``speed``
        t_acc = float(np.sqrt(distance / acceleration))
        return 2.0 * t_acc, t_acc, acceleration * t_acc
    t_acc = speed / acceleration
    return distance / speed + t_acc, t_acc, speed


def trapezoid_fraction(t: float, distance: float, speed: float, acceleration: float) -> float:
    """Fraction in [0, 1] of the path covered ``t`` seconds into a trapezoidal move."""
    duration, t_acc, v_peak = trapezoid_profile(distance, speed, acceleration)
    if distance <= 0.0 or t >= duration:
        return 1.0
    a = v_peak / t_acc if t_acc > 0.0 else 0.0
    if t < t_acc:
        covered = 0.5 * a * t * t
    elif t < duration - t_acc:
        covered = 0.5 * a * t_acc * t_acc + v_peak * (t - t_acc)
    else:
        covered = distance - 0.5 * a * (duration - t) ** 2
    return float(np.clip(covered / distance, 0.0, 1.0))


@dataclass
class Faults:
    """Injected faults; one-shot ones are consumed by the move they affect."""

    protective_stop_during_move: bool = False
    emergency_stop_during_move: bool = False
    program_never_starts: bool = False
    drop_during_move: float = 0.0
    slow_replies: float = 0.0
    local_control: bool = False
    program_status_lag: float = 0.0

    def set(self, spec: str) -> None:
        """Apply ``NAME`` or ``NAME=VALUE``; raise ValueError for an unknown name or value."""
        name, _, value = spec.partition("=")
        name = name.strip()
        if name not in FAULT_NAMES:
            raise ValueError(f"unknown fault {name!r}; known: {', '.join(FAULT_NAMES)}")
        if name in TIMED_FAULTS:
            setattr(self, name, float(value) if value else 1.0)
        else:
            setattr(self, name, True)


@dataclass
class Motion:
    """One motion: path length (m or rad), speed and acceleration limits, and the path itself.

    ``path(s)`` gives (joints (6,), pose (6,)) at path fraction ``s`` in [0, 1].
    """

    distance: float
    speed: float
    acceleration: float
    path: Callable[[float], tuple[np.ndarray, np.ndarray]]


class Controller:
    """Robot state and the native twin of the ``rtde_control`` script; thread-safe."""

    def __init__(self, *, instant: bool, settle_time: float, faults: Faults,
                 on_drop: Callable[[float], None]) -> None:
        self.lock = threading.RLock()
        self.instant = instant
        self.settle_time = settle_time
        self.faults = faults
        self._on_drop = on_drop  # closes every connection for the given seconds
        self.t0 = time.monotonic()
        self.q = kin.HOME_Q.copy()
        self.pose = kin.fk_pose(self.q)
        self.qd = np.zeros(6)
        self.tcp_speed = np.zeros(6)
        self.runtime_state = RUNTIME_STOPPED
        self.safety_mode = SAFETY_MODE_NORMAL
        self.safety_bits = SAFETY_NORMAL
        self.inputs: dict[str, float | int | bool] = {}
        self.out_int: dict[int, int] = {}
        self.out_double: dict[int, float] = {}
        self.reg_offset = 0
        self._program_id = 0  # incremented on every start/stop: stale twin loops exit
        self._program_started = 0.0  # monotonic time the running program started
        self._ring: tuple[float, np.ndarray] | None = None  # (start, speed) after a motion

    # ---- values streamed to RTDE clients -------------------------------------------------

    def value(self, name: str) -> object:
        """Current value of output field ``name`` (caller holds the lock)."""
        m = _REGISTER.match(name)
        if m:
            kind, idx = m.group(2), int(m.group(3))
            if m.group(1) == "input":
                return self.inputs.get(name, 0)
            if kind == "int":
                return self.out_int.get(idx, 0)
            if kind == "double":
                return self.out_double.get(idx, 0.0)
            return False
        running = self.runtime_state == RUNTIME_PLAYING
        shown_running = running and (time.monotonic() - self._program_started
                                     >= self.faults.program_status_lag)
        special = {
            "timestamp": time.monotonic() - self.t0,
            "actual_q": self.q, "target_q": self.q, "actual_qd": self.qd, "target_qd": self.qd,
            "actual_TCP_pose": self.pose, "target_TCP_pose": self.pose,
            "actual_TCP_speed": self._reported_speed(), "target_TCP_speed": self.tcp_speed,
            "robot_mode": ROBOT_MODE_RUNNING, "safety_mode": self.safety_mode,
            "safety_status": self.safety_mode, "runtime_state": self.runtime_state,
            "robot_status_bits": ROBOT_STATUS_POWER_ON
            | (ROBOT_STATUS_PROGRAM_RUNNING if shown_running else 0),
            "safety_status_bits": self.safety_bits, "speed_scaling": 1.0,
            "target_speed_fraction": 1.0, "actual_main_voltage": 48.0,
            "actual_robot_voltage": 48.0, "joint_temperatures": np.full(6, 30.0),
            "joint_mode": [253] * 6, "actual_tool_accelerometer": [0.0, 0.0, 9.81],
        }
        return special.get(name)  # None: a field the emulator does not model, sent as zeros

    def _reported_speed(self) -> np.ndarray:
        """TCP speed, including the decaying ring-out after a timed motion."""
        if self._ring is None:
            return self.tcp_speed
        age = time.monotonic() - self._ring[0]
        if age >= self.settle_time:
            self._ring = None
            return self.tcp_speed
        return self._ring[1] * np.exp(-5.0 * age / max(self.settle_time, 1e-6))

    def set_input(self, name: str, value: object) -> None:
        with self.lock:
            self.inputs[name] = value

    def state_json(self) -> str:
        with self.lock:
            return json.dumps({
                "pid": os.getpid(), "q": self.q.tolist(), "pose": self.pose.tolist(),
                "runtime_state": self.runtime_state, "safety_status_bits": self.safety_bits,
                "reg_offset": self.reg_offset, "faults": self.faults.__dict__,
            })

    # ---- program lifecycle -----------------------------------------------------------------

    def start_program(self, reg_offset: int) -> None:
        """A complete control script arrived: start the twin (unless the fault forbids it)."""
        with self.lock:
            self._program_id += 1
            if self.faults.program_never_starts:
                return
            if self.safety_bits != SAFETY_NORMAL:
                return  # a stopped robot does not start programs
            self.reg_offset = reg_offset
            self.runtime_state = RUNTIME_PLAYING
            self._program_started = time.monotonic()
            self.out_int[reg_offset] = SCRIPT_READY
            program_id = self._program_id
        threading.Thread(target=self._twin_loop, args=(program_id,), daemon=True).start()

    def stop_program(self) -> None:
        """Dashboard ``stop`` or STOP_SCRIPT: the program ends, any motion halts at once."""
        with self.lock:
            self._program_id += 1
            self.runtime_state = RUNTIME_STOPPED
            self.out_int[self.reg_offset] = 0
            self.qd[:] = 0.0
            self.tcp_speed[:] = 0.0

    def unlock(self) -> bool:
        """Clear a protective stop; False if an emergency stop still holds the robot."""
        with self.lock:
            if self.safety_bits & SAFETY_EMERGENCY_STOP:
                return False
            self.safety_bits = SAFETY_NORMAL
            self.safety_mode = SAFETY_MODE_NORMAL
            return True

    def reset(self) -> None:
        """``emulator clear``: no faults, normal safety, robot kept where it is."""
        with self.lock:
            self.faults.__init__()
            self.safety_bits = SAFETY_NORMAL
            self.safety_mode = SAFETY_MODE_NORMAL

    def _alive(self, program_id: int) -> bool:
        return self._program_id == program_id and self.runtime_state == RUNTIME_PLAYING

    def _twin_loop(self, program_id: int) -> None:
        """Native twin of the script's main loop: ready -> execute -> done -> wait for clear."""
        while True:
            with self.lock:
                if not self._alive(program_id):
                    return
                off = self.reg_offset
                cmd = int(self.inputs.get(f"input_int_register_{off}", 0))
                state = self.out_int.get(off, 0)
                if cmd == CMD_NONE and state != SCRIPT_READY:
                    self.out_int[off] = SCRIPT_READY
                    state = SCRIPT_READY
            if cmd != CMD_NONE and state == SCRIPT_READY:
                self._execute(cmd, off, program_id)
            time.sleep(0.002)

    def _execute(self, cmd: int, off: int, program_id: int) -> None:
        """Run one command; a motion blocks (sync) or runs in the background (async)."""
        with self.lock:
            target = np.array([float(self.inputs.get(f"input_double_register_{off + i}", 0.0))
                               for i in range(6)])
            speed = float(self.inputs.get(f"input_double_register_{off + 6}", 0.0))
            accel = float(self.inputs.get(f"input_double_register_{off + 7}", 0.0))
            is_async = int(self.inputs.get(f"input_int_register_{off + 1}", 0)) == 1
        if cmd == CMD_STOP_SCRIPT:
            self.stop_program()
            return
        motion = self._plan(cmd, target, speed, accel)
        if motion is None:
            with self.lock:
                if self._alive(program_id):
                    self.out_int[off] = SCRIPT_DONE
            return
        if is_async:
            with self.lock:
                self.out_int[off] = SCRIPT_DONE
                self.out_int[off + 2] = 0
            threading.Thread(target=self._run_motion, args=(motion, off, program_id),
                             daemon=True).start()
            return
        if self._run_motion(motion, off, program_id):
            with self.lock:
                if self._alive(program_id):
                    self.out_int[off] = SCRIPT_DONE

    def _plan(self, cmd: int, target: np.ndarray, speed: float, accel: float) -> Motion | None:
        """A Motion for a move command, or None for commands the twin only acknowledges."""
        with self.lock:
            q0, pose0 = self.q.copy(), self.pose.copy()
        if cmd in (CMD_MOVEJ, CMD_MOVEJ_IK):
            q1 = target if cmd == CMD_MOVEJ else kin.ik(target, q0)
            if q1 is None:
                return None  # unreachable: the real script would fail; here the move is skipped
            distance = float(np.abs(q1 - q0).max())

            def joint_path(s: float) -> tuple[np.ndarray, np.ndarray]:
                q = q0 + s * (q1 - q0)
                return q, kin.fk_pose(q)

            return Motion(distance, speed, accel, joint_path)
        if cmd in (CMD_MOVEL, CMD_MOVEL_FK):
            q_goal = target if cmd == CMD_MOVEL_FK else None
            pose1 = kin.fk_pose(target) if cmd == CMD_MOVEL_FK else target
            T0, T1 = matrix_from_ur_pose(pose0), matrix_from_ur_pose(pose1)
            slerp = Slerp([0.0, 1.0], Rotation.from_matrix([T0[:3, :3], T1[:3, :3]]))
            lin = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
            ang = float(np.linalg.norm((slerp(1.0) * slerp(0.0).inv()).as_rotvec()))
            distance = lin if lin > 1e-6 else ang
            seed = [q0]

            def line_path(s: float) -> tuple[np.ndarray, np.ndarray]:
                T = np.eye(4)
                T[:3, :3] = slerp(s).as_matrix()
                T[:3, 3] = T0[:3, 3] + s * (T1[:3, 3] - T0[:3, 3])
                pose = ur_pose_from_matrix(T)
                if s >= 1.0 and q_goal is not None:
                    return q_goal.copy(), pose1.copy()
                q = kin.ik(pose, seed[0], iterations=20)
                if q is not None:
                    seed[0] = q
                return seed[0].copy(), pose

            return Motion(distance, speed, accel, line_path)
        return None

    def _run_motion(self, motion: Motion, off: int, program_id: int) -> bool:
        """Play a motion tick by tick; False if it was interrupted (stop, fault, drop)."""
        timed = not self.instant
        with self.lock:
            faults = self.faults
            stop_kind = ("protective" if faults.protective_stop_during_move else
                         "emergency" if faults.emergency_stop_during_move else None)
            drop_for = faults.drop_during_move
            faults.protective_stop_during_move = False
            faults.emergency_stop_during_move = False
            faults.drop_during_move = 0.0
        start = time.monotonic()
        prev_pose, prev_q, prev_t = None, None, start
        while True:
            t = time.monotonic() - start
            s = (trapezoid_fraction(t, motion.distance, motion.speed, motion.acceleration)
                 if timed else 1.0)
            if (stop_kind or drop_for) and s >= 0.5:
                s = 0.5
            q, pose = motion.path(s)
            with self.lock:
                if not self._alive(program_id):
                    return False
                dt = max(t - (prev_t - start), 1e-6)
                if prev_pose is not None and timed:
                    self.tcp_speed = np.concatenate([
                        (pose[:3] - prev_pose[:3]) / dt,
                        (Rotation.from_rotvec(pose[3:])
                         * Rotation.from_rotvec(prev_pose[3:]).inv()).as_rotvec() / dt])
                    self.qd = (q - prev_q) / dt
                self.q, self.pose = q, pose
                if s >= 0.5 and stop_kind:
                    self._safety_stop(stop_kind)
                    return False
                if s >= 0.5 and drop_for:
                    self.qd[:] = 0.0
                    self.tcp_speed[:] = 0.0
                if s >= 1.0:
                    if timed and self.settle_time > 0.0:
                        self._ring = (time.monotonic(), 0.02 * self.tcp_speed)
                    self.qd[:] = 0.0
                    self.tcp_speed[:] = 0.0
                    self.out_int[off + 2] = -1
                    return True
            if s >= 0.5 and drop_for:
                self._on_drop(drop_for)
                return False
            prev_pose, prev_q, prev_t = pose, q, start + t
            time.sleep(TICK)

    def _safety_stop(self, kind: str) -> None:
        """Stop the arm and the program as a protective or emergency stop does (lock held)."""
        if kind == "protective":
            self.safety_bits, self.safety_mode = SAFETY_PROTECTIVE_STOP, SAFETY_MODE_PROTECTIVE_STOP
        else:
            self.safety_bits, self.safety_mode = SAFETY_EMERGENCY_STOP, SAFETY_MODE_ROBOT_ESTOP
        self.stop_program()


class RtdeSession:
    """One RTDE client connection: recipes, requests and the output stream."""

    def __init__(self, sock: socket.socket, ctrl: Controller) -> None:
        self.sock = sock
        self.ctrl = ctrl
        self.send_lock = threading.Lock()
        self.output: tuple[int, list[str], list[str], float] | None = None
        self.inputs: dict[int, tuple[list[str], list[str]]] = {}
        self.next_input_id = 1
        self.next_output_id = 1
        self.streaming = threading.Event()
        self.closed = threading.Event()

    def _send(self, msg_type: int, payload: bytes = b"") -> None:
        with self.send_lock:
            self.sock.sendall(struct.pack(">HB", len(payload) + 3, msg_type) + payload)

    def _recv_exact(self, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("client closed")
            buf += chunk
        return buf

    def serve(self) -> None:
        """Answer requests until the client leaves or the connection is dropped."""
        threading.Thread(target=self._stream, daemon=True).start()
        try:
            while True:
                size, msg_type = struct.unpack(">HB", self._recv_exact(3))
                payload = self._recv_exact(size - 3) if size > 3 else b""
                self._handle(msg_type, payload)
        except (OSError, ConnectionError, struct.error):
            pass
        finally:
            self.closed.set()
            self.streaming.clear()

    def _handle(self, msg_type: int, payload: bytes) -> None:
        if msg_type == RTDE_DATA:
            self._accept_data(payload)
            return
        delay = self.ctrl.faults.slow_replies
        if delay > 0.0:
            time.sleep(delay)
        if msg_type == RTDE_VERSION:
            self._send(RTDE_VERSION, b"\x01")
        elif msg_type == RTDE_CONTROLLER_VERSION:
            self._send(RTDE_CONTROLLER_VERSION, struct.pack(">IIII", *CONTROLLER_VERSION))
        elif msg_type == RTDE_SETUP_OUTPUTS:
            (frequency,) = struct.unpack(">d", payload[:8])
            names = [n for n in payload[8:].decode().split(",") if n]
            types = self._types(names)
            rid = self.next_output_id
            self.next_output_id += 1
            self.output = (rid, names, types, frequency)
            self._send(RTDE_SETUP_OUTPUTS, bytes([rid]) + ",".join(types).encode())
        elif msg_type == RTDE_SETUP_INPUTS:
            names = [n for n in payload.decode().split(",") if n]
            types = self._types(names)
            rid = self.next_input_id
            self.next_input_id += 1
            self.inputs[rid] = (names, types)
            self._send(RTDE_SETUP_INPUTS, bytes([rid]) + ",".join(types).encode())
        elif msg_type == RTDE_START:
            self._send(RTDE_START, b"\x01")
            self.streaming.set()
        elif msg_type == RTDE_PAUSE:
            self.streaming.clear()
            self._send(RTDE_PAUSE, b"\x01")
        # Unknown requests get no reply: never an unsolicited M message.

    @staticmethod
    def _types(names: list[str]) -> list[str]:
        """RTDE types for a recipe; unknown names become NOT_FOUND (logged, the client throws)."""
        types = [field_type(n) or "NOT_FOUND" for n in names]
        for name, rtype in zip(names, types, strict=True):
            if rtype == "NOT_FOUND":
                print(f"ur_emulator: unknown RTDE field {name!r}", file=sys.stderr, flush=True)
        return types

    def _accept_data(self, payload: bytes) -> None:
        """A data package from the client: write its values into the controller's inputs."""
        recipe = self.inputs.get(payload[0]) if payload else None
        if recipe is None:
            return
        names, types = recipe
        if "NOT_FOUND" in types:
            return
        fmt = ">" + "".join(TYPE_FORMATS[t] for t in types)
        try:
            values = struct.unpack(fmt, payload[1:1 + struct.calcsize(fmt)])
        except struct.error:
            return
        i = 0
        for name, rtype in zip(names, types, strict=True):
            width = int(TYPE_FORMATS[rtype][0]) if TYPE_FORMATS[rtype][0].isdigit() else 1
            value = values[i] if width == 1 else list(values[i:i + width])
            i += width
            self.ctrl.set_input(name, value)

    def _stream(self) -> None:
        """Send U packages for the output recipe while started, at most 125 Hz."""
        while not self.closed.is_set():
            if not self.streaming.wait(0.05) or self.output is None:
                continue
            rid, names, types, frequency = self.output
            period = max(1.0 / max(frequency, 1.0), MIN_STREAM_PERIOD)
            packed = bytearray([rid])
            with self.ctrl.lock:
                for name, rtype in zip(names, types, strict=True):
                    packed += _pack(rtype, self.ctrl.value(name))
            try:
                self._send(RTDE_DATA, bytes(packed))
            except OSError:
                return
            time.sleep(period)


def _bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on (host, port)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((host, port))
        s.listen(16)
    except OSError:
        s.close()
        raise
    return s


def _pack(rtype: str, value: object) -> bytes:
    """Big-endian bytes of ``value`` as RTDE type ``rtype``; None packs as zeros."""
    fmt = TYPE_FORMATS.get(rtype)
    if fmt is None:
        return b""
    count = int(fmt[0]) if fmt[0].isdigit() else 1
    values = [0] * count if value is None else list(np.ravel(value))
    convert = {"d": float, "?": bool}.get(fmt[-1], int)
    return struct.pack(">" + fmt, *[convert(v) for v in values])


class Emulator:
    """The three servers on one address, connection tracking and the drop fault."""

    def __init__(self, host: str, *, instant: bool, settle_time: float, faults: Faults) -> None:
        self.host = host
        self.ctrl = Controller(instant=instant, settle_time=settle_time, faults=faults,
                               on_drop=self.drop)
        self._conns: set[socket.socket] = set()
        self._conns_lock = threading.Lock()
        self._refuse_until = 0.0
        self._listeners: dict[int, socket.socket] = {}

    # ---- connections ----------------------------------------------------------------------

    def _listen(self) -> None:
        """Bind the three ports on ``self.host``, or on the first free 127.0.0.N for ``auto``.

        The ports are held until the process exits (a drop resets connections instead of
        releasing them), so no other emulator can take this address while this one lives.
        """
        candidates = ([f"127.0.0.{n}" for n in AUTO_HOSTS] if self.host == "auto"
                      else [self.host])
        for host in candidates:
            try:
                self._listeners = {port: _bind(host, port)
                                   for port in (DASHBOARD_PORT, SCRIPT_PORT, RTDE_PORT)}
            except OSError as err:
                self._unlisten()
                if len(candidates) == 1:
                    raise
                if err.errno not in (errno.EADDRINUSE, errno.EADDRNOTAVAIL):
                    raise
                continue
            self.host = host
            return
        raise OSError(errno.EADDRINUSE, "every address in 127.0.0.2..199 is taken")

    def _unlisten(self) -> None:
        for s in self._listeners.values():
            s.close()
        self._listeners.clear()

    def drop(self, seconds: float) -> None:
        """Close every connection and reset new ones for ``seconds``, like a cable pulled."""
        self._refuse_until = time.monotonic() + seconds
        with self._conns_lock:
            conns, self._conns = list(self._conns), set()
        for c in conns:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)
            c.close()

    def serve_forever(self) -> None:
        """Accept on all three ports; each connection gets its own thread.

        The first line on stdout names the address served (``ur_emulator listening on HOST
        ports ...``): with ``--host auto`` that is how the caller learns it.
        """
        handlers = {DASHBOARD_PORT: self._dashboard, SCRIPT_PORT: self._script,
                    RTDE_PORT: self._rtde}
        self._listen()
        print(f"ur_emulator listening on {self.host} ports 29999 30003 30004", flush=True)
        sel = selectors.DefaultSelector()
        for port, s in self._listeners.items():
            sel.register(s, selectors.EVENT_READ, port)
        while True:
            for key, _ in sel.select(timeout=0.05):
                try:
                    conn, _ = key.fileobj.accept()
                except OSError:
                    continue
                if time.monotonic() < self._refuse_until:  # dropped: reset at once
                    conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER,
                                    struct.pack("ii", 1, 0))
                    conn.close()
                    continue
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                with self._conns_lock:
                    self._conns.add(conn)
                threading.Thread(target=self._run, args=(handlers[key.data], conn),
                                 daemon=True).start()

    def _run(self, handler: Callable[[socket.socket], None], conn: socket.socket) -> None:
        try:
            handler(conn)
        except OSError:
            pass
        finally:
            with self._conns_lock:
                self._conns.discard(conn)
            conn.close()

    def _rtde(self, conn: socket.socket) -> None:
        RtdeSession(conn, self.ctrl).serve()

    def _script(self, conn: socket.socket) -> None:
        """Collect uploaded text; a complete ``def rtde_control(): ... end`` starts the twin."""
        buf = ""
        while True:
            chunk = conn.recv(65536)
            if not chunk:
                return
            buf += chunk.decode(errors="replace")
            start = buf.find("def rtde_control():")
            if start < 0:
                continue
            end = re.search(r"^end[ \t]*$", buf[start:], re.MULTILINE)
            if end is None:
                continue
            program = buf[start:start + end.end()]
            buf = buf[start + end.end():]
            m = re.search(r"global\s+reg_offset_int\s*=\s*(\d+)", program)
            self.ctrl.start_program(int(m.group(1)) if m else 0)

    def _dashboard(self, conn: socket.socket) -> None:
        conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
        reader = conn.makefile("r", encoding="utf-8", newline="\n")
        for line in reader:
            command = line.strip()
            reply = self._dashboard_reply(command)
            delay = self.ctrl.faults.slow_replies
            if delay > 0.0:
                time.sleep(delay)
            conn.sendall((reply + "\n").encode())
            if command.startswith("emulator drop"):
                parts = command.split()
                self.drop(float(parts[2]) if len(parts) > 2 else 1.0)
                return

    def _dashboard_reply(self, command: str) -> str:
        """The text a UR dashboard server answers to ``command`` (plus emulator controls)."""
        ctrl = self.ctrl
        version = ".".join(str(v) for v in CONTROLLER_VERSION)
        running = ctrl.runtime_state == RUNTIME_PLAYING
        simple = {
            "PolyscopeVersion": f"URSoftware {version} (Jan 01 2023)",
            "get serial number": "20205500001",
            "get robot model": "UR5",
            "is in remote control": "false" if ctrl.faults.local_control else "true",
            "robotmode": f"Robotmode: {'RUNNING'}",
            "safetymode": "Safetymode: " + ("NORMAL" if ctrl.safety_bits == SAFETY_NORMAL else
                                            "PROTECTIVE_STOP"
                                            if ctrl.safety_bits & SAFETY_PROTECTIVE_STOP else
                                            "ROBOT_EMERGENCY_STOP"),
            "safetystatus": "Safetystatus: " + ("NORMAL" if ctrl.safety_bits == SAFETY_NORMAL
                                                else "PROTECTIVE_STOP"),
            "running": f"Program running: {str(running).lower()}",
            "programState": ("PLAYING" if running else "STOPPED") + " <unnamed>",
            "power on": "Powering on", "brake release": "Brake releasing",
            "emulator state": ctrl.state_json(),
        }
        if command in simple:
            return simple[command]
        if command == "stop":
            ctrl.stop_program()
            return "Stopped"
        if command == "play":
            return "Starting program"
        if command == "unlock protective stop":
            return "Protective stop releasing" if ctrl.unlock() else \
                "Failed to unlock protective stop"
        if command == "close safety popup":
            return "closing safety popup"
        if command == "emulator clear":
            ctrl.reset()
            return "emulator: faults cleared"
        if command.startswith("emulator fault "):
            try:
                with ctrl.lock:
                    ctrl.faults.set(command[len("emulator fault "):])
            except ValueError as err:
                return f"emulator: {err}"
            return f"emulator: fault set: {command[len('emulator fault '):]}"
        if command.startswith("emulator drop"):
            return "emulator: dropping all connections"
        return f"could not understand: '{command}'"


def main(argv: list[str] | None = None) -> None:
    """Command line entry: parse options, start the servers, serve until killed."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--host", default="127.0.0.2",
                        help="loopback address to serve on (not 127.0.0.1, so the client runs its "
                             "remote-control check), or 'auto' for the first free one")
    parser.add_argument("--instant", action="store_true", help="motions take no time")
    parser.add_argument("--settle-time", type=float, default=0.15,
                        help="seconds the reported TCP speed rings out after a timed motion")
    parser.add_argument("--fault", action="append", default=[], metavar="NAME[=VALUE]",
                        help=f"inject a fault at start; one of {', '.join(FAULT_NAMES)}")
    args = parser.parse_args(argv)
    faults = Faults()
    for spec in args.fault:
        try:
            faults.set(spec)
        except ValueError as err:
            parser.error(str(err))
    emulator = Emulator(args.host, instant=args.instant, settle_time=args.settle_time,
                        faults=faults)
    try:
        emulator.serve_forever()
    except OSError as err:  # typically: the address is taken by another emulator
        sys.exit(f"ur_emulator: cannot serve on {args.host}: {err.strerror or err}")
    except KeyboardInterrupt:
        return


if __name__ == "__main__":
    main()
