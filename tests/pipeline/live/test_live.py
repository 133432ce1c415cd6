"""``iristac live`` through the real CLI and the real parts: the virtual sensor behind the ring
emulator on a pseudo-terminal, a video file through OpenCV, real HDF5 files, a real HTTP
server, a real SIGKILL, and a headless Chromium where one is installed.

Small frames (80 x 60) keep the virtual sensor's calibration (cached per test session in a
shared store) and rendering quick.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from cdp_chromium import find_chromium
from helpers import REPO, run_cli

SIZE = "80x60"
KEYS = {"results", "dropped", "fps", "latency_ms_p50", "latency_ms_p99", "mode", "solver"}


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """One stage store for the module: the virtual sensor is calibrated once per mode and solver."""
    return tmp_path_factory.mktemp("live-cache")


def _live(*args, store, timeout=300):
    r = run_cli("live", "--virtual", "--size", SIZE, "--cache", store, "--json", *args, timeout=timeout)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_live_virtual_trichromatic_lut(store):
    s = _live("--mode", "trichromatic", "--solver", "lut", "--frames", "40", store=store)
    assert KEYS <= set(s) and s["results"] == 40 and s["mode"] == "trichromatic" and s["solver"] == "lut"
    assert s["method"] == "fast" and s["stopped"] == "frames" and s["fps"] > 0
    assert 0 < s["latency_ms_p50"] <= s["latency_ms_p99"]
    # The second run finds the virtual sensor's calibration in the store.
    again = _live("--mode", "trichromatic", "--solver", "lut", "--frames", "5", store=store)
    assert again["results"] == 5


def test_live_virtual_point_nearfield_cycles(store):
    """Multi-pattern: the ring is driven through 24 patterns per result; every frame's LED state
    is checked against the emulator's history (mislabeled 0), stale frames are rejected."""
    s = _live("--mode", "point", "--solver", "nearfield", "--frames", "3", store=store)
    assert s["results"] == 3 and s["mode"] == "point" and s["method"] == "fast"
    assert s["mislabeled"] == 0 and s["stale"] > 0


class _PressOnSecondPattern:
    """The ring, with a press that changes as the second pattern of every other cycle is asked
    for: the first pattern's frame was read before the change and the second's is exposed
    after the ring confirms it, so that cycle is torn by construction (no clock involved)."""

    def __init__(self, ring, camera, patterns: int):
        self.ring, self.camera, self.patterns, self.calls, self.contact = ring, camera, patterns, 0, 0

    def show_pattern(self, drive, brightness):
        if self.calls % (2 * self.patterns) == 1:
            self.contact = 1 - self.contact
            self.camera.set_contact(self.contact)
        self.calls += 1
        return self.ring.show_pattern(drive, brightness)


def test_cycle_source_never_mixes_cycles(ring_backend):
    """A cycle whose frames saw two contacts is discarded and counted, never a sample: the press
    changes inside every other cycle, so three samples cost exactly three torn cycles, and each
    sample holds one contact (the new one). Every frame's LED state is the one its pattern
    asked for (checked against the emulator's history; the Python emulator and the C
    firmware's host build)."""
    from pipeline.base.modes import load_mode
    from pipeline.capture.client import RingClient
    from pipeline.capture.session import virtual_sensor
    from pipeline.capture.virtual import open_virtual_camera
    from pipeline.live.sources import CycleSource

    patterns = load_mode("monochromatic")
    spec = virtual_sensor(obj="sphere", contacts=2, shape=(24, 32), mm_per_px=0.3, fps=400.0)
    emu = ring_backend.emulator(patterns.num_leds)
    port = emu.start()
    try:
        with RingClient(port) as ring:
            cam = open_virtual_camera(spec, emu, patterns.drive, patterns.brightness)
            try:
                cam.set_contact(0)
                src = CycleSource(_PressOnSecondPattern(ring, cam, len(patterns.frames)), cam, patterns, truth=emu,
                                  max_attempts=2)
                samples = [src.next() for _ in range(3)]
            finally:
                cam.close()
    finally:
        emu.stop()
    assert src.counters["torn"] == 3 and src.counters["mislabeled"] == 0
    assert [s.info["contact"] for s in samples] == [1, 0, 1]
    for s in samples:
        assert s.frames.shape == (len(patterns.frames), 24, 32, 3)


