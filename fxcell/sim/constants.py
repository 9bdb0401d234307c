"""The simulated controller's constants: delays, the PolyScope it presents, register counts.

They sit below the controller and the protocol modules (Dashboard, RTDE, primary, URScript),
which all read them, so none of those needs to import the controller for a number.
"""

from __future__ import annotations

import datetime

# Real-controller delays in seconds, before time scaling.
DELAYS = {
    "boot": 2.0,
    "power_on": 2.0,  # POWER_ON -> IDLE
    "brake_release": 1.5,  # IDLE -> RUNNING
    "program_start": 0.3,  # compile and start a program or an uploaded script
    "restart_safety": 1.5,
}
UNLOCK_DELAY = 5.0  # protective stop: unlock refused until this long after the stop

# The PolyScope the simulator presents, the same everywhere: Dashboard ``PolyscopeVersion``
# and ``version``, the primary/secondary version message, RTDE's controller version. The
# RTDE outputs are those of this version's RTDE guide (``actual_current_as_torque`` and the
# other fields of the 5.2x releases included). Its build number and date are the
# simulator's own.
POLYSCOPE_VERSION = (5, 25, 1, 1)
POLYSCOPE_BUILD_DATE = datetime.datetime(2025, 9, 3)
SERIAL_NUMBER = "20235500001"
ROBOT_MODEL = "UR3"

REGISTER_COUNT = 48

__all__ = [
    "DELAYS",
    "POLYSCOPE_BUILD_DATE",
    "POLYSCOPE_VERSION",
    "REGISTER_COUNT",
    "ROBOT_MODEL",
    "SERIAL_NUMBER",
    "UNLOCK_DELAY",
]
