"""What the emulated controller shows on the wire: its ports and version, the RTDE message
types and field types, runtime states, safety bits and the control script's commands."""


from __future__ import annotations

import re

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
REGISTER_FIELD = re.compile(r"^(input|output)_(int|double|bit)_register_(\d+)$")
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
    m = REGISTER_FIELD.match(name)
    if m and int(m.group(3)) < (128 if m.group(2) == "bit" else 48):
        if m.group(2) == "bit" and int(m.group(3)) < 64:
            return None
        return _REGISTER_TYPES[m.group(2)]
    return None

