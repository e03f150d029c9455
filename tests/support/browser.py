"""Headless Chromium for tests, driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``:
JSON messages ending in a NUL byte, Chromium reading fd 3 and writing fd 4), so that no port and no
websocket library is needed. It opens pages, collects their console lines and takes screenshots.

WebGPU runs on Chromium's SwiftShader adapter (the CPU) with ``--enable-unsafe-webgpu``. Debian's
``chromium`` package provides it (``scripts/install-system-deps.sh``); without it the tests fail with
that install line, never skip.
"""

from __future__ import annotations

import base64
import json
import os
import queue
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

#: Browsers tried in this order (Debian's package first).
EXECUTABLES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = (
    "--headless=new",
    "--enable-unsafe-webgpu",
    # Headless Chromium 156 needs these three for a WebGPU canvas: without the first two a page
    # loses its GPU instance at its first getCurrentTexture() ("A valid external Instance reference
    # no longer exists"), without the third the canvas never reaches the screenshot. Compute-only
    # pages work either way; WebGPU's adapter stays SwiftShader.
    "--enable-features=Vulkan",
    "--use-angle=vulkan",
    "--use-vulkan=swiftshader",
    "--no-sandbox",
    "--no-first-run",
    "--disable-extensions",
    "--disable-background-networking",
    "--disable-renderer-backgrounding",
    "--disable-background-timer-throttling",
)


class BrowserError(RuntimeError):
    """Chromium is missing, exited, or did not answer in time."""


def find_chromium() -> str:
    for name in EXECUTABLES:
        path = shutil.which(name)
        if path is not None:
            return path
    raise BrowserError(
        f"no Chromium found (tried {', '.join(EXECUTABLES)}): install it with "
        "`apt-get install chromium` (scripts/install-system-deps.sh does)"
    )


