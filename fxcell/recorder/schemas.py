"""Schemas of every topic, and the JSON encoding of the low-rate messages.

Low-rate topics are JSON with a JSON Schema (draft 2020-12) so that Foxglove and
any JSON tool read them; ``foxglove.FrameTransforms`` and ``foxglove.Log`` follow
Foxglove's published JSON schemas (timestamps as ``{sec, nsec}``). The 500 Hz
robot state is protobuf (:mod:`fxcell.recorder.protobuf`).
"""

from __future__ import annotations

import json
from typing import Any, Final

from fxcell.recorder import topics
from fxcell.recorder.protobuf import robot_state_schema

_DRAFT: Final = "https://json-schema.org/draft/2020-12/schema"


def _object(title: str, properties: dict[str, Any], required: list[str]) -> dict[str, Any]:
    return {
        "$schema": _DRAFT,
        "title": title,
        "type": "object",
        "properties": properties,
        "required": required,
    }


_TIMESTAMP: Final = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
    "required": ["sec", "nsec"],
}
_STR: Final = {"type": "string"}
_NUM: Final = {"type": "number"}
_OPT_NUM: Final = {"type": ["number", "null"]}
_OPT_STR: Final = {"type": ["string", "null"]}

COMMAND_SCHEMA: Final = _object(
    topics.SCHEMA_COMMAND,
    {
        "command_id": {"type": "integer"},
        "name": _STR,
        "args": {"type": "object"},
        "origin": {"enum": ["library", "daemon", "replay", "internal"]},
        "phase": {"enum": ["start", "end"]},
        "started": _NUM,
        "ended": _OPT_NUM,
        "outcome": {"enum": ["started", "ok", "error"]},
        "error_type": _OPT_STR,
        "error_message": _OPT_STR,
        "result": {},
    },
    ["command_id", "name", "args", "origin", "phase", "started", "outcome"],
)

TRANSITION_SCHEMA: Final = _object(
    topics.SCHEMA_TRANSITION,
    {
        "time": _NUM,
        "source": _STR,
        "dest": _STR,
        "trigger": _STR,
        "cause": {"enum": ["command", "observed"]},
        "detail": _STR,
    },
    ["time", "source", "dest", "trigger", "cause"],
)

ROBOT_MODES_SCHEMA: Final = _object(
    topics.SCHEMA_ROBOT_MODES,
    {
        "controller_time": _NUM,
        "robot_mode": _STR,
        "safety_mode": _STR,
        "runtime_state": _STR,
        "robot_status_bits": {"type": "integer"},
        "safety_status_bits": {"type": "integer"},
    },
    ["robot_mode", "safety_mode", "runtime_state"],
)

MOTION_SCHEMA: Final = _object(
    topics.SCHEMA_MOTION,
    {
        "time": _NUM,
        "move_id": {"type": "integer"},
        "kind": {"enum": ["path", "trajectory", "tracking", "result"]},
        "data": {"type": "object"},
    },
    ["time", "move_id", "kind", "data"],
)

IO_SCHEMA: Final = _object(
    topics.SCHEMA_IO,
    {
        "controller_time": _NUM,
        "digital_input_bits": {"type": "integer"},
        "digital_output_bits": {"type": "integer"},
        "analog_inputs": {"type": "array", "items": _NUM},
        "analog_outputs": {"type": "array", "items": _NUM},
    },
    ["digital_input_bits", "digital_output_bits"],
)

GRIPPER_SCHEMA: Final = _object(
    topics.SCHEMA_GRIPPER,
    {"time": _NUM, "width": _NUM, "holding": {"type": "boolean"}, "held": {}, "event": _STR},
    ["time", "event"],
)

JOB_SCHEMA: Final = _object(topics.SCHEMA_JOB, {"time": _NUM, "event": _STR}, ["time", "event"])

RECORDER_SCHEMA: Final = _object(
    topics.SCHEMA_RECORDER,
    {
        "level": {"enum": ["info", "warning", "error"]},
        "message": _STR,
        "dropped": {"type": "integer"},
        "written": {"type": "integer"},
    },
    ["level", "message"],
)

STRING_SCHEMA: Final = _object(topics.SCHEMA_STRING, {"data": _STR}, ["data"])

