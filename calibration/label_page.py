"""``iristac label CAPTURE.h5``: a page on 127.0.0.1 where a person accepts, moves, resizes or rejects
each press's contact circle (the web side of :class:`calibration.label_session.LabelSession`).

The server is the standard library's ``ThreadingHTTPServer``; the page is plain HTML, SVG and a
little JavaScript with no external resources (works offline). Endpoints:

- ``GET /``: the page;
- ``GET /api/state``: :meth:`LabelSession.summary` (every press's status and label);
- ``GET /api/press/K``: press ``K`` with its detected circle (detected on first request);
- ``GET /img/frame/K.png``, ``/img/diff/K.png``: the press, and its difference to the reference;
- ``POST /api/press/K`` with JSON ``{"action": "set", "x": X, "y": Y, "radius_px": R}``,
  ``{"action": "reject"}`` or ``{"action": "clear"}``: saved into the capture and the CSV
  before the answer (``{"ok": true, "press": ...}``; a bad request: 400 and ``{"error": ...}``).

Only requests whose ``Host`` is this server's own address are answered, and edits must be
JSON posts, so another web page open in the same browser cannot change the labels.

On the page: drag inside the yellow circle to move it, drag its rim (or the handle) to
resize it; click an empty spot to place a circle; keys ``A`` accept the detected circle,
``R`` reject, ``C`` clear, ``D`` frame/difference, ``←``/``→`` previous/next press.
"""

from __future__ import annotations

import json
import re
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from calibration.label_session import LabelSession
from pipeline.base.errors import UserError
from pipeline.base.http_page import send, send_json
from pipeline.results.exports import png_bytes

__all__ = ["LabelServer", "serve_labeller", "PAGE"]

