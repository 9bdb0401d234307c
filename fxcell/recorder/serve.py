"""Stream a recorded log to Foxglove over its WebSocket protocol, with play, pause and seek.

Clients connect with the SDK's ``foxglove.sdk.v1`` WebSocket subprotocol (the Foxglove
app does so by itself: open a Foxglove WebSocket connection to ``ws://HOST:PORT``).

Built on the ``foxglove-sdk`` WebSocket server: every topic of the file becomes a
channel with the file's own schema, the server advertises the file's time range
(``PlaybackControl``), and Foxglove's playback bar drives :meth:`Player.control`.
Messages go out at their recorded pace times the requested speed.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

from foxglove.websocket import PlaybackCommand, ServerListener

from fxcell.errors import RecorderError
from fxcell.recorder.reading import LogReader

log = logging.getLogger(__name__)

TIME_BROADCAST_INTERVAL = 0.05
"""Seconds of wall time between the server's time broadcasts while playing."""


class Player:
    """Plays one log file into a Foxglove WebSocket server (``port=0``: any free port)."""

    def __init__(
        self,
        path: str | Path,
        *,
        host: str = "127.0.0.1",
        port: int = 8765,
        speed: float = 1.0,
        autoplay: bool = True,
    ) -> None:
        import foxglove
        from foxglove.websocket import Capability

        self.reader = LogReader(path)
        if self.reader.start_time is None or self.reader.end_time is None:
            raise RecorderError(f"{path} has no messages to play")
        self.start_time: int = self.reader.start_time
        self.end_time: int = self.reader.end_time
        self._lock = threading.Condition()
        self._position = self.start_time
        self._speed = speed if speed > 0 else 1.0
        self._playing = autoplay
        self._generation = 0  # bumped on every seek/pause/play: the loop restarts from _position
        self._stop = False
        self._context = foxglove.Context()
        self._channels: dict[str, Any] = {}
        for ch in self.reader.channels.values():
            schema = self.reader.schemas.get(ch.schema_id)
            self._channels[ch.topic] = foxglove.Channel(
                ch.topic,
                schema=None
                if schema is None
                else foxglove.Schema(name=schema.name, encoding=schema.encoding, data=schema.data),
                message_encoding=ch.message_encoding,
                context=self._context,
            )
        self.server = foxglove.start_server(
            name=f"fxcell replay {self.reader.path.name}",
            host=host,
            port=port,
            capabilities=[Capability.Time],
            server_listener=_Listener(self),
            playback_time_range=(self.start_time, self.end_time),
            context=self._context,
        )

    @property
    def port(self) -> int:
        return int(self.server.port)

    @property
    def position(self) -> int:
        """Current playback time, ns since the epoch."""
        with self._lock:
            return self._position

    @property
    def playing(self) -> bool:
        with self._lock:
            return self._playing

    def control(
        self, *, play: bool | None = None, speed: float | None = None, seek: int | None = None
    ) -> None:
        """Play or pause, change speed, or seek to ``seek`` (ns, clamped to the file's range)."""
        with self._lock:
            if play is not None:
                self._playing = play
            if speed is not None and speed > 0:
                self._speed = speed
            if seek is not None:
                self._position = min(max(seek, self.start_time), self.end_time)
            self._generation += 1
            self._lock.notify_all()

    def state(self, did_seek: bool = False, request_id: str | None = None) -> Any:
        from foxglove.websocket import PlaybackState, PlaybackStatus

        with self._lock:
            if self._position >= self.end_time and not self._playing:
                status = PlaybackStatus.Ended
            else:
                status = PlaybackStatus.Playing if self._playing else PlaybackStatus.Paused
            return PlaybackState(
                status=status,
                current_time=self._position,
                playback_speed=self._speed,
                did_seek=did_seek,
                request_id=request_id,
            )

    def stop(self) -> None:
        with self._lock:
            self._stop = True
            self._lock.notify_all()
        self.server.stop()

    def run(self, until: float | None = None) -> None:
        """Serve until :meth:`stop` (or ``until`` seconds of wall time have passed)."""
        deadline = None if until is None else time.monotonic() + until
        while True:
            with self._lock:
                while not self._playing and not self._stop:
                    if deadline is not None and time.monotonic() >= deadline:
                        return
                    self._lock.wait(0.1)
                if self._stop:
                    return
                generation, start, speed = self._generation, self._position, self._speed
            ended = self._play_from(generation, start, speed, deadline)
            if deadline is not None and time.monotonic() >= deadline:
                return
            if ended:
                with self._lock:
                    if self._generation == generation:
                        self._playing = False
                        self._position = self.end_time
                self.server.broadcast_playback_state(self.state())

    def _play_from(self, generation: int, start: int, speed: float, deadline: float | None) -> bool:
        """Publish from ``start`` until the end (True) or a control change (False)."""
        wall0 = time.monotonic()
        last_broadcast = 0.0
        for msg in self.reader.messages(start=start):
            due = wall0 + (msg.log_time - start) / 1e9 / speed
            while True:
                with self._lock:
                    if self._generation != generation or self._stop:
                        return False
                    delay = due - time.monotonic()
                    if delay <= 0:
                        break
                    self._lock.wait(min(delay, 0.1))
                if deadline is not None and time.monotonic() >= deadline:
                    return False
            channel = self._channels.get(msg.topic)
            if channel is not None:
                channel.log(msg.data, log_time=msg.log_time)
            with self._lock:
                if self._generation != generation:
                    return False
                self._position = msg.log_time
            now = time.monotonic()
            if now - last_broadcast >= TIME_BROADCAST_INTERVAL:
                last_broadcast = now
                self.server.broadcast_time(msg.log_time)
        return True


class _Listener(ServerListener):
    """Turns Foxglove's playback-bar requests into :meth:`Player.control` calls."""

    def __init__(self, player: Player) -> None:
        self.player = player

    def on_playback_control_request(self, request: Any) -> Any:
        play = request.playback_command == PlaybackCommand.Play
        self.player.control(play=play, speed=request.playback_speed, seek=request.seek_time)
        return self.player.state(request.seek_time is not None, request.request_id)


def serve(
    path: str | Path, *, host: str = "127.0.0.1", port: int = 8765, speed: float = 1.0
) -> None:
    """``fxcell replay FILE --serve``: serve until interrupted."""
    player = Player(path, host=host, port=port, speed=speed)
    url = player.server.app_url()
    print(f"serving {path} on ws://{host}:{player.port} (Ctrl-C to stop)")
    if url:
        print(f"open in Foxglove: {url}")
    try:
        player.run()
    except KeyboardInterrupt:
        pass
    finally:
        player.stop()
