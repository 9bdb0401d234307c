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

The clients are asyncio, with typed errors (:mod:`fxcell.errors`); none knows the
Cell. Facts about the interfaces: ``docs/guides/ned2.md``.
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