PAGE = r"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>IrisTac labeller</title><link rel="icon" href="data:,">
<style>
body { font-family: sans-serif; margin: 0; background: #1b1b1b; color: #eee; display: flex; height: 100vh; }
#list { width: 14em; overflow-y: auto; border-right: 1px solid #444; padding: 0.5em; }
#list button { display: block; width: 100%; text-align: left; margin: 1px 0; background: #2a2a2a; color: #ddd;
  border: 1px solid #333; padding: 0.2em 0.4em; cursor: pointer; font: inherit; }
#list button.current { border-color: #ffd400; }
#list .labelled::before { content: "\2713  "; color: #6c6; }
#list .rejected::before { content: "\2717  "; color: #e66; }
#list .undecided::before { content: "\00b7  "; color: #999; }
#main { flex: 1; padding: 0.8em; overflow: auto; }
#view { position: relative; display: inline-block; background: #000; }
#view img { display: block; image-rendering: pixelated; }
#view svg { position: absolute; left: 0; top: 0; cursor: crosshair; }
.tools button { font: inherit; margin-right: 0.4em; padding: 0.25em 0.7em; }
#status { margin: 0.5em 0; min-height: 1.3em; }
#detected-info { color: #bbb; }
.err { color: #f88; }
</style></head>
<body>
<div id="list"><div id="progress">loading...</div></div>
<div id="main">
<div class="tools">
<button id="prev" title="previous press (left arrow)">&larr; prev</button>
<button id="next" title="next press (right arrow)">next &rarr;</button>
<button id="accept" title="use the detected circle (A)">accept detected (A)</button>
<button id="reject" title="no usable contact in this press (R)">reject (R)</button>
<button id="clear" title="undecided again (C)">clear (C)</button>
<button id="toggle" title="frame or difference to the reference (D)">difference (D)</button>
</div>
<h2 id="title">-</h2>
<div id="detected-info">-</div>
<div id="status">&nbsp;</div>
<div id="view"><img id="img" alt="press">
<svg id="svg" xmlns="http://www.w3.org/2000/svg">
<circle id="det" fill="none" stroke-width="1" stroke-dasharray="3 2" vector-effect="non-scaling-stroke"/>
<circle id="lab" fill="rgba(255,212,0,0.08)" stroke="#ffd400" stroke-width="2" vector-effect="non-scaling-stroke"
 style="cursor: move" visibility="hidden"/>
<circle id="handle" fill="#ffd400" style="cursor: ew-resize" visibility="hidden"/>
</svg></div>
<p>Drag inside the yellow circle to move it, drag its rim or the handle to resize it, click an empty spot to
place one. Dashed: the detected circle (green accepted, red rejected by the detector). Every change is saved
into the capture and the CSV at once.</p>
</div>
<script>
const S = {state: null, k: 0, press: null, view: 'diff', scale: 1, drag: null, saving: 0, saved: 0, errors: 0};
window.labeller = S;
const $ = (id) => document.getElementById(id);
const svg = $('svg'), lab = $('lab'), det = $('det'), handle = $('handle');

async function api(path, body) {
  const opt = body === undefined ? {cache: 'no-store'} :
    {method: 'POST', headers: {'Content-Type': 'application/json'}, body: JSON.stringify(body)};
  const r = await fetch(path, opt);
  const j = await r.json();
  if (!r.ok) throw new Error(j.error || r.statusText);
  return j;
}

function renderList() {
  const st = S.state;
  const list = $('list');
  list.querySelectorAll('button').forEach((b) => b.remove());
  st.presses.forEach((p) => {
    const b = document.createElement('button');
    b.textContent = p.index + ': ' + p.name;
    b.className = p.status + (p.index === S.k ? ' current' : '');
    b.id = 'press-' + p.index;
    b.onclick = () => show(p.index);
    list.appendChild(b);
  });
  $('progress').textContent = (st.labelled + st.rejected) + ' of ' + st.presses.length + ' decided (' +
    st.labelled + ' labelled, ' + st.rejected + ' rejected)';
}

function placeCircle(el, x, y, r) {
  el.setAttribute('cx', x + 0.5); el.setAttribute('cy', y + 0.5); el.setAttribute('r', Math.max(r, 0.5));
}

function draw() {
  const p = S.press;
  if (!p) return;
  const d = p.detected;
  placeCircle(det, d.x, d.y, d.radius_px);
  det.setAttribute('stroke', d.accepted ? '#4d4' : '#e44');
  det.setAttribute('visibility', d.radius_px > 0 ? 'visible' : 'hidden');
  const l = p.label;
  lab.setAttribute('visibility', l ? 'visible' : 'hidden');
  handle.setAttribute('visibility', l ? 'visible' : 'hidden');
  if (l) {
    placeCircle(lab, l.x, l.y, l.radius_px);
    placeCircle(handle, l.x + l.radius_px, l.y, 4 / S.scale);
  }
  $('title').textContent = 'press ' + p.index + ' of ' + S.state.presses.length + ': ' + p.name + ' (' + p.status + ')';
  $('detected-info').textContent = 'detected: ' + (d.accepted ? 'accepted' : 'rejected') + ' - ' + d.reason +
    ' (x ' + d.x.toFixed(1) + ', y ' + d.y.toFixed(1) + ', r ' + d.radius_px.toFixed(1) + ' px)' +
    (l ? '; label: x ' + l.x.toFixed(1) + ', y ' + l.y.toFixed(1) + ', r ' + l.radius_px.toFixed(1) + ' px' : '');
  $('toggle').textContent = (S.view === 'diff' ? 'frame' : 'difference') + ' (D)';
}

async function show(k) {
  const n = S.state.presses.length;
  S.k = Math.max(0, Math.min(n - 1, k));
  history.replaceState(null, '', '?press=' + S.k);
  $('status').textContent = 'detecting...';
  try {
    S.press = await api('api/press/' + S.k);
    $('status').innerHTML = '&nbsp;';
  } catch (e) { setError(e); return; }
  const [h, w] = S.state.shape;
  const room = [Math.max(200, window.innerWidth - $('list').offsetWidth - 40), Math.max(150, window.innerHeight - 190)];
  S.scale = Math.min(4, Math.floor(Math.min(room[0] / w, room[1] / h) * 100) / 100);
  const img = $('img');
  img.width = w * S.scale; img.height = h * S.scale;
  img.src = 'img/' + S.view + '/' + S.k + '.png';
  svg.setAttribute('width', w * S.scale); svg.setAttribute('height', h * S.scale);
  svg.setAttribute('viewBox', '0 0 ' + w + ' ' + h);
  renderList();
  draw();
}

function setError(e) { S.errors += 1; $('status').innerHTML = '<span class="err">' + e.message + '</span>'; }

async function send(body) {
  S.saving += 1;
  $('status').textContent = 'saving...';
  try {
    const r = await api('api/press/' + S.k, body);
    const det = S.press.detected;
    S.press = r.press; S.press.detected = det;
    S.state.presses[S.k] = r.press;
    for (const s of ['labelled', 'rejected', 'undecided']) {
      S.state[s] = S.state.presses.filter((p) => p.status === s).length;
    }
    S.saved += 1;
    $('status').textContent = 'saved press ' + S.k + ' (' + r.press.status + ')';
  } catch (e) { setError(e); }
  S.saving -= 1;
  renderList();
  draw();
}

function toImage(ev) {
  const pt = svg.createSVGPoint();
  pt.x = ev.clientX; pt.y = ev.clientY;
  const q = pt.matrixTransform(svg.getScreenCTM().inverse());
  return {x: q.x - 0.5, y: q.y - 0.5};
}

svg.addEventListener('mousedown', (ev) => {
  if (!S.press || ev.button !== 0) return;
  ev.preventDefault();
  const p = toImage(ev), l = S.press.label;
  if (l) {
    const dist = Math.hypot(p.x - l.x, p.y - l.y);
    const rim = 6 / S.scale;
    if (ev.target === handle || Math.abs(dist - l.radius_px) <= rim) {
      S.drag = {kind: 'resize'};
    } else if (dist < l.radius_px) {
      S.drag = {kind: 'move', dx: l.x - p.x, dy: l.y - p.y};
    }
    return;
  }
  const d = S.press.detected;
  const r = d.radius_px > 0 ? d.radius_px : 0.6 * S.state.ball_radius_px;
  S.press.label = {x: p.x, y: p.y, radius_px: r};
  S.drag = {kind: 'new'};
  draw();
});

window.addEventListener('mousemove', (ev) => {
  if (!S.drag) return;
  const p = toImage(ev), l = S.press.label;
  const [h, w] = S.state.shape;
  if (S.drag.kind === 'move') {
    l.x = Math.min(w - 0.5, Math.max(-0.5, p.x + S.drag.dx));
    l.y = Math.min(h - 0.5, Math.max(-0.5, p.y + S.drag.dy));
  } else if (S.drag.kind === 'resize') {
    l.radius_px = Math.max(1, Math.hypot(p.x - l.x, p.y - l.y));
  }
  draw();
});

window.addEventListener('mouseup', () => {
  if (!S.drag) return;
  S.drag = null;
  const l = S.press.label;
  send({action: 'set', x: l.x, y: l.y, radius_px: l.radius_px});
});

function accept() {
  const d = S.press && S.press.detected;
  if (!d || !(d.radius_px > 0)) { setError(new Error('no detected circle to accept')); return; }
  send({action: 'set', x: d.x, y: d.y, radius_px: d.radius_px});
}
$('accept').onclick = accept;
$('reject').onclick = () => send({action: 'reject'});
$('clear').onclick = () => send({action: 'clear'});
$('prev').onclick = () => show(S.k - 1);
$('next').onclick = () => show(S.k + 1);
$('toggle').onclick = () => { S.view = S.view === 'diff' ? 'frame' : 'diff'; show(S.k); };
window.addEventListener('keydown', (ev) => {
  const key = ev.key.toLowerCase();
  if (key === 'a') accept();
  else if (key === 'r') send({action: 'reject'});
  else if (key === 'c') send({action: 'clear'});
  else if (key === 'd') $('toggle').onclick();
  else if (ev.key === 'ArrowLeft') show(S.k - 1);
  else if (ev.key === 'ArrowRight') show(S.k + 1);
});

(async () => {
  try { S.state = await api('api/state'); } catch (e) { setError(e); return; }
  const m = /press=(\d+)/.exec(location.search);
  await show(m ? parseInt(m[1], 10) : 0);
  S.ready = true;
})();
</script>
</body></html>
"""

_PRESS = re.compile(r"^/api/press/(\d+)$")
_IMG = re.compile(r"^/img/(frame|diff)/(\d+)\.png$")


class LabelServer:
    """Serve a :class:`LabelSession` on 127.0.0.1 (in a background thread).

    Parameters
    ----------
    session : LabelSession
    port : int
        TCP port (0: any free one; :attr:`url` says which).

    Examples
    --------
    >>> import tempfile, os, json, urllib.request
    >>> from sim.virtual_sensor import random_sensor, write_sensor_capture
    >>> path = os.path.join(tempfile.mkdtemp(), "cap.h5")
    >>> _ = write_sensor_capture(path, random_sensor(1, shape=(48, 64), num_presses=2, effects="none"))
    >>> server = LabelServer(LabelSession(path))
    >>> json.load(urllib.request.urlopen(server.url + "api/state"))["undecided"]
    2
    >>> server.close()
    """

    def __init__(self, session: LabelSession, port: int = 0):
        self.session = session
        handler = _handler(session, self)
        self.server = ThreadingHTTPServer(("127.0.0.1", int(port)), handler)
        self.server.daemon_threads = True
        host, p = self.server.server_address[:2]
        self.allowed_hosts = {f"{host}:{p}", f"localhost:{p}"}
        self.thread = threading.Thread(target=self.server.serve_forever, name="iristac-label", daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        host, port = self.server.server_address[:2]
        return f"http://{host}:{port}/"

    def close(self) -> None:
        """Stop serving (every edit is already saved)."""
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(timeout=5)


class _Handler(BaseHTTPRequestHandler):
    """The labeller's requests; :func:`_handler` binds a session and its server."""

    session: LabelSession
    owner: LabelServer

    def do_GET(self):  # noqa: N802 - http.server's name
        if not self._host_ok():
            return
        path = self.path.split("?", 1)[0]
        try:
            self._get(path)
        except UserError as exc:
            self._json(404, {"error": str(exc)})

    def _get(self, path: str) -> None:
        session = self.session
        if path in ("/", "/index.html"):
            self._send(200, "text/html; charset=utf-8", PAGE.encode())
        elif path == "/api/state":
            self._json(200, session.summary())
        elif _PRESS.match(path):
            self._json(200, session.press(int(_PRESS.match(path)[1])))
        elif _IMG.match(path):
            kind, k = _IMG.match(path).groups()
            img = session.frame_image(int(k)) if kind == "frame" else session.difference_image(int(k))
            self._send(200, "image/png", png_bytes(img))
        else:
            self._json(404, {"error": f"not found: {path}"})

    def do_POST(self):  # noqa: N802 - http.server's name
        if not self._host_ok():
            return
        m = _PRESS.match(self.path.split("?", 1)[0])
        if m is None:
            self._json(404, {"error": f"not found: {self.path}"})
            return
        if self.headers.get("Content-Type", "").split(";")[0].strip() != "application/json":
            self._json(415, {"error": "edits must be posted as application/json"})
            return
        try:
            body = json.loads(self.rfile.read(int(self.headers.get("Content-Length") or 0)) or b"{}")
            press = self._edit(int(m[1]), body)
        except (ValueError, TypeError) as exc:
            self._json(400, {"error": f"bad request: {exc}"})
            return
        except UserError as exc:
            self._json(400, {"error": str(exc)})
            return
        self._json(200, {"ok": True, "press": press})

    def _edit(self, k: int, body) -> dict:
        action = body.get("action") if isinstance(body, dict) else None
        if action == "set":
            return self.session.set_label(k, body.get("x"), body.get("y"), body.get("radius_px"))
        if action == "reject":
            return self.session.reject(k)
        if action == "clear":
            return self.session.clear(k)
        raise UserError(f"unknown action {action!r} (expected set, reject or clear)")

    def _host_ok(self) -> bool:
        if self.headers.get("Host") in self.owner.allowed_hosts:
            return True
        self._json(403, {"error": "this labeller answers only requests addressed to its own 127.0.0.1 address"})
        return False

    def _json(self, code, obj):
        send_json(self, code, obj)

    def _send(self, code, kind, body):
        send(self, code, kind, body)

    def log_message(self, *args):  # the terminal stays quiet
        pass


def _handler(session: LabelSession, owner: LabelServer):
    return type("LabelHandler", (_Handler,), {"session": session, "owner": owner})


def serve_labeller(capture, *, port: int = 8766, ball_radius_mm: float | None = None, csv_path=None,
                   open_browser: bool = False, seconds: float | None = None, announce=print) -> dict:
    """Open ``capture`` for labelling and serve the page until Ctrl-C (or ``seconds`` have passed).

    Parameters
    ----------
    capture : path
        The capture file; labels are saved into it as they are made.
    port : int
        Port on 127.0.0.1 (0: any free one).
    ball_radius_mm, csv_path
        As :class:`calibration.label_session.LabelSession`.
    open_browser : bool
        Also open the page in the default browser (:mod:`webbrowser`).
    seconds : float, optional
        Stop after this long (scripts and tests); default: until interrupted.
    announce : callable
        Called once with the line saying where the page is.

    Returns
    -------
    dict
        :meth:`LabelSession.summary` when serving stopped, plus ``url`` and ``saves`` (edits
        saved in this run).
    """
    import time

    session = LabelSession(capture, ball_radius_mm=ball_radius_mm, csv_path=csv_path)
    try:
        server = LabelServer(session, port)
    except OSError as exc:
        raise UserError(f"cannot serve the labeller on 127.0.0.1:{port}: {exc} (try --port 0)") from None
    done = session.summary()
    announce(f"labelling {session.path} ({session.num_presses} presses: {done['labelled']} labelled, "
             f"{done['rejected']} rejected): open {server.url} in a browser; every edit is saved at once to the "
             f"capture and {session.csv_path}; Ctrl-C to stop")
    if open_browser:
        import webbrowser

        webbrowser.open(server.url)
    try:
        end = None if seconds is None else time.monotonic() + float(seconds)
        while end is None or time.monotonic() < end:
            time.sleep(0.2 if end is None else max(0.0, min(0.2, end - time.monotonic())))
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
    return {**session.summary(), "url": server.url, "saves": session.saves}
