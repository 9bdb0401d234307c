"""Request and response bodies of the daemon's HTTP API (validated before anything moves)."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field

Finite = Annotated[float, Field(allow_inf_nan=False)]
Factor = Annotated[
    float,
    Field(gt=0, le=1, allow_inf_nan=False, description="scale of the joint limits, in (0, 1]"),
]
Joints = Annotated[
    list[Finite],
    Field(min_length=6, max_length=6, description="joint positions (rad), base to wrist 3"),
]
PoseList = Annotated[
    list[Finite],
    Field(
        min_length=6,
        max_length=7,
        description="[x, y, z, roll, pitch, yaw] or [x, y, z, qx, qy, qz, qw] in the base frame "
        "(m, rad)",
    ),
]
Vector3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]


class Body(BaseModel):
    # strict: a number is a JSON number (never a bool or a numeric string), a flag a JSON
    # boolean; unknown keys are refused
    model_config = ConfigDict(extra="forbid", strict=True)


class Factors(Body):
    velocity_factor: Factor | None = None
    acceleration_factor: Factor | None = None

    def kwargs(self) -> dict[str, Any]:
        return {k: v for k, v in self.model_dump().items() if v is not None}


class MoveJointRequest(Factors):
    target: Joints


class GoHomeRequest(Factors):
    pass


class MovePoseRequest(Factors):
    target: PoseList
    linear: bool = False


class MoveDistanceRequest(Factors):
    distance: Vector3 = Field(description="TCP displacement along the base axes (m)")


class MoveRelativeRequest(Factors):
    start_pose: PoseList
    target_pose: PoseList


class FactorRequest(Body):
    value: Factor


class UnlockRequest(Body):
    wait: bool = Field(False, description="wait out the controller's 5 s rule instead of failing")


class ControlRequest(Body):
    force: bool = Field(False, description="take control over from the current holder")


class ErrorBody(BaseModel):
    type: str
    message: str
    status: int
    detail: dict[str, Any] = {}


class ErrorResponse(BaseModel):
    error: ErrorBody
    operation: dict[str, Any] | None = None


class OperationModel(BaseModel):
    id: str
    name: str
    args: dict[str, Any]
    client: str
    status: str = Field(description="running, succeeded, failed or cancelled")
    started: float
    ended: float | None
    result: Any = None
    error: dict[str, Any] | None = None