class Chromium:
    """One headless browser process; :meth:`open` a page, then :meth:`wait_console` or
    :meth:`screenshot` on it. Use as a context manager."""

    def __init__(self, extra_flags: tuple[str, ...] = ()) -> None:
        self.profile = tempfile.mkdtemp(prefix="lp3d-chromium-")
        self.log = Path(self.profile) / "stderr.log"
        to_child, self._to_browser = os.pipe()
        self._from_browser, from_child = os.pipe()

        def plumb() -> None:  # in the child, before exec: its fds 3 and 4 are the pipe
            os.dup2(to_child, 3)
            os.dup2(from_child, 4)

        with open(self.log, "wb") as err:
            self.proc = subprocess.Popen(
                [
                    find_chromium(),
                    *FLAGS,
                    *extra_flags,
                    "--remote-debugging-pipe",
                    f"--user-data-dir={self.profile}",
                ],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=err,
                preexec_fn=plumb,
                pass_fds=(3, 4),
            )
        os.close(to_child)
        os.close(from_child)
        self._messages: queue.Queue[dict[str, Any] | None] = queue.Queue()
        self._next_id = 0
        self.console: list[tuple[str, str]] = []  # (session, text) of every console line so far
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        buffer = b""
        while chunk := os.read(self._from_browser, 1 << 20):
            buffer += chunk
            *messages, buffer = buffer.split(b"\0")
            for m in messages:
                self._messages.put(json.loads(m))
        self._messages.put(None)  # the browser closed its end

    def _next(self, deadline: float, what: str) -> dict[str, Any]:
        try:
            message = self._messages.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            raise BrowserError(f"no answer from Chromium in time ({what})") from None
        if message is None:
            tail = self.log.read_text(errors="replace")[-2000:]
            raise BrowserError(f"Chromium exited ({what}); its stderr ends with:\n{tail}")
        if message.get("method") == "Runtime.consoleAPICalled":
            args = message["params"]["args"]
            text = " ".join(str(a.get("value", a.get("description", ""))) for a in args)
            self.console.append((message.get("sessionId", ""), text))
        elif message.get("method") == "Runtime.exceptionThrown":
            details = message["params"]["exceptionDetails"]
            text = details.get("exception", {}).get("description", details.get("text", ""))
            self.console.append((message.get("sessionId", ""), f"LP3D_ERROR uncaught: {text}"))
        return message

    def call(
        self,
        method: str,
        params: dict[str, Any] | None = None,
        session: str | None = None,
        timeout: float = 60.0,
    ) -> dict[str, Any]:
        """Send one DevTools command and return its result (events meanwhile are collected)."""
        self._next_id += 1
        message: dict[str, Any] = {"id": self._next_id, "method": method, "params": params or {}}
        if session is not None:
            message["sessionId"] = session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            answer = self._next(deadline, method)
            if answer.get("id") == self._next_id:
                if "error" in answer:
                    raise BrowserError(f"{method}: {answer['error']}")
                return answer["result"]

    def open(self, url: str, *, width: int = 600, height: int = 720, before: str | None = None) -> str:
        """A new tab showing ``url`` at ``width`` x ``height`` CSS pixels, running the script
        ``before`` ahead of the page's own; returns its session id."""
        target = self.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        self.call("Runtime.enable", session=session)
        self.call("Page.enable", session=session)
        metrics = {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False}
        self.call("Emulation.setDeviceMetricsOverride", metrics, session=session)
        if before is not None:
            self.call("Page.addScriptToEvaluateOnNewDocument", {"source": before}, session=session)
        self.call("Page.navigate", {"url": url}, session=session)
        return session

    def wait_console(self, session: str, accept: Callable[[str], bool], timeout: float) -> str:
        """The first console line of ``session`` that ``accept``s, waiting up to ``timeout`` seconds;
        a line starting ``LP3D_ERROR`` fails at once."""
        deadline = time.monotonic() + timeout
        seen = 0
        while True:
            for s, text in self.console[seen:]:
                if s == session and text.startswith("LP3D_ERROR"):
                    raise BrowserError(f"the page reported: {text}")
                if s == session and accept(text):
                    return text
            seen = len(self.console)
            self._next(deadline, "waiting for the page's console")

    def centre(self, session: str, selector: str) -> tuple[float, float]:
        """The centre of the element ``selector`` names, in CSS pixels of the viewport."""
        script = f"JSON.stringify(document.querySelector({json.dumps(selector)}).getBoundingClientRect())"
        answer = self.call("Runtime.evaluate", {"expression": script, "returnByValue": True}, session=session)
        box = json.loads(answer["result"]["value"])
        return box["x"] + box["width"] / 2, box["y"] + box["height"] / 2

    def mouse(self, session: str, kind: str, x: float, y: float, **extra: Any) -> None:
        """One mouse event (``mousePressed``, ``mouseMoved``, ``mouseReleased``, ``mouseWheel``)."""
        event = {"type": kind, "x": x, "y": y, **extra}
        self.call("Input.dispatchMouseEvent", event, session=session)

    def drag(self, session: str, start: tuple[float, float], by: tuple[float, float], steps: int = 5) -> None:
        """A left-button drag from ``start`` by ``by`` pixels, in ``steps`` moves."""
        x, y = start
        self.mouse(session, "mousePressed", x, y, button="left", buttons=1, clickCount=1)
        for i in range(1, steps + 1):
            self.mouse(
                session, "mouseMoved", x + by[0] * i / steps, y + by[1] * i / steps, button="left", buttons=1
            )
        self.mouse(session, "mouseReleased", x + by[0], y + by[1], button="left", buttons=0, clickCount=1)

    def click(self, session: str, selector: str) -> None:
        x, y = self.centre(session, selector)
        self.mouse(session, "mousePressed", x, y, button="left", buttons=1, clickCount=1)
        self.mouse(session, "mouseReleased", x, y, button="left", buttons=0, clickCount=1)

    def screenshot(self, session: str) -> bytes:
        """The tab's viewport as PNG bytes."""
        data = self.call("Page.captureScreenshot", {"format": "png"}, session=session)["data"]
        return base64.b64decode(data)

    def close(self) -> None:
        try:
            self.call("Browser.close", timeout=10)
        except BrowserError:
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for fd in (self._to_browser, self._from_browser):
            try:
                os.close(fd)
            except OSError:
                pass
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
