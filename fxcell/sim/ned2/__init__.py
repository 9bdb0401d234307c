"""The embedded Niryo Ned2 simulator: the robot's TCP server (port 40001) as pyniryo
1.2.5 uses it, its rosbridge WebSocket (port 9090) with the topics and services Niryo's
ROS clients (pyniryo2) read and call, an arm moving at Niryo's planning limits,
calibration, learning mode, collision detection, a Gripper 1 with objects, digital/analog
IO, and fault injection on the simulator's control port (29990, the UR simulator's line
protocol).

``python -m fxcell.sim.ned2`` or ``fxcell sim --robot ned2``. Runtime code never imports
this package.
"""

from fxcell.link.ned2 import ROSBRIDGE_PORT
from fxcell.link.ned2 import TCP_PORT as NED2_PORT

__all__ = ["CONTROL_PORT", "FAULTS", "NED2_PORT", "PORTS", "ROSBRIDGE_PORT"]

CONTROL_PORT = 29990
PORTS = (NED2_PORT, ROSBRIDGE_PORT, CONTROL_PORT)
FAULTS = (
    "collision",  # the arm detects a collision: a running move stops and fails
    "stop",  # a running move stops (as the rosbridge's stop_command service does)
    "drop_connection",  # the TCP server drops its client
    "stall",  # SECONDS: the TCP server answers nothing for that long
    "power_loss",  # the robot goes dark: connections close, nobody answers, calibration lost
    "power_restore",  # the robot boots again (needs calibration)
    "motor_error",  # [JOINT]: a motor reports a hardware error; moves are refused
    "clear_motor_error",
    "gripper_drop",  # the held object slips out of the fingers
    "tool_disconnect",  # the tool goes away (GET_CURRENT_TOOL_ID says NONE)
    "tool_connect",
    "uncalibrate",  # the robot needs calibration again
)
