"""``lp3d serve``'s live stream: webcam frames in over a WebSocket, triplanes out.

The page sends binary messages, each a frame number (u32, little-endian) and one JPEG frame. Per
connection a reader takes every message as it comes and keeps only the newest frame not yet
started (**latest frame wins**: a frame that a newer one overtakes before the server starts it is
dropped and counted, so a client never builds a queue on the server); workers align and encode it
on the server's worker threads and send back one triplane message
(:func:`lp3d.serve.lifting.triplane_message`) whose header says the frame, its timings and how many
frames were dropped. At most :attr:`LiveLimits.in_flight` frames of one connection (one, by default:
frames are then aligned and steadied in order, and the page keeps the next frame waiting so that the
server does not idle between frames) are being lifted at once, so one client holds at most that many
of the shared workers and cannot stall another.

Limits (:class:`LiveLimits`): a message over ``max_message_bytes`` (also uvicorn's ``ws_max_size``)
closes the stream with 1009; more than ``max_messages_per_s`` messages a second (averaged over one
second's burst) closes it with 1008; a text message closes it with 1003; past ``max_clients``
connections a new one is closed with 1013. A frame that cannot be read (not an image, too large)
gets a text message ``{"error": ...}`` and the stream goes on.
"""

from __future__ import annotations

import asyncio
import json
import time
from dataclasses import dataclass
from typing import Any

from starlette.websockets import WebSocket, WebSocketDisconnect

from lp3d.photo import PhotoError
from lp3d.serve.lifting import MAX_FRAME_BYTES, LiveSession, frame_id_and_image, triplane_message

__all__ = ["LiveLimits", "live_endpoint"]


@dataclass(frozen=True)
class LiveLimits:
    """The live stream's caps (module docstring)."""

    max_message_bytes: int = MAX_FRAME_BYTES
    max_messages_per_s: float = 60.0
    max_clients: int = 8
    in_flight: int = 1


class _Latest:
    """The newest frame not yet started, and how many were overtaken."""

    def __init__(self) -> None:
        self.item: tuple[int, bytes, float] | None = None
        self.dropped = 0
        self.ready = asyncio.Event()

    def put(self, item: tuple[int, bytes, float]) -> None:
        if self.item is not None:
            self.dropped += 1
        self.item = item
        self.ready.set()

    async def take(self) -> tuple[int, bytes, float]:
        while self.item is None:
            self.ready.clear()
            await self.ready.wait()
        item, self.item = self.item, None
        return item


class _Rate:
    """A token bucket: ``rate`` messages a second, bursts of one second's worth."""

    def __init__(self, rate: float) -> None:
        self.rate, self.tokens, self.at = rate, rate, time.monotonic()

    def take(self) -> bool:
        now = time.monotonic()
        self.tokens = min(self.rate, self.tokens + (now - self.at) * self.rate)
        self.at = now
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True


async def _read(ws: WebSocket, latest: _Latest, limits: LiveLimits) -> tuple[int, str] | None:
    """Take messages until the client leaves (None) or breaks a limit ((code, reason) to close with)."""
    rate = _Rate(limits.max_messages_per_s)
    while True:
        message = await ws.receive()
        if message["type"] == "websocket.disconnect":
            return None
        data = message.get("bytes")
        if data is None:
            return 1003, "frames are binary messages"
        if len(data) > limits.max_message_bytes:
            return 1009, f"a frame message is at most {limits.max_message_bytes} bytes"
        if not rate.take():
            return 1008, f"more than {limits.max_messages_per_s:g} messages a second"
        latest.put((*frame_id_and_image(data), time.perf_counter()))


async def _lift(ws: WebSocket, latest: _Latest, session: LiveSession, state: Any) -> None:
    """One worker of a connection: lift the newest frame, send its triplane, repeat."""
    loop = asyncio.get_running_loop()
    lifter = state.lifter
    while True:
        frame, data, t_in = await latest.take()

        def work(data: bytes = data) -> tuple[Any, dict]:
            face, info = lifter.align_frame(data, session)
            t0 = time.perf_counter()
            planes = lifter.encode(face)
            info["timings_ms"]["encode"] = round((time.perf_counter() - t0) * 1000, 2)
            return planes, info

        try:
            planes, info = await loop.run_in_executor(state.workers, work)
        except (PhotoError, ValueError) as e:
            await ws.send_text(json.dumps({"error": str(e), "frame": frame}))
            continue
        except Exception as e:  # a frame that breaks a library (OpenCV, dlib): that frame only
            await ws.send_text(
                json.dumps({"error": f"live frame: {type(e).__name__}: {e}"[:300], "frame": frame})
            )
            continue
        info["timings_ms"]["server"] = round((time.perf_counter() - t_in) * 1000, 2)
        header = {"kind": "live", "frame": frame, "dropped": latest.dropped, **info}
        await ws.send_bytes(triplane_message(planes, header))


async def live_endpoint(ws: WebSocket) -> None:
    state = ws.app.state.serve
    limits: LiveLimits = state.live_limits
    if state.live_clients >= limits.max_clients:
        await ws.close(code=1013, reason=f"the server takes {limits.max_clients} live streams at most")
        return
    await ws.accept()
    state.live_clients += 1
    latest, session = _Latest(), LiveSession()
    workers = [asyncio.ensure_future(_lift(ws, latest, session, state)) for _ in range(limits.in_flight)]
    try:
        verdict = await _read(ws, latest, limits)
        if verdict is not None:
            await ws.close(code=verdict[0], reason=verdict[1])
    except WebSocketDisconnect:
        pass
    finally:
        state.live_clients -= 1
        for w in workers:
            w.cancel()
        # A worker may be sending to a client that left: its error is the end of that worker.
        await asyncio.gather(*workers, return_exceptions=True)
