"""The embedded Niryo Ned2 simulator: the robot's TCP server (port 40001) as pyniryo
1.2.5 uses it, its rosbridge WebSocket (port 9090) with the topics and services Niryo's
ROS clients (pyniryo2) read and call, an arm moving at Niryo's planning limits,
calibration, learning mode, collision detection, a Gripper 1 with objects, digital/analog
IO, and fault injection on the simulator's control port (29990, the UR simulator's line
protocol).

``python -m fxcell.sim.ned2`` or ``fxcell sim --robot ned2``; the Cell starts it through
:mod:`fxcell.link.ned2.embedded` when a Ned2 cell has no host (its ports and faults are
written there, in :mod:`fxcell.link.ned2`). Runtime code never imports this package.
"""

from fxcell.link.ned2 import ROSBRIDGE_PORT
from fxcell.link.ned2 import SIMULATOR_CONTROL_PORT as CONTROL_PORT
from fxcell.link.ned2 import SIMULATOR_FAULTS as FAULTS
from fxcell.link.ned2 import SIMULATOR_PORTS as PORTS
from fxcell.link.ned2 import TCP_PORT as NED2_PORT

__all__ = ["CONTROL_PORT", "FAULTS", "NED2_PORT", "PORTS", "ROSBRIDGE_PORT"]
