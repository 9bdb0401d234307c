"""UR e-series controller protocol facts shared by the robot link and the simulator.

The bottom layer of fxcell: ports, robot/safety/runtime modes as RTDE reports them,
status bits, the ur_rtde control-script command ids, and one sample of the RTDE
state stream. Nothing here talks to a socket.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

DASHBOARD_PORT = 29999
RTDE_PORT = 30004
SCRIPT_PORT = 30003  # real-time client interface: ur_rtde uploads its control script here
SECONDARY_PORT = 30002
URCAP_SCRIPT_PORT = 50002  # PC side: the ExternalControl URCap requests the script here

CONTROL_PERIOD = 0.002  # e-series controller cycle, 500 Hz

AT_REST_SPEED = 0.01
"""rad/s: an arm whose every joint is slower than this is at rest (well above the encoder
noise of a standing arm); the cell takes new moves only then."""


class RobotMode(enum.IntEnum):
    """``robot_mode`` as RTDE reports it (the dashboard uses the names)."""

    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7
    UPDATING_FIRMWARE = 8


class SafetyMode(enum.IntEnum):
    """``safety_mode`` as RTDE reports it."""

    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9
    VALIDATE_JOINT_ID = 10
    UNDEFINED_SAFETY_MODE = 11
    AUTOMATIC_MODE_SAFEGUARD_STOP = 12
    SYSTEM_THREE_POSITION_ENABLING_STOP = 13


SAFETY_STOPS: dict[int, str] = {
    SafetyMode.PROTECTIVE_STOP: "protective_stop",
    SafetyMode.SAFEGUARD_STOP: "safeguard_stop",
    SafetyMode.AUTOMATIC_MODE_SAFEGUARD_STOP: "safeguard_stop",
    SafetyMode.SYSTEM_THREE_POSITION_ENABLING_STOP: "safeguard_stop",
    SafetyMode.SYSTEM_EMERGENCY_STOP: "emergency_stop",
    SafetyMode.ROBOT_EMERGENCY_STOP: "emergency_stop",
    SafetyMode.VIOLATION: "fault",
    SafetyMode.FAULT: "fault",
}
"""The safety modes in which the arm is stopped, and which kind of stop each is: the one
table the link process (why a trajectory ends), the state machine (the cell's state, named
the same) and the errors of aborted moves derive from."""


class RuntimeState(enum.IntEnum):
    """``runtime_state``: the state of the controller's program."""

    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


class ProgramState(enum.StrEnum):
    """Program state as the dashboard's ``programState`` names it."""

    STOPPED = "STOPPED"
    PLAYING = "PLAYING"
    PAUSED = "PAUSED"


class RobotStatusBits(enum.IntFlag):
    POWER_ON = 1 << 0
    PROGRAM_RUNNING = 1 << 1
    TEACH_BUTTON_PRESSED = 1 << 2
    POWER_BUTTON_PRESSED = 1 << 3


class SafetyStatusBits(enum.IntFlag):
    NORMAL_MODE = 1 << 0
    REDUCED_MODE = 1 << 1
    PROTECTIVE_STOPPED = 1 << 2
    RECOVERY_MODE = 1 << 3
    SAFEGUARD_STOPPED = 1 << 4
    SYSTEM_EMERGENCY_STOPPED = 1 << 5
    ROBOT_EMERGENCY_STOPPED = 1 << 6
    EMERGENCY_STOPPED = 1 << 7
    VIOLATION = 1 << 8
    FAULT = 1 << 9
    STOPPED_DUE_TO_SAFETY = 1 << 10