_VECTOR3: Final = {
    "type": "object",
    "properties": {"x": _NUM, "y": _NUM, "z": _NUM},
    "required": ["x", "y", "z"],
}
_QUATERNION: Final = {
    "type": "object",
    "properties": {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM},
    "required": ["x", "y", "z", "w"],
}
FRAME_TRANSFORMS_SCHEMA: Final = _object(
    topics.SCHEMA_FRAME_TRANSFORMS,
    {
        "transforms": {
            "type": "array",
            "items": {
                "title": "foxglove.FrameTransform",
                "type": "object",
                "properties": {
                    "timestamp": _TIMESTAMP,
                    "parent_frame_id": _STR,
                    "child_frame_id": _STR,
                    "translation": _VECTOR3,
                    "rotation": _QUATERNION,
                },
                "required": [
                    "timestamp",
                    "parent_frame_id",
                    "child_frame_id",
                    "translation",
                    "rotation",
                ],
            },
        }
    },
    ["transforms"],
)

LOG_SCHEMA: Final = _object(
    topics.SCHEMA_LOG,
    {
        "timestamp": _TIMESTAMP,
        "level": {
            "title": "foxglove.LogLevel",
            "description": "0 unknown, 1 debug, 2 info, 3 warning, 4 error, 5 fatal",
            "type": "integer",
            "oneOf": [
                {"title": name, "const": value}
                for name, value in (
                    ("UNKNOWN", 0),
                    ("DEBUG", 1),
                    ("INFO", 2),
                    ("WARNING", 3),
                    ("ERROR", 4),
                    ("FATAL", 5),
                )
            ],
        },
        "message": _STR,
        "name": _STR,
        "file": _STR,
        "line": {"type": "integer", "minimum": 0},
    },
    ["timestamp", "level", "message", "name", "file", "line"],
)

_POINT2: Final = {
    "title": "foxglove.Point2",
    "type": "object",
    "properties": {"x": _NUM, "y": _NUM},
    "required": ["x", "y"],
}
_METADATA: Final = {
    "type": "array",
    "items": {
        "title": "foxglove.KeyValuePair",
        "type": "object",
        "properties": {"key": _STR, "value": _STR},
        "required": ["key", "value"],
    },
}
_COLOR: Final = {
    "title": "foxglove.Color",
    "type": "object",
    "properties": {"r": _NUM, "g": _NUM, "b": _NUM, "a": _NUM},
    "required": ["r", "g", "b", "a"],
}
COMPRESSED_IMAGE_SCHEMA: Final = _object(
    topics.SCHEMA_COMPRESSED_IMAGE,
    {
        "timestamp": _TIMESTAMP,
        "frame_id": _STR,
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": _STR,
    },
    ["timestamp", "frame_id", "data", "format"],
)
IMAGE_ANNOTATIONS_SCHEMA: Final = _object(
    topics.SCHEMA_IMAGE_ANNOTATIONS,
    {
        "timestamp": _TIMESTAMP,
        "metadata": _METADATA,
        "circles": {
            "type": "array",
            "items": {
                "title": "foxglove.CircleAnnotation",
                "type": "object",
                "properties": {
                    "timestamp": _TIMESTAMP,
                    "position": _POINT2,
                    "diameter": _NUM,
                    "thickness": _NUM,
                    "fill_color": _COLOR,
                    "outline_color": _COLOR,
                    "metadata": _METADATA,
                },
                "required": ["timestamp", "position", "diameter", "thickness"],
            },
        },
        "points": {"type": "array", "items": {"type": "object"}},
        "texts": {
            "type": "array",
            "items": {
                "title": "foxglove.TextAnnotation",
                "type": "object",
                "properties": {
                    "timestamp": _TIMESTAMP,
                    "position": _POINT2,
                    "text": _STR,
                    "font_size": _NUM,
                    "text_color": _COLOR,
                    "background_color": _COLOR,
                    "metadata": _METADATA,
                },
                "required": ["timestamp", "position", "text", "font_size"],
            },
        },
    },
    ["circles", "points", "texts"],
)
PLACEMENT_SCHEMA: Final = _object(
    topics.SCHEMA_PLACEMENT,
    {
        "time": _NUM,
        "ok": {"type": "boolean"},
        "reason": _STR,
        "positions": {"type": "array", "items": {"type": "object"}},
        "obstructions": {"type": "array", "items": {"type": "object"}},
        "holder_found": {"type": "boolean"},
    },
    ["time", "ok", "reason", "positions"],
)

