"""The Niryo Ned2's network interfaces as the Ned2 driver speaks them.

- :mod:`~fxcell.link.ned2.tcp`: the robot's TCP server (port 40001, the protocol of Niryo's
  pyniryo client): one command at a time, each answered once it has finished, so a move
  holds the connection until the arm arrives.
- :mod:`~fxcell.link.ned2.rosbridge`: the robot's rosbridge WebSocket (port 9090): topics
  streamed while a move runs (joint states, hardware status, learning mode, collision
  detection, the IO panel's pins) and services that reach a running move
  (``stop_command``) or set an output (``set_digital_io``).
- :mod:`~fxcell.link.ned2.gripper`: Gripper 1 as ``cell.gripper`` drives it, through the
  TCP server's tool commands.

Both are asyncio clients with typed errors (:mod:`fxcell.errors`); neither knows the
Cell. Facts about the interfaces: ``docs/guides/ned2.md``. The embedded simulator's
launcher (:mod:`~fxcell.link.ned2.embedded`) and its ports and faults are here too: the
runtime starts it by module name, never importing :mod:`fxcell.sim`.
"""

TCP_PORT = 40001
"""The robot's TCP server (pyniryo's protocol)."""
ROSBRIDGE_PORT = 9090
"""The robot's rosbridge WebSocket."""
JOINT_NAMES = tuple(f"joint_{i}" for i in range(1, 7))
"""The arm's joints as ``/joint_states`` and trajectories name them."""
ARM_ACTION = "/niryo_robot_arm_commander/robot_action"
"""The arm commander's action server (moves, trajectories)."""
MOVE_ACTION = "niryo_robot_arm_commander/RobotMoveAction"
"""Its action type."""
EXECUTE_FULL_TRAJ = 11
"""``ArmMoveCommand.cmd_type`` of a timed ``trajectory_msgs/JointTrajectory``."""
PENDING, ACTIVE, PREEMPTED, SUCCEEDED, ABORTED, REJECTED = 0, 1, 2, 3, 4, 5
"""``actionlib_msgs/GoalStatus`` values."""

SIMULATOR_CONTROL_PORT = 29990
"""The embedded simulator's control port (fault injection, state; the UR simulator's line
protocol)."""
SIMULATOR_PORTS = (TCP_PORT, ROSBRIDGE_PORT, SIMULATOR_CONTROL_PORT)
"""Every port the embedded Ned2 simulator serves on its address."""
SIMULATOR_FAULTS = (
    "collision",  # the arm detects a collision: a running move stops and fails
    "stop",  # a running move stops (as the rosbridge's stop_command service does)
    "drop_connection",  # the network drops: the TCP server's and the rosbridge's clients
    "stall",  # SECONDS: the robot answers nothing and publishes nothing for that long
    "power_loss",  # the robot goes dark: connections close, nobody answers, calibration lost
    "power_restore",  # the robot boots again (needs calibration)
    "motor_error",  # [JOINT]: a motor reports a hardware error; moves are refused
    "clear_motor_error",
    "gripper_drop",  # the held object slips out of the fingers
    "tool_disconnect",  # the tool goes away (GET_CURRENT_TOOL_ID says NONE)
    "tool_connect",
    "uncalibrate",  # the robot needs calibration again
    # the simulated fusion machine's (a simulator started with --machine)
    "machine_error",  # the machine faults: a running cycle aborts, error until machine_reset
    "machine_reset",
    "door_open",  # the machine's door opens: error, not ready; a running cycle aborts
    "door_close",
)
"""The faults the embedded simulator injects (``fxcell sim inject --robot ned2``)."""
