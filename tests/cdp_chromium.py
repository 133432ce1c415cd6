"""Headless Chromium driven over the DevTools protocol on a pipe: load a page, wait, evaluate, screenshot.

Chromium's ``--remote-debugging-pipe`` reads protocol messages from file descriptor 3 and
writes them to 4, each JSON message ended by a NUL byte, so no WebSocket client or open port
is needed. The protocol (rather than ``--enable-logging``) because it reports console
messages with their level (``console.error`` is an error, ``console.log`` is not), uncaught
exceptions with their text, and the browser's own errors (a script that failed to load, a
blocked request) as ``Log.entryAdded`` entries, and it answers ``Runtime.evaluate`` so a
test can wait for a page's own "rendered" signal and read its DOM.

Use::

    with Chromium() as browser:
        page = browser.open("http://127.0.0.1:8000/page.html", ready="document.body.dataset.rendered")
        page.evaluate("document.title"); png = page.screenshot(); page.errors  # [...]
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time

__all__ = ["find_chromium", "Chromium", "Page", "FLAGS", "serve", "CHART_CHECK_JS", "blank_fraction"]

#: The flags every launch uses (the project's standard set for a sandboxed headless run).
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync", "--hide-scrollbars",
         "--mute-audio", "--remote-debugging-pipe"]


def find_chromium() -> str | None:
    """The Chromium executable (Debian's ``chromium`` first), or None."""
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    return None


class Chromium:
    """A headless Chromium process and its protocol pipe (a context manager)."""

    def __init__(self, executable: str | None = None, width: int = 1000, height: int = 1200, timeout: float = 60.0):
        self.executable = executable or find_chromium()
        if not self.executable:
            raise RuntimeError("no chromium executable on PATH (Debian: apt-get install -y chromium)")
        self.width, self.height, self.timeout = width, height, timeout
        self._next = 0
        self._messages: list[dict] = []
        self._cond = threading.Condition()
        self._closed = False

    def __enter__(self) -> "Chromium":
        self._profile = tempfile.mkdtemp(prefix="iristac-chromium-")
        to_child_r, self._to_child = os.pipe()
        self._from_child, from_child_w = os.pipe()
        args = [self.executable, *FLAGS, f"--user-data-dir={self._profile}",
                f"--window-size={self.width},{self.height}", "about:blank"]
        # A small exec shim maps our pipe ends onto the descriptors 3 and 4 that Chromium expects
        # (sh's redirections stop at fd 9; ours may be higher).
        shim = (f"import os, sys; os.dup2({to_child_r}, 3); os.dup2({from_child_w}, 4); "
                f"os.execv(sys.argv[1], sys.argv[1:])")
        self._log = tempfile.TemporaryFile()
        self.proc = subprocess.Popen([sys.executable, "-c", shim, *args],
                                     pass_fds=(to_child_r, from_child_w), stdin=subprocess.DEVNULL,
                                     stdout=self._log, stderr=self._log)
        os.close(to_child_r)
        os.close(from_child_w)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.send("Browser.close", timeout=5.0)
        except (RuntimeError, TimeoutError, OSError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)
        for fd in (self._to_child, self._from_child):
            try:
                os.close(fd)
            except OSError:
                pass
        shutil.rmtree(self._profile, ignore_errors=True)
        self._log.close()

    def log_tail(self, n: int = 2000) -> str:
        """The end of Chromium's own output (why it stopped, when it did)."""
        self._log.seek(0)
        return self._log.read().decode(errors="replace")[-n:]

    def _read(self) -> None:
        buf = b""
        while True:
            try:
                chunk = os.read(self._from_child, 1 << 16)
            except OSError:
                chunk = b""
            if not chunk:
                break
            buf += chunk
            while b"\0" in buf:
                raw, buf = buf.split(b"\0", 1)
                with self._cond:
                    self._messages.append(json.loads(raw))
                    self._cond.notify_all()
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def send(self, method: str, params: dict | None = None, session: str | None = None,
             timeout: float | None = None) -> dict:
        """Send one command and wait for its result (an error reply raises RuntimeError)."""
        self._next += 1
        msg = {"id": self._next, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        try:
            os.write(self._to_child, json.dumps(msg).encode() + b"\0")
        except BrokenPipeError:
            raise RuntimeError(f"{method}: chromium has exited ({self.proc.poll()}): {self.log_tail()}") from None
        deadline = time.monotonic() + (timeout or self.timeout)
        with self._cond:
            while True:
                for m in self._messages:
                    if m.get("id") == msg["id"]:
                        self._messages.remove(m)
                        if "error" in m:
                            raise RuntimeError(f"{method}: {m['error']}")
                        return m.get("result", {})
                left = deadline - time.monotonic()
                if left <= 0 or self._closed:
                    raise TimeoutError(f"{method}: no reply within {timeout or self.timeout:.0f} s")
                self._cond.wait(left)

    def events(self, session: str) -> list[dict]:
        """Take every event received so far for ``session``."""
        with self._cond:
            mine = [m for m in self._messages if "method" in m and m.get("sessionId") == session]
            for m in mine:
                self._messages.remove(m)
            return mine

    def open(self, url: str, ready: str | None = None, timeout: float | None = None) -> "Page":
        """A new tab at ``url``, after its load event and (if given) once the JavaScript
        expression ``ready`` is truthy."""
        target = self.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        page = Page(self, session)
        for domain in ("Page", "Runtime", "Log"):
            self.send(f"{domain}.enable", session=session)
        self.send("Emulation.setDeviceMetricsOverride", {"width": self.width, "height": self.height,
                                                         "deviceScaleFactor": 1, "mobile": False}, session=session)
        self.send("Page.navigate", {"url": url}, session=session)
        page.wait_for("document.readyState === 'complete'", timeout)
        if ready:
            page.wait_for(ready, timeout)
        return page


class Page:
    """One tab: evaluate JavaScript, take screenshots, collect errors."""

    def __init__(self, browser: Chromium, session: str):
        self.browser, self.session = browser, session
        self._errors: list[str] = []
        self.console: list[tuple[str, str]] = []

    def _drain(self) -> None:
        for ev in self.browser.events(self.session):
            m, p = ev["method"], ev.get("params", {})
            if m == "Runtime.consoleAPICalled":
                text = " ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", []))
                self.console.append((p.get("type", ""), text))
                if p.get("type") in ("error", "assert"):
                    self._errors.append(f"console.{p['type']}: {text}")
            elif m == "Runtime.exceptionThrown":
                d = p.get("exceptionDetails", {})
                self._errors.append(f"exception: {d.get('exception', {}).get('description') or d.get('text')}")
            elif m == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
                e = p["entry"]
                self._errors.append(f"{e.get('source')}: {e.get('text')} {e.get('url', '')}".strip())

    @property
    def errors(self) -> list[str]:
        """Console errors, uncaught exceptions and browser error log entries so far."""
        self._drain()
        return list(self._errors)

    def evaluate(self, expression: str):
        """The value of a JavaScript expression (promises awaited; JSON-able values)."""
        r = self.browser.send("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                                   "awaitPromise": True}, session=self.session)
        if "exceptionDetails" in r:
            raise RuntimeError(f"evaluate {expression[:60]!r}: {r['exceptionDetails'].get('text')}")
        return r.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout: float | None = None) -> None:
        deadline = time.monotonic() + (timeout or self.browser.timeout)
        while not self.evaluate(f"Boolean({expression})"):
            if time.monotonic() > deadline:
                raise TimeoutError(f"page: {expression!r} still false after {timeout or self.browser.timeout:.0f} s; "
                                   f"errors: {self.errors}")
            time.sleep(0.1)

    def mouse(self, kind: str, x: float, y: float, buttons: int = 0) -> None:
        """One ``Input.dispatchMouseEvent`` (``mouseMoved``, ``mousePressed``, ``mouseReleased``)
        at page coordinates; ``buttons`` 1 while the left button is held."""
        pressed = kind != "mouseMoved" or buttons
        self.browser.send("Input.dispatchMouseEvent", {"type": kind, "x": x, "y": y,
                                                       "button": "left" if pressed else "none", "buttons": buttons,
                                                       "clickCount": 0 if kind == "mouseMoved" else 1},
                          session=self.session)

    def drag(self, x0: float, y0: float, x1: float, y1: float, steps: int = 6) -> None:
        """Press the left button at ``(x0, y0)``, move in ``steps`` to ``(x1, y1)``, release."""
        self.mouse("mouseMoved", x0, y0)
        self.mouse("mousePressed", x0, y0, buttons=1)
        for i in range(1, steps + 1):
            self.mouse("mouseMoved", x0 + (x1 - x0) * i / steps, y0 + (y1 - y0) * i / steps, buttons=1)
        self.mouse("mouseReleased", x1, y1)

    def click(self, selector: str) -> None:
        """A left click at the centre of the element ``selector`` matches."""
        x, y = self.evaluate(f"(() => {{ const b = document.querySelector({json.dumps(selector)})"
                             ".getBoundingClientRect(); return [b.x + b.width / 2, b.y + b.height / 2]; })()")
        self.mouse("mousePressed", x, y, buttons=1)
        self.mouse("mouseReleased", x, y)

    def screenshot(self, clip: dict | None = None) -> bytes:
        """A PNG of the viewport, or of ``clip`` (``{"x", "y", "width", "height"}`` in page px)."""
        params: dict = {"format": "png"}
        if clip:
            params.update(clip={**clip, "scale": 1}, captureBeyondViewport=True)
        return base64.b64decode(self.browser.send("Page.captureScreenshot", params, session=self.session)["data"])


