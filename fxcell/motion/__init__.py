"""The motion layer: kinematics, robot and collision model, planning, trajectories, moves.

| module | concept |
|---|---|
| ``kinematics`` | UR3e DH forward and closed-form inverse kinematics (numpy only) |
| ``robot_model`` | the same arm as a Pinocchio model |
| ``collision`` | coal collision geometry of robot, gripper and scene |
| ``planning`` | collision-free joint paths (OMPL) and Cartesian straight lines |
| ``trajectory`` | jerk-limited time parameterisation (Ruckig) and braking |
| ``execution`` | how a kind's link takes a streamed plan (light: no numpy) |
| ``moves`` | a move from target to executed trajectory: plan, stream, stop |

Nothing is imported here, so that light users (the simulator imports ``kinematics``) do
not load Pinocchio, coal or OMPL.
"""
