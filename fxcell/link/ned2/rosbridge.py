"""An asyncio client of a rosbridge WebSocket (the Ned2's port 9090), rosbridge v2.

It subscribes to topics (:meth:`RosbridgeClient.subscribe`: each message to a callback,
called on the client's event loop), calls services (:meth:`RosbridgeClient.call`: the
response's values, or a typed error) and sends actionlib goals
(:meth:`RosbridgeClient.send_goal`, then ``goal_result`` or ``cancel_goal``). One reader
task dispatches what arrives; a service that answers ``result: false`` raises
:class:`~fxcell.errors.RobotCommandError` with rosbridge's message, a response carrying a
Niryo ``status`` below 0 raises :class:`~fxcell.errors.RobotCommandStatusError`; a lost
connection fails every pending call and goal with
:class:`~fxcell.errors.ConnectionLostError`.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI

from fxcell.errors import (
    ConnectionLostError,
    RobotCommandError,
    RobotCommandStatusError,
    RobotTimeoutError,
)
from fxcell.link.ned2 import ABORTED, ROSBRIDGE_PORT

__all__ = ["ActionGoal", "RosbridgeClient", "Subscription"]

log = logging.getLogger(__name__)

Message = dict[str, Any]


@dataclass
class ActionGoal:
    """A goal sent to an action server: :meth:`RosbridgeClient.goal_result` waits for its
    end, :meth:`RosbridgeClient.cancel_goal` cancels it."""

    id: str
    server: str
    ended: asyncio.Future[tuple[int, Message]]
    """(final ``actionlib_msgs/GoalStatus``, the action's result message)."""


@dataclass
class Subscription:
    """A subscription of the client's: cancel it with :meth:`RosbridgeClient.unsubscribe`."""

    id: str
    topic: str
    callback: Callable[[Message], None]


class RosbridgeClient:
    """One WebSocket to a rosbridge server."""

    def __init__(self, host: str, port: int = ROSBRIDGE_PORT) -> None:
        self.host = host
        self.port = port
        self._ws: ClientConnection | None = None
        self._reader: asyncio.Task[None] | None = None
        self._calls: dict[str, asyncio.Future[Message]] = {}
        self._subscriptions: dict[str, list[Subscription]] = {}
        self._ids = itertools.count(1)
        self._goals: dict[str, ActionGoal] = {}
        self._action_servers: set[str] = set()
        self.closed_because = ""

    @property
    def connected(self) -> bool:
        return self._ws is not None and self._reader is not None and not self._reader.done()

    async def connect(self, within: float = 5.0) -> None:
        url = f"ws://{self.host}:{self.port}"
        try:
            self._ws = await connect(url, open_timeout=within, compression=None)
        except TimeoutError:
            raise RobotTimeoutError(f"no rosbridge answered at {url} within {within:g} s") from None
        except (OSError, InvalidHandshake, InvalidURI) as exc:
            raise ConnectionLostError(f"cannot reach the rosbridge at {url}: {exc}") from None
        self._reader = asyncio.create_task(self._read(self._ws), name=f"rosbridge {url}")

    async def close(self) -> None:
        ws, reader = self._ws, self._reader
        self._ws = self._reader = None
        if ws is not None:
            await ws.close()
        if reader is not None:
            reader.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await reader
        self._fail_calls("the client closed the connection")

    # ---------------------------------------------------------------- topics

    async def subscribe(
        self,
        topic: str,
        message_type: str,
        callback: Callable[[Message], None],
        *,
        throttle_rate: int = 0,
    ) -> Subscription:
        """Receive ``topic``'s messages (at most one per ``throttle_rate`` ms)."""
        sub = Subscription(f"subscribe:{topic}:{next(self._ids)}", topic, callback)
        self._subscriptions.setdefault(topic, []).append(sub)
        await self._send(
            {
                "op": "subscribe",
                "id": sub.id,
                "topic": topic,
                "type": message_type,
                "throttle_rate": throttle_rate,
            }
        )
        return sub

    async def unsubscribe(self, sub: Subscription) -> None:
        subs = self._subscriptions.get(sub.topic, [])
        if sub in subs:
            subs.remove(sub)
            await self._send({"op": "unsubscribe", "id": sub.id, "topic": sub.topic})

    # ---------------------------------------------------------------- services

    async def call(
        self, service: str, args: Message | None = None, *, within: float | None = 5.0
    ) -> Message:
        """Call ``service``; its response's values. A Niryo response whose ``status`` is
        below 0 raises :class:`RobotCommandStatusError`."""
        cid = f"call_service:{service}:{next(self._ids)}"
        answer: asyncio.Future[Message] = asyncio.get_running_loop().create_future()
        self._calls[cid] = answer
        try:
            await self._send(
                {"op": "call_service", "id": cid, "service": service, "args": args or {}}
            )
            async with asyncio.timeout(within):
                response = await answer
        except TimeoutError:
            raise RobotTimeoutError(f"{service}: no response within {within:g} s") from None
        finally:
            self._calls.pop(cid, None)
        values = response.get("values")
        if response.get("result") is False:
            raise RobotCommandError(f"{service}: {values}")
        if not isinstance(values, dict):
            values = {} if values is None else {"value": values}
        status = values.get("status")
        if isinstance(status, int) and not isinstance(status, bool) and status < 0:
            raise RobotCommandStatusError(status, f"{service}: {values.get('message', '')}")
        return values

    # ---------------------------------------------------------------- actions

    async def send_goal(self, server: str, action_type: str, goal: Message) -> ActionGoal:
        """Send ``goal`` to the actionlib server ``server`` (``action_type`` e.g.
        ``niryo_robot_arm_commander/RobotMoveAction``), as ROS 1's actionlib does it over
        the server's ``goal``, ``cancel`` and ``result`` topics."""
        if server not in self._action_servers:
            await self._send(
                {"op": "advertise", "topic": f"{server}/goal", "type": f"{action_type}Goal"}
            )
            await self._send(
                {"op": "advertise", "topic": f"{server}/cancel", "type": "actionlib_msgs/GoalID"}
            )
            await self.subscribe(f"{server}/result", f"{action_type}Result", self._on_result)
            self._action_servers.add(server)
        gid = f"fxcell:{server}:{next(self._ids)}"
        handle = ActionGoal(gid, server, asyncio.get_running_loop().create_future())
        self._goals[gid] = handle
        stamp = {"secs": 0, "nsecs": 0}
        await self._send(
            {
                "op": "publish",
                "topic": f"{server}/goal",
                "msg": {"goal_id": {"stamp": stamp, "id": gid}, "goal": goal},
            }
        )
        return handle

    async def goal_result(
        self, goal: ActionGoal, *, within: float | None = None
    ) -> tuple[int, Message]:
        """Wait for the goal's end: its final status and the action's result."""
        try:
            async with asyncio.timeout(within):
                return await asyncio.shield(goal.ended)
        except TimeoutError:
            raise RobotTimeoutError(
                f"{goal.server}: the goal did not end within {within:g} s"
            ) from None
        finally:
            if goal.ended.done():
                self._goals.pop(goal.id, None)

    async def cancel_goal(self, goal: ActionGoal) -> None:
        await self._send(
            {"op": "publish", "topic": f"{goal.server}/cancel", "msg": {"id": goal.id}}
        )

    def _on_result(self, msg: Message) -> None:
        status = msg.get("status")
        goal_id = status.get("goal_id") if isinstance(status, dict) else None
        gid = goal_id.get("id") if isinstance(goal_id, dict) else None
        goal = self._goals.get(gid) if isinstance(gid, str) else None
        if goal is None or goal.ended.done() or not isinstance(status, dict):
            return
        result = msg.get("result")
        code = status.get("status")
        goal.ended.set_result(
            (code if isinstance(code, int) else ABORTED, result if isinstance(result, dict) else {})
        )

    # ---------------------------------------------------------------- the socket

    async def _send(self, message: Message) -> None:
        ws = self._ws
        if ws is None or not self.connected:
            raise ConnectionLostError(
                f"the rosbridge at {self.host} is not connected ({self.closed_because})"
            )
        try:
            await ws.send(json.dumps(message))
        except ConnectionClosed as exc:
            raise ConnectionLostError(f"the rosbridge at {self.host} closed ({exc})") from None

    async def _read(self, ws: ClientConnection) -> None:
        try:
            async for raw in ws:
                try:
                    message = json.loads(raw)
                except ValueError:
                    log.warning("rosbridge sent a message that is not JSON: %.80r", raw)
                    continue
                if isinstance(message, dict):
                    self._dispatch(message)
            self.closed_because = "the rosbridge closed the connection"
        except ConnectionClosed as exc:
            self.closed_because = f"the connection was lost ({exc})"
        finally:
            self._fail_calls(self.closed_because or "the connection ended")

    def _dispatch(self, message: Message) -> None:
        op = message.get("op")
        if op == "publish":
            msg = message.get("msg")
            if isinstance(msg, dict):
                for sub in list(self._subscriptions.get(str(message.get("topic")), [])):
                    sub.callback(msg)
        elif op == "service_response":
            future = self._calls.get(str(message.get("id")))
            if future is not None and not future.done():
                future.set_result(message)
        elif op == "status":
            log.info("rosbridge %s: %s", message.get("level"), message.get("msg"))

    def _fail_calls(self, why: str) -> None:
        lost: list[asyncio.Future[Any]] = [*self._calls.values()]
        lost += [g.ended for g in self._goals.values()]
        for future in lost:
            if not future.done():
                future.set_exception(ConnectionLostError(f"rosbridge at {self.host}: {why}"))
                future.exception()  # retrieved here: a goal nobody waits for is not an error
        self._goals.clear()
