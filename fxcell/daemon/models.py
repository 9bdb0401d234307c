"""Request and response bodies of the daemon's HTTP API (validated before anything moves)."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, create_model

from fxcell import commands

Finite = Annotated[float, Field(allow_inf_nan=False)]


class Body(BaseModel):
    # strict: a number is a JSON number (never a bool or a numeric string), a flag a JSON
    # boolean; unknown keys are refused
    model_config = ConfigDict(extra="forbid", strict=True)


Flag = bool


def field_type(kind: commands.ArgType) -> Any:
    """The pydantic type of an argument type of the command table: a finite float in its
    bounds (low exclusive, high inclusive), a list of finite floats of its lengths, a flag,
    a short name, or an IO level (flag or number); JSON types only: the models are strict."""
    if kind.scalar == "bool":
        return Flag
    if kind.scalar == "str":
        return Annotated[str, Field(min_length=1, max_length=64)]
    if kind.scalar == "level":
        return Flag | Finite
    if kind.length is not None:
        low, high = kind.length
        return Annotated[list[Finite], Field(min_length=low, max_length=high)]
    if kind.bounds is not None:
        bottom, top = kind.bounds
        bound = Field(ge=bottom, le=top) if kind.closed else Field(gt=bottom, le=top)
        return Annotated[Finite, bound]
    return Finite


def request_model(command: commands.Command) -> type[Body] | None:
    """The request body of ``command``, built from its table entry (None: no arguments)."""
    if not command.args:
        return None
    fields: dict[str, Any] = {}
    for arg in command.args:
        annotation = field_type(arg.type)
        unit = f" ({arg.type.unit})" if arg.type.unit else ""
        info = Field(description=arg.doc + unit)
        if arg.required:
            fields[arg.name] = (Annotated[annotation, info], ...)
        elif arg.default is None:
            fields[arg.name] = (Annotated[annotation | None, info], None)
        else:
            fields[arg.name] = (Annotated[annotation, info], arg.default)
    name = "".join(part.title() for part in command.name.split("_")) + "Request"
    model: type[Body] = create_model(name, __base__=Body, **fields)
    return model


REQUEST_MODELS: dict[str, type[Body] | None] = {
    name: request_model(command)
    for name, command in commands.COMMANDS.items()
    if command.kind != "query"
}


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
