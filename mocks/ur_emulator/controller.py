"""The emulated controller's state: joints and pose, motions with a trapezoidal profile, the
control script's register handshake, safety and the injected faults."""


from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from calib import matrix_from_ur_pose, ur_pose_from_matrix
from mocks import ur_kinematics as kin
from mocks.ur_emulator.safety import SafetyBox
from mocks.ur_emulator.wire import (
    CMD_MOVEJ,
    CMD_MOVEJ_IK,
    CMD_MOVEL,
    CMD_MOVEL_FK,
    CMD_NONE,
    CMD_STOP_SCRIPT,
    FAULT_NAMES,
    REGISTER_FIELD,
    ROBOT_MODE_RUNNING,
    ROBOT_STATUS_POWER_ON,
    ROBOT_STATUS_PROGRAM_RUNNING,
    RUNTIME_PLAYING,
    RUNTIME_STOPPED,
    SAFETY_EMERGENCY_STOP,
    SAFETY_MODE_NORMAL,
    SAFETY_MODE_PROTECTIVE_STOP,
    SAFETY_MODE_ROBOT_ESTOP,
    SAFETY_NORMAL,
    SAFETY_PROTECTIVE_STOP,
    SCRIPT_DONE,
    SCRIPT_READY,
    TICK,
    TIMED_FAULTS,
)


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

    ``path(s)`` gives (joints (6,), pose (6,)) at path fraction ``s`` in [0, 1]; ``pose_at(s)``
    the pose alone, without moving the IK seed (for the safety box).
    """

    distance: float
    speed: float
    acceleration: float
    path: Callable[[float], tuple[np.ndarray, np.ndarray]]
    pose_at: Callable[[float], np.ndarray]


class Controller:
    """Robot state and the native twin of the ``rtde_control`` script; thread-safe."""

    def __init__(self, *, instant: bool, settle_time: float, faults: Faults,
                 on_drop: Callable[[float], None], box: SafetyBox | None = None) -> None:
        self.lock = threading.RLock()
        self.box = box
        self.box_stops: list[str] = []  # why each move the safety box refused was refused
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
        m = REGISTER_FIELD.match(name)
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
                "box_stops": self.box_stops,
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
        if motion is not None and self.box is not None and (
                why := self.box.refuses(motion.pose_at)) is not None:
            with self.lock:
                self.box_stops.append(why)
                self._safety_stop("protective")
            return
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

            return Motion(distance, speed, accel, joint_path, lambda s: joint_path(s)[1])
        if cmd in (CMD_MOVEL, CMD_MOVEL_FK):
            q_goal = target if cmd == CMD_MOVEL_FK else None
            pose1 = kin.fk_pose(target) if cmd == CMD_MOVEL_FK else target
            T0, T1 = matrix_from_ur_pose(pose0), matrix_from_ur_pose(pose1)
            slerp = Slerp([0.0, 1.0], Rotation.from_matrix([T0[:3, :3], T1[:3, :3]]))
            lin = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
            ang = float(np.linalg.norm((slerp(1.0) * slerp(0.0).inv()).as_rotvec()))
            distance = lin if lin > 1e-6 else ang
            seed = [q0]

            def line_pose(s: float) -> np.ndarray:
                T = np.eye(4)
                T[:3, :3] = slerp(s).as_matrix()
                T[:3, 3] = T0[:3, 3] + s * (T1[:3, 3] - T0[:3, 3])
                return ur_pose_from_matrix(T)

            def line_path(s: float) -> tuple[np.ndarray, np.ndarray]:
                pose = line_pose(s)
                if s >= 1.0 and q_goal is not None:
                    return q_goal.copy(), pose1.copy()
                q = kin.ik(pose, seed[0], iterations=20)
                if q is not None:
                    seed[0] = q
                return seed[0].copy(), pose

            return Motion(distance, speed, accel, line_path, line_pose)
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


