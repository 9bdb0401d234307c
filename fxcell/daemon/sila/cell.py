"""The cell's SiLA features: CellController, LabwareTransferManipulatorController,
SimulationController (definitions in ``features/``).

Each command is one entry of the command table run as a daemon operation
(:class:`~fxcell.daemon.sila.access.SilaCommands`); the cell's typed errors become the
feature's defined execution errors (:class:`~fxcell.daemon.sila.bridge.ErrorMap`).
Observable properties are fed from the loop by :meth:`CellController.refresh`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, NamedTuple, TypeVar

from sila2.framework import DefinedExecutionError, Feature
from sila2.server import FeatureImplementationBase, MetadataDict

from fxcell import errors
from fxcell.daemon.sila.access import SilaCommands, lock_identifier
from fxcell.daemon.sila.bridge import CELL_ERRORS, ErrorMap, LoopBridge, PropertyQueue
from fxcell.errors import FxcellError

if TYPE_CHECKING:
    from queue import Queue

    from sila2.server import SilaServer

    from fxcell.daemon.service import CellService

T = TypeVar("T")


class _CellFeature(FeatureImplementationBase):
    """Runs table commands through the loop and translates the cell's errors."""

    def __init__(
        self,
        parent_server: SilaServer,
        bridge: LoopBridge,
        commands: SilaCommands,
        errors_: ErrorMap,
    ) -> None:
        super().__init__(parent_server=parent_server)
        self.bridge = bridge
        self.commands = commands
        self.errors = errors_

    def _run(self, name: str, args: Mapping[str, Any], metadata: MetadataDict) -> Any:
        identifier = lock_identifier(metadata)
        return self._call(lambda: self.commands.run(name, args, identifier))

    def _call(self, make: Callable[[], Any]) -> Any:
        try:
            return self.bridge.run(make)
        except FxcellError as exc:
            raise self.errors.translate(exc) from None


class GripperOpen_Responses(NamedTuple):
    Width: float


class GripperClose_Responses(NamedTuple):
    Width: float
    Holding: bool


class CellController(_CellFeature):
    """``org.fxcell/robot/CellController/v1``."""

    def __init__(
        self,
        parent_server: SilaServer,
        feature: Feature,
        bridge: LoopBridge,
        commands: SilaCommands,
        service: CellService,
    ) -> None:
        super().__init__(
            parent_server, bridge, commands, ErrorMap(feature, CELL_ERRORS, "CellError")
        )
        self.service = service
        self.state = PropertyQueue("disconnected")
        self.robot_mode = PropertyQueue("")
        self.safety_mode = PropertyQueue("")
        self.control_holder = PropertyQueue("")
        self._CellState_producer_queue: Queue[object] = self.state.queue
        self._RobotMode_producer_queue: Queue[object] = self.robot_mode.queue
        self._SafetyMode_producer_queue: Queue[object] = self.safety_mode.queue
        self._ControlHolder_producer_queue: Queue[object] = self.control_holder.queue

    def refresh(self) -> None:
        """Offer the observable properties' current values (on the loop)."""
        service = self.service
        self.state.offer(service.machine_state())
        sample = service.latest
        self.robot_mode.offer(sample.robot_mode.name if sample is not None else "")
        self.safety_mode.offer(sample.safety_mode.name if sample is not None else "")
        holder = service.control.holder
        self.control_holder.offer(holder.client if holder is not None else "")

    # Observable properties: every subscriber gets the latest value, then each change.
    def CellState_on_subscription(self, *, metadata: MetadataDict) -> None:
        return None

    def RobotMode_on_subscription(self, *, metadata: MetadataDict) -> None:
        return None

    def SafetyMode_on_subscription(self, *, metadata: MetadataDict) -> None:
        return None

    def ControlHolder_on_subscription(self, *, metadata: MetadataDict) -> None:
        return None

    def get_TaughtPositions(self, *, metadata: MetadataDict) -> list[str]:
        positions = self._call(lambda: self.service.query("get_positions"))
        return ["home", *sorted(positions)]

    def Init(self, *, metadata: MetadataDict) -> None:
        self._run("init", {}, metadata)

    def GoHome(self, *, metadata: MetadataDict) -> None:
        self._run("go_home", {}, metadata)

    def MoveToPosition(self, PositionName: str, *, metadata: MetadataDict) -> None:
        self._run("move_to", {"name": PositionName}, metadata)

    def Stop(self, *, metadata: MetadataDict) -> bool:
        return bool(self._run("stop", {}, metadata))

    def GripperActivate(self, *, metadata: MetadataDict) -> None:
        self._run("gripper_activate", {}, metadata)

    def GripperOpen(self, *, metadata: MetadataDict) -> GripperOpen_Responses:
        result = self._run("gripper_open", {}, metadata)
        return GripperOpen_Responses(float(result.width))

    def GripperClose(self, *, metadata: MetadataDict) -> GripperClose_Responses:
        result = self._run("gripper_close", {}, metadata)
        return GripperClose_Responses(float(result.width), bool(result.holding))