# topic -> (schema name, schema encoding, schema data, message encoding)
SchemaSpec = tuple[str, str, bytes, str]


def _json_spec(schema: dict[str, Any]) -> SchemaSpec:
    return (schema["title"], topics.JSONSCHEMA, json.dumps(schema).encode(), topics.JSON)


def topic_schemas() -> dict[str, SchemaSpec]:
    """Schema of every topic the recorder writes."""
    return {
        topics.COMMANDS: _json_spec(COMMAND_SCHEMA),
        topics.TRANSITIONS: _json_spec(TRANSITION_SCHEMA),
        topics.ROBOT_STATE: (
            topics.SCHEMA_ROBOT_STATE,
            topics.PROTOBUF,
            robot_state_schema(),
            topics.PROTOBUF,
        ),
        topics.ROBOT_MODES: _json_spec(ROBOT_MODES_SCHEMA),
        topics.MOTION: _json_spec(MOTION_SCHEMA),
        topics.IO: _json_spec(IO_SCHEMA),
        topics.GRIPPER: _json_spec(GRIPPER_SCHEMA),
        topics.JOB: _json_spec(JOB_SCHEMA),
        topics.TF: _json_spec(FRAME_TRANSFORMS_SCHEMA),
        topics.LOG: _json_spec(LOG_SCHEMA),
        topics.ROBOT_DESCRIPTION: _json_spec(STRING_SCHEMA),
        topics.CAMERA_PLACEMENT: _json_spec(COMPRESSED_IMAGE_SCHEMA),
        topics.CAMERA_PLACEMENT_ANNOTATIONS: _json_spec(IMAGE_ANNOTATIONS_SCHEMA),
        topics.CAMERA_PLACEMENT_VERDICT: _json_spec(PLACEMENT_SCHEMA),
        topics.RECORDER: _json_spec(RECORDER_SCHEMA),
    }


# ----------------------------------------------------------------- JSON encoding


def dumps(message: dict[str, Any]) -> bytes:
    """Compact JSON of a message whose values are already JSON-compatible."""
    return json.dumps(message, separators=(",", ":"), allow_nan=False).encode()


def placement_messages(
    ns: int, jpeg: bytes, report: dict[str, Any], frame_id: str = "camera"
) -> tuple[bytes, bytes, bytes]:
    """The ``foxglove.CompressedImage``, ``foxglove.ImageAnnotations`` and verdict messages
    of one placement check (``report``: :meth:`PlacementReport.as_dict`)."""
    import base64

    stamp = timestamp(ns)
    image = {
        "timestamp": stamp,
        "frame_id": frame_id,
        "data": base64.b64encode(jpeg).decode(),
        "format": "jpeg",
    }
    green = {"r": 0.24, "g": 0.75, "b": 0.24, "a": 1.0}
    red = {"r": 0.9, "g": 0.16, "b": 0.16, "a": 1.0}
    clear = {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.0}
    circles, texts = [], []
    for p in report.get("positions", ()):
        if p.get("pixel") is None:
            continue
        colour = green if p.get("ok") else red
        x, y = p["pixel"]
        circles.append(
            {
                "timestamp": stamp,
                "position": {"x": x, "y": y},
                "diameter": 2 * float(p.get("pixel_radius") or 20.0),
                "thickness": 3.0,
                "fill_color": clear,
                "outline_color": colour,
            }
        )
        label = f"{p['slot']} {p['verdict']}"
        if p.get("offset_mm") is not None:
            label += f" {p['offset_mm']:.1f} mm"
        texts.append(
            {
                "timestamp": stamp,
                "position": {"x": x, "y": y + float(p.get("pixel_radius") or 20.0) + 14},
                "text": label,
                "font_size": 14.0,
                "text_color": colour,
                "background_color": {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.6},
            }
        )
    annotations = {"timestamp": stamp, "circles": circles, "points": [], "texts": texts}
    verdict = {"time": ns / 1e9, **report}
    return dumps(image), dumps(annotations), dumps(verdict)


def timestamp(ns: int) -> dict[str, int]:
    """A Foxglove ``time`` object from nanoseconds."""
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


LOG_LEVELS: Final = ((50, 5), (40, 4), (30, 3), (20, 2), (10, 1))


def foxglove_log_level(level: int) -> int:
    """``foxglove.LogLevel`` of a Python logging level."""
    for threshold, fox in LOG_LEVELS:
        if level >= threshold:
            return fox
    return 0
