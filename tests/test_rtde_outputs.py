"""The RTDE outputs the link reads are one list: the raw stream subscribes to it and the
ur_rtde reader's getters are derived from it."""

from __future__ import annotations

import dataclasses
from typing import Any

import pytest

from fxcell.link.process import Link
from fxcell.link.rtde_stream import FIELDS, UR_RTDE_GETTERS, ur_rtde_getter
from fxcell.protocol import RTDE_STATE_OUTPUTS, RobotState

rtde_receive = pytest.importorskip("rtde_receive")


def test_every_output_has_a_ur_rtde_getter() -> None:
    interface = rtde_receive.RTDEReceiveInterface
    missing = [getter for _, getter in UR_RTDE_GETTERS if not hasattr(interface, getter)]
    assert not missing, f"RTDEReceiveInterface has no {missing}"


def test_getter_names_follow_ur_rtdes_naming() -> None:
    assert ur_rtde_getter("actual_TCP_pose") == "getActualTCPPose"
    assert ur_rtde_getter("target_qdd") == "getTargetQdd"
    assert ur_rtde_getter("standard_analog_input0") == "getStandardAnalogInput0"
    assert ur_rtde_getter("robot_status_bits") == "getRobotStatus"


def test_the_stream_and_the_getters_read_the_same_fields() -> None:
    assert [a for a, _ in UR_RTDE_GETTERS] == [a for a, _ in RTDE_STATE_OUTPUTS]
    assert tuple(output for _, output in RTDE_STATE_OUTPUTS) == FIELDS
    read = {a for a, _ in RTDE_STATE_OUTPUTS}
    host_side = {"output_int_registers", "received_at"}
    assert read | host_side == {f.name for f in dataclasses.fields(RobotState)}


class _Receive:
    """ur_rtde's receive interface as the link polls it: each getter answers a distinct value,
    vectors as lists (pybind's std::vector)."""

    def __init__(self) -> None:
        self.values: dict[str, Any] = {}
        for i, field in enumerate(dataclasses.fields(RobotState)):
            if isinstance(field.default, tuple) and field.name != "output_int_registers":
                self.values[field.name] = [float(i + k) for k in range(6)]
            elif field.name not in ("output_int_registers", "received_at"):
                self.values[field.name] = i

    def __getattr__(self, name: str) -> Any:
        for attr, getter in UR_RTDE_GETTERS:
            if getter == name:
                return lambda attr=attr: self.values[attr]
        raise AttributeError(name)


def test_a_ur_rtde_sample_carries_every_getters_value() -> None:
    receive = _Receive()
    state = Link._sample(receive, 12.5)
    assert state.timestamp == 12.5
    for attr, value in receive.values.items():
        if attr != "timestamp":
            expected = tuple(value) if isinstance(value, list) else value
            assert getattr(state, attr) == expected, attr
    assert isinstance(state.actual_q, tuple)
