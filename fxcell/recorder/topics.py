"""Topic names, schema names and encodings of fxcell's MCAP logs: the one place for them.

Replay, the daemon and Foxglove layouts refer to topics through these constants.
Well-known Foxglove schema names are used verbatim so Foxglove recognises them.
"""

from __future__ import annotations

from typing import Final

# ----------------------------------------------------------------- topics
FILE_SUFFIX: Final = ".mcap"
"""Every fxcell log file ends in this."""

COMMANDS: Final = "/fxcell/commands"
"""Every API call, once when it starts and once when it ends (JSON)."""
TRANSITIONS: Final = "/fxcell/transitions"
"""Robot-mode state-machine transitions (JSON)."""
ROBOT_STATE: Final = "/robot/state"
"""Every 500 Hz RTDE sample, nothing decimated (protobuf ``fxcell.RobotState``)."""
ROBOT_MODES: Final = "/robot/modes"
"""A message whenever robot mode, safety mode, runtime state or status bits change (JSON)."""
MOTION: Final = "/motion"
"""Planned paths, trajectories, tracking reports and results of moves (JSON)."""
IO: Final = "/robot/io"
"""The controller's digital and analog IO, whenever a digital bit changes (JSON)."""
GRIPPER: Final = "/gripper"
"""The gripper after every command and change: width, object held, fault (JSON)."""
JOB: Final = "/job"
"""Fusion-machine job events: steps started and ended, sample locations (JSON)."""
TF: Final = "/tf"
"""``foxglove.FrameTransforms`` of the robot links, for the 3D panel (JSON)."""
LOG: Final = "/log"
"""``foxglove.Log`` records (JSON)."""
ROBOT_DESCRIPTION: Final = "/robot_description"
"""The robot's URDF as a string message, published once per file (JSON)."""
CAMERA_PLACEMENT: Final = "/camera/placement"
"""Each placement check's annotated frame (``foxglove.CompressedImage``, JPEG, JSON)."""
CAMERA_PLACEMENT_ANNOTATIONS: Final = "/camera/placement/annotations"
"""The check's verdicts drawn over that image (``foxglove.ImageAnnotations``, JSON)."""
CAMERA_PLACEMENT_VERDICT: Final = "/camera/placement/verdict"
"""The check's verdict: ok, reason, each position's verdict and measures (JSON)."""
RECORDER: Final = "/fxcell/recorder"
"""The recorder's own notices: drops, disk errors, file rotation (JSON)."""

ALL_TOPICS: Final = (
    COMMANDS,
    TRANSITIONS,
    ROBOT_STATE,
    ROBOT_MODES,
    MOTION,
    IO,
    GRIPPER,
    JOB,
    TF,
    LOG,
    ROBOT_DESCRIPTION,
    CAMERA_PLACEMENT,
    CAMERA_PLACEMENT_ANNOTATIONS,
    CAMERA_PLACEMENT_VERDICT,
    RECORDER,
)
EVENT_TOPICS: Final = (
    COMMANDS,
    TRANSITIONS,
    ROBOT_MODES,
    IO,
    GRIPPER,
    JOB,
    CAMERA_PLACEMENT_VERDICT,
    LOG,
    RECORDER,
)
"""The low-rate topics a timeline lists."""

# ----------------------------------------------------------------- schema names
SCHEMA_COMMAND: Final = "fxcell.Command"
SCHEMA_TRANSITION: Final = "fxcell.Transition"
SCHEMA_ROBOT_STATE: Final = "fxcell.RobotState"
SCHEMA_ROBOT_MODES: Final = "fxcell.RobotModes"
SCHEMA_MOTION: Final = "fxcell.Motion"
SCHEMA_IO: Final = "fxcell.IO"
SCHEMA_GRIPPER: Final = "fxcell.Gripper"
SCHEMA_JOB: Final = "fxcell.JobEvent"
SCHEMA_RECORDER: Final = "fxcell.RecorderNotice"
SCHEMA_STRING: Final = "fxcell.String"
SCHEMA_FRAME_TRANSFORMS: Final = "foxglove.FrameTransforms"
SCHEMA_LOG: Final = "foxglove.Log"
SCHEMA_COMPRESSED_IMAGE: Final = "foxglove.CompressedImage"
SCHEMA_IMAGE_ANNOTATIONS: Final = "foxglove.ImageAnnotations"
SCHEMA_PLACEMENT: Final = "fxcell.PlacementCheck"

# ----------------------------------------------------------------- encodings
JSON: Final = "json"
JSONSCHEMA: Final = "jsonschema"
PROTOBUF: Final = "protobuf"

# ----------------------------------------------------------------- metadata, attachments
METADATA_NAME: Final = "fxcell"
"""Name of the MCAP metadata record: fxcell version, config snapshot, controller, serial."""
RECOVERY_METADATA_NAME: Final = "fxcell.recovery"
URDF_SUFFIX: Final = ".urdf"
"""The robot's URDF is attached to every file as ``<robot kind>.urdf``."""
URDF_ATTACHMENT: Final = "ur3e" + URDF_SUFFIX
"""The UR3e's URDF attachment."""
URDF_MEDIA_TYPE: Final = "application/xml"