TRANSFER_ERRORS: dict[type[FxcellError], str] = {
    errors.UnknownStationError: "HandoverPositionUnknown",
    errors.SlotError: "HandoverPositionUnknown",
    errors.ControlHeldError: "ControlHeld",
}


class LabwareTransferManipulatorController(_CellFeature):
    """``org.fxcell/robot/LabwareTransferManipulatorController/v1``: pick and place at sites."""

    def __init__(
        self,
        parent_server: SilaServer,
        feature: Feature,
        bridge: LoopBridge,
        commands: SilaCommands,
        service: CellService,
    ) -> None:
        super().__init__(
            parent_server,
            bridge,
            commands,
            ErrorMap(feature, TRANSFER_ERRORS, "LabwareTransferFailed"),
        )
        self.service = service

    @staticmethod
    def _site(position: Any) -> dict[str, str]:
        return {"station": str(position.Position), "slot": str(position.SubPosition)}

    def get_Sites(self, *, metadata: MetadataDict) -> list[str]:
        layout = self._call(lambda: self.service.query("get_layout"))
        return [
            f"{station}/{slot}"
            for station, data in layout["stations"].items()
            for slot in (data.get("slots") or {})
        ]

    def GetLabware(self, HandoverPosition: Any, *, metadata: MetadataDict) -> None:
        self._run("pick", self._site(HandoverPosition), metadata)

    def PutLabware(self, HandoverPosition: Any, *, metadata: MetadataDict) -> None:
        self._run("place", self._site(HandoverPosition), metadata)

    def TransferLabware(
        self, SourcePosition: Any, DestinationPosition: Any, *, metadata: MetadataDict
    ) -> None:
        identifier = lock_identifier(metadata)
        source, destination = self._site(SourcePosition), self._site(DestinationPosition)

        async def transfer() -> None:
            await self.commands.run("pick", source, identifier)
            await self.commands.run("place", destination, identifier)

        self._call(transfer)


class SimulationController(FeatureImplementationBase):
    """``org.silastandard/core/SimulationController/v1``: reports the embedded simulator.

    Which robot the cell drives is fixed at the daemon's start (``robot.host``): switching
    is refused with the reason and what to do instead."""

    def __init__(self, parent_server: SilaServer, feature: Feature, simulated: bool) -> None:
        super().__init__(parent_server=parent_server)
        self.feature = feature
        self.simulated = simulated

    def get_SimulationModeActive(self, *, metadata: MetadataDict) -> bool:
        return self.simulated

    def _refuse(self, identifier: str, wanted: str) -> None:
        if wanted == "simulation" and self.simulated:
            return
        if wanted == "real" and not self.simulated:
            return
        now = "the embedded simulator" if self.simulated else "a real robot (robot.host)"
        how = (
            "restart the daemon with robot.host set (or --robot-host HOST)"
            if wanted == "real"
            else "restart the daemon without robot.host"
        )
        node = self.feature.defined_execution_errors[identifier]
        raise DefinedExecutionError(
            node, f"the cell runs on {now}, chosen when the daemon started: {how}"
        )

    def StartSimulationMode(self, *, metadata: MetadataDict) -> None:
        self._refuse("StartSimulationModeFailed", "simulation")

    def StartRealMode(self, *, metadata: MetadataDict) -> None:
        self._refuse("StartRealModeFailed", "real")
