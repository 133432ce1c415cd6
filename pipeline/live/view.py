"""``--view``: a page on 127.0.0.1 showing the live depth, normals and contact mask, with rate and latency.

The headless OpenCV build has no windows, and a robot's computer has a browser anyway. The
server is the standard library's ``ThreadingHTTPServer`` (no framework); the page polls:

- ``GET /``: the page (plain HTML and a few lines of JavaScript, no external resources);
- ``GET /depth.png``, ``/normals.png``, ``/contact.png``: the latest result as PNG (encoded
  on request, once per result: a viewer never slows the pipeline down by more than one
  encode per image it asks for);
- ``GET /stats.json``: ``results``, ``dropped``, ``fps``, ``latency_ms_p50``,
  ``latency_ms_p99``, ``mode``, ``solver``, ``source``, ``running``, ``message``, ``size``.

:class:`LiveView` holds the latest result under a lock; the live loop calls
:meth:`LiveView.publish` after every result.
"""

from __future__ import annotations

import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np

from pipeline.base.http_page import send, send_json

__all__ = ["LiveView", "PAGE"]

PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>IrisTac live</title><link rel="icon" href="data:,">
<style>
body { font-family: sans-serif; margin: 1em; background: #111; color: #eee; }
.maps { display: flex; gap: 1em; flex-wrap: wrap; }
figure { margin: 0; } img { image-rendering: pixelated; width: 320px; background: #222; }
figcaption { text-align: center; } table { margin-top: 1em; } td { padding: 0 1em 0 0; }
</style></head>
<body>
<h1>IrisTac live</h1>
<div class="maps">
<figure><img id="depth" alt="depth"><figcaption>depth (mm)</figcaption></figure>
<figure><img id="normals" alt="normals"><figcaption>normals</figcaption></figure>
<figure><img id="contact" alt="contact mask"><figcaption>contact</figcaption></figure>
</div>
<table>
<tr><td>frame rate</td><td><span id="fps">-</span> results/s</td></tr>
<tr><td>latency p50 / p99</td><td><span id="p50">-</span> / <span id="p99">-</span> ms</td></tr>
<tr><td>results</td><td id="results">-</td></tr>
<tr><td>dropped</td><td id="dropped">-</td></tr>
<tr><td>mode / solver</td><td><span id="mode">-</span> / <span id="solver">-</span></td></tr>
<tr><td>status</td><td id="status">-</td></tr>
</table>
<script>
let last = -1;
async function tick() {
  try {
    const s = await (await fetch('stats.json', {cache: 'no-store'})).json();
    document.getElementById('fps').textContent = s.fps.toFixed(1);
    document.getElementById('p50').textContent = s.latency_ms_p50.toFixed(1);
    document.getElementById('p99').textContent = s.latency_ms_p99.toFixed(1);
    document.getElementById('results').textContent = s.results;
    document.getElementById('dropped').textContent = s.dropped;
    document.getElementById('mode').textContent = s.mode;
    document.getElementById('solver').textContent = s.solver;
    document.getElementById('status').textContent = s.running ? 'running' : ('stopped: ' + s.message);
    if (s.results !== last && s.results > 0) {
      last = s.results;
      for (const k of ['depth', 'normals', 'contact']) {
        document.getElementById(k).src = k + '.png?r=' + s.results;
      }
    }
  } catch (e) {
    document.getElementById('status').textContent = 'no connection';
  }
  setTimeout(tick, 200);
}
tick();
</script>
</body></html>
"""


def _png(img: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - cv2 encodes any uint8 image
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


class LiveView:
    """The live page's server and the latest result it shows.

    Parameters
    ----------
    port : int
        TCP port on 127.0.0.1 (0: any free port; :attr:`url` says which).
    contact_mm : float, optional
        Heights above this are contact in ``/contact.png`` (default: the contact mask's own
        threshold, :func:`pipeline.frame_pipeline.contact.contact_mask`).
    """

    def __init__(self, port: int = 0, contact_mm: float | None = None):
        self.contact_mm = contact_mm
        self._lock = threading.Lock()
        self._latest = None  # (result number, normals, mask, height)
        self._contact = (None, None, None)  # (contact mask, frames, no-contact reference) of the latest
        self._cache: dict[str, tuple[int, bytes]] = {}
        self._stats: dict = {"results": 0, "dropped": 0, "fps": 0.0, "latency_ms_p50": 0.0, "latency_ms_p99": 0.0,
                             "mode": "", "solver": "", "source": "", "running": True, "message": "", "size": None}
        view = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 - http.server's name
                path = self.path.split("?", 1)[0]
                if path in ("/", "/index.html"):
                    send(self, 200, "text/html; charset=utf-8", PAGE.encode())
                elif path == "/stats.json":
                    send_json(self, 200, view.stats())
                elif path in ("/depth.png", "/normals.png", "/contact.png"):
                    body = view.image(path[1:-4])
                    if body is None:
                        send(self, 503, "text/plain", b"no result yet")
                    else:
                        send(self, 200, "image/png", body)
                else:
                    send(self, 404, "text/plain", b"not found")

            def log_message(self, *args):  # the live loop's terminal stays quiet
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", int(port)), Handler)
        self.server.daemon_threads = True
        self.thread = threading.Thread(target=self.server.serve_forever, name="iristac-live-view", daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        host, port = self.server.server_address[:2]
        return f"http://{host}:{port}/"

    def publish(self, number: int, normals, mask, height, stats: dict, *, contact=None, frames=None,
                reference=None) -> None:
        """Show result ``number`` (normals ``(H, W, 3)``, mask ``(H, W)``, height ``(H, W)`` mm);
        its contact mask ``(H, W)`` when computed, else from ``frames`` and ``reference`` (the
        no-contact sample) and the height when the page asks for it."""
        with self._lock:
            self._latest = (int(number), normals, mask, height)
            self._contact = (contact, frames, reference)
            self._stats.update(stats)

    def set_stats(self, **stats) -> None:
        with self._lock:
            self._stats.update(stats)

    def stats(self) -> dict:
        with self._lock:
            return dict(self._stats)

    def image(self, kind: str) -> bytes | None:
        """PNG of the latest ``depth``, ``normals`` or ``contact`` map (None before the first result)."""
        with self._lock:
            latest = self._latest
            cached = self._cache.get(kind)
        if latest is None:
            return None
        number, normals, mask, height = latest
        if cached is not None and cached[0] == number:
            return cached[1]
        if kind == "contact":
            body = _png(self._contact_image(mask, height))
        else:
            body = _png(self._render(kind, normals, mask, height))
        with self._lock:
            self._cache[kind] = (number, body)
        return body

    def _render(self, kind, normals, mask, height) -> np.ndarray:
        import cv2

        from pipeline.results.exports import normal_map_rgb

        if kind == "normals":
            return cv2.cvtColor(normal_map_rgb(normals, mask), cv2.COLOR_RGB2BGR)
        h = np.where(mask, height, 0.0)
        top = max(float(np.abs(h).max()), 1e-6)
        return cv2.applyColorMap(np.clip(128 + 127 * h / top, 0, 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)

    def _contact_image(self, mask, height) -> np.ndarray:
        from pipeline.frame_pipeline.contact import contact_mask

        with self._lock:
            contact, frames, reference = self._contact
        if contact is None:
            colour = (frames, reference) if reference is not None else (None, None)
            contact = contact_mask(*colour, height, valid=mask, height_threshold_mm=self.contact_mm)
        return np.where(contact, 255, 0).astype(np.uint8)

    def close(self) -> None:
        """Stop serving (idempotent)."""
        if self.server is not None:
            self.server.shutdown()
            self.server.server_close()
            self.server = None