def test_live_drops_the_oldest_when_processing_falls_behind(store, tmp_path):
    """An eager solver behind a 500 fps camera with a queue of one: samples are dropped and
    counted, the recording carries the running count, and every result still comes."""
    from pipeline.live.recorder import read_recording

    rec = tmp_path / "rec.h5"
    s = _live("--mode", "trichromatic", "--solver", "lut", "--eager", "--fps", "500", "--queue", "1", "--frames", "25",
              "--record", rec, store=store)
    assert s["results"] == 25 and s["method"] == "eager" and s["dropped"] > 0
    got = read_recording(rec)
    assert got.meta["dropped_total"] == s["dropped"] and (np.diff(got.data["dropped"]) >= 0).all()
    assert got.data["dropped"][-1] <= s["dropped"]


@pytest.fixture(scope="module")
def video_and_calibration(tmp_path_factory, store):
    """A video file of rendered trichromatic presses and a LUT calibration of the same sensor."""
    import cv2

    from pipeline.base.modes import load_mode
    from pipeline.base.store import Record, StageStore, write_record
    from pipeline.live import virtual_calibration
    from sim.contacts import contact_surfaces
    from sim.render import bare_ring_illumination
    from sim.rendered_capture import render_capture

    d = tmp_path_factory.mktemp("video")
    model = bare_ring_illumination((60, 80), 0.15)
    cal = virtual_calibration(StageStore(store), model, "test", "trichromatic", "lut")
    cal_path = write_record(d / "cal.h5", Record(cal.schema, cal.data, cal.meta))
    presses = contact_surfaces("sphere", (60, 80), 0.15, 6, size_mm=2.0, depth_mm=0.5, seed=5)
    cap = render_capture(model, load_mode("trichromatic"), presses, noise_dn=1.0, bit_depth=8, seed=3)
    frames = cap.data["frames"][:, 0]  # (6, 60, 80, 3) RGB
    video = d / "presses.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (80, 60))
    assert w.isOpened()
    for f in frames:
        w.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    w.release()
    return video, cal_path, frames


def test_live_video_file_ends_recording_closed_and_valid(video_and_calibration, tmp_path):
    """The camera runs out mid-stream (a video file ends): one clear message, the recording is
    closed, consolidated and valid, and holds every frame and (``--contact``) its contact mask,
    taken against the calibration's no-contact frame with the drift removed."""
    from pipeline.live.recorder import read_recording

    video, cal, frames = video_and_calibration
    rec = tmp_path / "rec.h5"
    r = run_cli("live", "--camera", video, "--calibration", cal, "--solver", "lut", "--record", rec, "--json",
                "--queue", "64", "--contact")
    assert r.returncode == 0, r.stderr  # no --frames asked: the end of the file is the end of the run
    assert "end of the video file" in r.stderr and "Traceback" not in r.stderr
    s = json.loads(r.stdout)
    assert s["results"] == len(frames) and s["dropped"] == 0
    got = read_recording(rec)
    assert got.meta["complete"] is True and got.meta["results"] == len(frames) and "end of the video" in got.meta["stopped"]
    np.testing.assert_array_equal(got.data["frames"][:, 0], frames)  # lossless codec: the frames as rendered
    assert got.data["normals"].shape == (len(frames), 60, 80, 3) and np.isfinite(got.data["height"]).all()
    assert (np.diff(got.data["timestamp"]) > 0).all()
    assert not Path(str(rec) + ".parts").exists()
    contact = got.data["contact"]
    assert contact.shape == (len(frames), 60, 80) and contact.dtype == bool and got.meta["drift"] == s["drift"]
    assert s["drift"] == "gain_offset" and s["contact_fraction"] == pytest.approx(contact.mean(), abs=1e-4)
    assert 0.005 < s["contact_fraction"] < 0.3 and all(m.any() for m in contact)
    # Asking for more results than the file has: the same message, exit status 1.
    r = run_cli("live", "--camera", video, "--calibration", cal, "--solver", "lut", "--frames", "50")
    assert r.returncode == 1 and "end of the video file" in r.stderr


