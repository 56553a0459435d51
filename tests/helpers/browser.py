"""A headless Chromium driven over the DevTools protocol, for the viewer's browser tests.

Chromium is started with ``--remote-debugging-pipe``: protocol messages are JSON objects
separated by NUL bytes, read by the browser from file descriptor 3 and written to descriptor 4
(no WebSocket and no network port are involved). :class:`Browser` sends commands and waits for
their replies; :meth:`Browser.open` attaches to one page target with a flattened session.

WebGL runs on SwiftShader (the CPU implementation shipped with Chromium):
``--use-angle=swiftshader`` with ``--enable-unsafe-swiftshader``, since CI machines have no GPU.
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "chrome")


def default_sigint() -> None:
    """``preexec_fn`` for a ``ps-lab view`` server a test stops with SIGINT (Ctrl-C).

    A job a non-interactive shell starts in the background (``make test &``, a CI wrapper, a
    loop under ``nohup``) inherits SIGINT *ignored*, and Python then installs no
    KeyboardInterrupt handler in the server: the test's Ctrl-C was lost and every stop timed
    out. The child gets the default disposition back, as a terminal's Ctrl-C would find it.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def find_chromium() -> str | None:
    """Path of a Chromium or Chrome executable, or None (``PS_LAB_CHROMIUM`` overrides)."""
    chosen = os.environ.get("PS_LAB_CHROMIUM")
    if chosen:
        return chosen if Path(chosen).exists() else None
    for name in CANDIDATES:
        found = shutil.which(name)
        if found:
            return found
    return None


class BrowserError(RuntimeError):
    """A protocol error reply, a crashed browser or a timeout."""


class Browser:
    """One headless Chromium process; use as a context manager."""

    def __init__(self, executable: str, width: int = 1200, height: int = 800) -> None:
        self.profile = tempfile.mkdtemp(prefix="ps-lab-chromium-")
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        self.width, self.height = width, height
        args = [
            executable,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--disable-extensions",
            "--disable-default-apps",
            "--no-first-run",
            "--no-default-browser-check",
            "--mute-audio",
            "--force-device-scale-factor=1",
            f"--window-size={width},{height}",
            f"--user-data-dir={self.profile}",
            "--remote-debugging-pipe",
            "about:blank",
        ]

        def wire() -> None:  # in the child: the pipe ends on descriptors 3 and 4
            # Moved above 10 first: either end may itself be descriptor 3 or 4.
            read_end = fcntl.fcntl(to_browser_r, fcntl.F_DUPFD, 10)
            write_end = fcntl.fcntl(from_browser_w, fcntl.F_DUPFD, 10)
            os.dup2(read_end, 3)
            os.dup2(write_end, 4)

        self.process = subprocess.Popen(
            args,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=wire,  # noqa: PLW1509 - only dup2 runs before exec
            pass_fds=(3, 4, to_browser_r, from_browser_w),
        )
        os.close(to_browser_r)
        os.close(from_browser_w)
        self._buffer = b""
        self._next_id = 0
        self.events: list[dict] = []
        self.session: str | None = None

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Ask the browser to quit, then make sure it is gone; remove its profile."""
        try:
            self.send("Browser.close", timeout=5)
        except (BrowserError, OSError):
            pass
        try:
            self.process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        for fd in (self._to_browser, self._from_browser):
            try:
                os.close(fd)
            except OSError:
                pass
        shutil.rmtree(self.profile, ignore_errors=True)

    def _read_message(self, deadline: float) -> dict:
        import select

        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0:
                raise BrowserError("timed out waiting for the browser")
            ready, _, _ = select.select([self._from_browser], [], [], left)
            if not ready:
                continue
            chunk = os.read(self._from_browser, 1 << 20)
            if not chunk:
                raise BrowserError(f"the browser exited (code {self.process.poll()})")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def send(self, method: str, params: dict | None = None, *, timeout: float = 30, **kw) -> dict:
        """Send one command (to the attached page unless ``browser=True``); return its result."""
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params or {}}
        if self.session and not kw.get("browser"):
            message["sessionId"] = self.session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            reply = self._read_message(deadline)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise BrowserError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            self.events.append(reply)

    def open(self, url: str, timeout: float = 30) -> None:
        """Open ``url`` in a new page and attach to it (later commands go to that page).

        The page opened before is closed first: one page, one WebGL context at a time, so a test
        never shares the GPU process's state with an earlier test's page that is still drawing.
        """
        previous = getattr(self, "target", None)
        if previous is not None:
            try:
                self.send("Target.closeTarget", {"targetId": previous}, browser=True)
            except BrowserError:
                pass  # already gone
            # closeTarget answers before the page is gone: wait until the browser no longer
            # lists it (its renderer and WebGL context released) before the next page draws.
            deadline = time.monotonic() + 10
            while any(t.get("targetId") == previous for t in self.send(
                "Target.getTargets", browser=True).get("targetInfos", [])):
                if time.monotonic() > deadline:
                    raise BrowserError(f"page {previous} still open 10 s after closing it")
                time.sleep(0.02)
        target = self.send("Target.createTarget", {"url": "about:blank"}, browser=True)["targetId"]
        self.target = target
        self.session = self.send(
            "Target.attachToTarget", {"targetId": target, "flatten": True}, browser=True
        )["sessionId"]
        self.send("Page.enable")
        self.send("Runtime.enable")
        self.send(
            "Emulation.setDeviceMetricsOverride",
            {"width": self.width, "height": self.height, "deviceScaleFactor": 1, "mobile": False},
        )
        self.send("Page.navigate", {"url": url})
        self.wait_for("document.readyState === 'complete'", timeout=timeout)

    def evaluate(self, expression: str, timeout: float = 30):
        """The value of a JavaScript expression (promises awaited)."""
        result = self.send(
            "Runtime.evaluate",
            {"expression": expression, "returnByValue": True, "awaitPromise": True},
            timeout=timeout,
        )
        if "exceptionDetails" in result:
            raise BrowserError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout: float = 30, interval: float = 0.05):
        """Evaluate ``expression`` until it is truthy; return its value."""
        deadline = time.monotonic() + timeout
        while True:
            value = self.evaluate(expression)
            if value:
                return value
            if time.monotonic() > deadline:
                raise BrowserError(f"timed out waiting for {expression}")
            time.sleep(interval)

    def mouse(self, kind: str, x: float, y: float, **extra) -> None:
        """One mouse event (``mousePressed``, ``mouseMoved``, ``mouseReleased``) at CSS (x, y)."""
        params = {"type": kind, "x": x, "y": y, "button": "left", "clickCount": 1}
        if kind == "mouseMoved":
            params["buttons"] = extra.pop("buttons", 0)
        params.update(extra)
        self.send("Input.dispatchMouseEvent", params)

    def drag(self, start: tuple[float, float], end: tuple[float, float], steps: int = 5) -> None:
        """Press at ``start``, move to ``end`` in steps, release."""
        self.mouse("mousePressed", *start)
        for k in range(1, steps + 1):
            x = start[0] + (end[0] - start[0]) * k / steps
            y = start[1] + (end[1] - start[1]) * k / steps
            self.mouse("mouseMoved", x, y, buttons=1)
        self.mouse("mouseReleased", *end)

    def screenshot(self) -> np.ndarray:
        """The page as an RGB uint8 array (H, W, 3)."""
        data = self.send("Page.captureScreenshot", {"format": "png"})["data"]
        picture = cv2.imdecode(np.frombuffer(base64.b64decode(data), np.uint8), cv2.IMREAD_COLOR)
        return picture[:, :, ::-1].copy()