class ControlCommand(enum.IntEnum):
    """Command ids of ur_rtde's control script (``input_int_register_0``)."""

    NO_CMD = 0
    MOVEJ = 1
    MOVEJ_IK = 2
    MOVEL = 3
    MOVEL_FK = 4
    FORCE_MODE = 6
    FORCE_MODE_STOP = 7
    ZERO_FT_SENSOR = 8
    SPEEDJ = 9
    SPEEDL = 10
    SERVOJ = 11
    SERVOC = 12
    SPEED_STOP = 15
    SERVO_STOP = 16
    SET_PAYLOAD = 17
    TEACH_MODE = 18
    END_TEACH_MODE = 19
    SERVOL = 24
    SET_TCP = 29
    GET_IK_ARGS = 30
    PROTECTIVE_STOP = 31
    STOPL = 33
    STOPJ = 34
    SET_WATCHDOG = 35
    POSE_TRANS = 39
    FK_DEFAULT = 43
    FK_ARGS = 44
    MOVE_PATH = 45
    GET_IK_DEFAULT = 46
    IS_STEADY = 47
    STOP_SCRIPT = 255


class ControlStatus(enum.IntEnum):
    """``output_int_register_0`` as written by the control script."""

    IDLE = 0
    READY = 1
    DONE = 2


@dataclass(slots=True)
class RobotState:
    """One sample of the controller's 500 Hz state stream (SI units, UR base frame).

    Joint vectors are 6-tuples in radians (rad/s, rad/s², A); poses are
    ``(x, y, z, rx, ry, rz)`` with a rotation vector, as on the teach pendant.
    """

    timestamp: float = 0.0  # controller time since boot, s
    robot_mode: RobotMode = RobotMode.DISCONNECTED
    safety_mode: SafetyMode = SafetyMode.NORMAL
    runtime_state: RuntimeState = RuntimeState.STOPPED
    robot_status_bits: int = 0
    safety_status_bits: int = 0
    target_q: tuple[float, ...] = (0.0,) * 6
    target_qd: tuple[float, ...] = (0.0,) * 6
    target_qdd: tuple[float, ...] = (0.0,) * 6
    actual_q: tuple[float, ...] = (0.0,) * 6
    actual_qd: tuple[float, ...] = (0.0,) * 6
    actual_current: tuple[float, ...] = (0.0,) * 6
    target_tcp_pose: tuple[float, ...] = (0.0,) * 6
    actual_tcp_pose: tuple[float, ...] = (0.0,) * 6
    actual_tcp_speed: tuple[float, ...] = (0.0,) * 6
    speed_scaling: float = 1.0
    output_int_registers: tuple[int, ...] = field(default=(0, 0, 0))
    digital_input_bits: int = 0  # standard 0-7, configurable 8-15, tool 16-17
    digital_output_bits: int = 0  # same layout
    standard_analog_input0: float = 0.0  # V or A, as the input is configured
    standard_analog_input1: float = 0.0
    standard_analog_output0: float = 0.0
    standard_analog_output1: float = 0.0
    received_at: float = 0.0  # host monotonic time the sample reached fxcell, s


RTDE_STATE_OUTPUTS: tuple[tuple[str, str], ...] = (
    ("timestamp", "timestamp"),
    ("robot_mode", "robot_mode"),
    ("safety_mode", "safety_mode"),
    ("runtime_state", "runtime_state"),
    ("robot_status_bits", "robot_status_bits"),
    ("safety_status_bits", "safety_status_bits"),
    ("target_q", "target_q"),
    ("target_qd", "target_qd"),
    ("target_qdd", "target_qdd"),
    ("actual_q", "actual_q"),
    ("actual_qd", "actual_qd"),
    ("actual_current", "actual_current"),
    ("target_tcp_pose", "target_TCP_pose"),
    ("actual_tcp_pose", "actual_TCP_pose"),
    ("actual_tcp_speed", "actual_TCP_speed"),
    ("speed_scaling", "speed_scaling"),
    ("digital_input_bits", "actual_digital_input_bits"),
    ("digital_output_bits", "actual_digital_output_bits"),
    ("standard_analog_input0", "standard_analog_input0"),
    ("standard_analog_input1", "standard_analog_input1"),
    ("standard_analog_output0", "standard_analog_output0"),
    ("standard_analog_output1", "standard_analog_output1"),
)
"""The :class:`RobotState` fields read from RTDE, with the output each comes from: the one
list the link's reader subscribes to. ``output_int_registers`` come from the control
script's registers and ``received_at`` from the host."""