def _mjpeg_server(frames, repeat: int):
    """A network camera on 127.0.0.1: ``frames`` (RGB) ``repeat`` times as an MJPEG stream over
    HTTP (what IP cameras serve), then the connection closes: the camera goes away mid-stream."""
    import threading
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    import cv2

    jpgs = [cv2.imencode(".jpg", cv2.cvtColor(f, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
            for f in frames]

    class Stream(BaseHTTPRequestHandler):
        def do_GET(self):
            self.send_response(200)
            self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
            self.end_headers()
            for i in range(repeat * len(jpgs)):
                jpg = jpgs[i % len(jpgs)]
                self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n" % len(jpg)
                                 + jpg + b"\r\n")
                self.wfile.flush()
                time.sleep(0.03)
            self.close_connection = True  # unplugged

        def log_message(self, *args):
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Stream)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_address[1]}/stream.mjpg"


def test_live_camera_unplugged_mid_stream(video_and_calibration, tmp_path):
    """A network camera (MJPEG over real HTTP through OpenCV) stops mid-stream: one clear
    message naming the camera, exit status 1, and the recording closed, consolidated and valid
    with every result made before."""
    from pipeline.live.recorder import read_recording

    _, cal, frames = video_and_calibration
    server, url = _mjpeg_server(frames, repeat=4)
    try:
        rec = tmp_path / "rec.h5"
        r = run_cli("live", "--camera", url, "--calibration", cal, "--solver", "lut", "--record", rec, "--json",
                    "--queue", "64", timeout=120)
    finally:
        server.shutdown()
        server.server_close()
    assert r.returncode == 1, r.stderr
    assert f"camera {url!r}: no frame (the device stopped delivering)" in r.stderr and "Traceback" not in r.stderr
    s = json.loads(r.stdout)
    assert s["results"] >= len(frames) and "stopped delivering" in s["stopped"]
    assert f"the recording {rec} is closed and holds {s['results']} results" in r.stderr
    got = read_recording(rec)
    assert got.meta["complete"] is True and got.meta["results"] == s["results"]
    assert got.data["frames"].shape == (s["results"], 1, 60, 80, 3) and np.isfinite(got.data["height"]).all()
    assert not Path(str(rec) + ".parts").exists()


def test_recording_survives_sigkill(store, tmp_path):
    """SIGKILL a recording process mid-stream: FILE.h5 opens, validates and holds the segments written."""
    from pipeline.live.recorder import read_recording

    rec = tmp_path / "rec.h5"
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", "live", "--virtual", "--size", SIZE, "--cache",
                             str(store), "--mode", "trichromatic", "--solver", "lut", "--seconds", "120", "--record",
                             str(rec)], cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 240
        results = 0
        while time.monotonic() < deadline and results < 40:
            time.sleep(0.3)
            assert proc.poll() is None, proc.stderr.read().decode()
            if rec.exists():
                results = read_recording(rec).meta["results"]
        assert results >= 40
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stderr.close()
    got = read_recording(rec)
    n = got.meta["results"]
    assert got.meta["complete"] is False and n >= 40
    assert got.data["frames"].shape == (n, 1, 60, 80, 3) and got.data["normals"].shape == (n, 60, 80, 3)
    assert np.isfinite(got.data["normals"]).all() and (np.diff(got.data["timestamp"]) > 0).all()
    assert (np.diff(got.data["dropped"]) >= 0).all()