class serve:
    """Serve ``directory`` over HTTP on 127.0.0.1 (a free port) in a thread: ``with serve(d) as base_url``."""

    def __init__(self, directory):
        self.directory = str(directory)

    def __enter__(self) -> str:
        import functools
        import http.server

        class Quiet(http.server.SimpleHTTPRequestHandler):
            def log_message(self, *args):  # keep pytest's output clean
                pass

        class Server(http.server.ThreadingHTTPServer):
            def handle_error(self, request, client_address):
                # Chromium drops connections it no longer needs (a page navigated on, a
                # prefetch): not a failure of the files served; anything else is printed.
                if not isinstance(sys.exc_info()[1], (ConnectionResetError, BrokenPipeError)):
                    super().handle_error(request, client_address)

        self.server = Server(("127.0.0.1", 0), functools.partial(Quiet, directory=self.directory))
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()
        return f"http://127.0.0.1:{self.server.server_address[1]}"

    def __exit__(self, *exc) -> None:
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(timeout=5)


#: JavaScript: per chart element, its label boxes (Plotly annotations named "label") and whether
#: any two overlap, the number of drawn points, and whether it has an SVG.
CHART_CHECK_JS = """
(() => [...document.querySelectorAll('.js-plotly-plot')].map(gd => {
  const boxes = [...gd.querySelectorAll('.annotation')].map(a => a.querySelector('.annotation-text-g, text'))
      .filter(Boolean).map(t => t.getBoundingClientRect()).filter(r => r.width > 0);
  let overlaps = 0;
  for (let i = 0; i < boxes.length; i++) for (let j = i + 1; j < boxes.length; j++) {
    const a = boxes[i], b = boxes[j];
    if (a.left < b.right - 1 && b.left < a.right - 1 && a.top < b.bottom - 1 && b.top < a.bottom - 1) overlaps++;
  }
  return {id: gd.id, svg: !!gd.querySelector('svg.main-svg'),
          points: gd.querySelectorAll('.scatterlayer .point').length, labels: boxes.length, overlaps: overlaps};
}))()
"""


def blank_fraction(png: bytes) -> tuple[float, float]:
    """``(fraction of near-white pixels, grey-level standard deviation)`` of a PNG."""
    import cv2
    import numpy as np

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError("not a PNG")
    grey = img.mean(axis=2)
    return float((grey > 245).mean()), float(grey.std())