def _ctrl_c_as_in_a_terminal() -> None:
    """In the child before exec: Ctrl-C (SIGINT) back to its default. A test run started as a
    background job of a non-interactive shell (``nohup pytest &``, some CI runners) ignores SIGINT,
    an ignored signal stays ignored across exec, and Python then never installs its handler: the
    live process would sit out the 20 s wait of :func:`_stop_view` and be killed."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start_view(store, *extra):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", "live", "--virtual", "--size", SIZE, "--cache",
                             str(store), "--mode", "trichromatic", "--solver", "lut", "--view", "--view-port", "0",
                             *extra], cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_ctrl_c_as_in_a_terminal)
    url = None
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        if "view at " in line:
            url = line.split("view at ", 1)[1].strip()
            break
    assert url and url.startswith("http://127.0.0.1:"), f"no view URL (exit {proc.poll()})"
    return proc, url


def _get(url, timeout=10):
    with urllib.request.urlopen(url, timeout=timeout) as r:
        return r.status, r.headers.get("Content-Type"), r.read()


def test_live_view_endpoints_over_http(store):
    import cv2

    proc, url = _start_view(store, "--seconds", "60")
    try:
        deadline = time.monotonic() + 60
        stats = {}
        while time.monotonic() < deadline:
            stats = json.loads(_get(url + "stats.json")[2])
            if stats["results"] >= 5:
                break
            time.sleep(0.2)
        assert stats["results"] >= 5 and stats["running"] and stats["mode"] == "trichromatic"
        assert {"fps", "latency_ms_p50", "latency_ms_p99", "dropped", "solver"} <= set(stats)
        status, kind, page = _get(url)
        assert status == 200 and kind.startswith("text/html") and b"stats.json" in page
        for name in ("depth", "normals", "contact"):
            status, kind, body = _get(url + f"{name}.png")
            img = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_UNCHANGED)
            assert status == 200 and kind == "image/png" and img.shape[:2] == (60, 80)
        try:
            _get(url + "nothing")
            raise AssertionError("expected 404")
        except urllib.error.HTTPError as exc:
            assert exc.code == 404
    finally:
        _stop_view(proc)


def _stop_view(proc) -> None:
    """Ctrl-C the live process (killed if it has not ended in 20 s), reading what it still writes to
    stderr meanwhile (a full pipe would block it before it sees the signal)."""
    proc.send_signal(signal.SIGINT)
    try:
        proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()


@pytest.mark.skipif(find_chromium() is None, reason="no headless Chromium installed (apt-get install chromium); "
                                                "the page's endpoints are tested over HTTP regardless")
def test_live_page_in_headless_chromium(store, tmp_path):
    """The page, rendered by a real browser: its script fetched the stats and the three maps."""
    proc, url = _start_view(store, "--seconds", "90")
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and json.loads(_get(url + "stats.json")[2])["results"] < 3:
            time.sleep(0.2)
        flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run",
                 f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=3000"]
        dom = subprocess.run([find_chromium(), *flags, "--dump-dom", url], capture_output=True, text=True, timeout=120)
        assert dom.returncode == 0, dom.stderr[-2000:]
        html = dom.stdout
        assert 'id="fps"' in html and "trichromatic" in html  # filled in from stats.json by the page's script
        import re

        assert re.search(r'<span id="fps">\d+\.\d</span>', html), html[-1500:]
        assert re.search(r'<img id="depth" alt="depth" src="depth\.png\?r=\d+"', html), html[-1500:]
        shot = tmp_path / "page.png"
        subprocess.run([find_chromium(), *flags, f"--screenshot={shot}", "--window-size=1100,700", url],
                       capture_output=True, timeout=120)
        import cv2

        img = cv2.imread(str(shot))
        assert img is not None and img.std() > 5  # not a blank page
    finally:
        _stop_view(proc)


def test_live_bad_input_is_one_line(tmp_path):
    r = run_cli("live", "--camera", tmp_path / "missing.avi", "--calibration", tmp_path / "cal.h5")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    r = run_cli("live", "--virtual", "--mode", "point", "--solver", "lut", "--frames", "1", "--size", "40x30",
                "--cache", tmp_path / "c")
    assert r.returncode == 2 and "one RGB pattern" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "c").exists()  # refused before calibrating anything
