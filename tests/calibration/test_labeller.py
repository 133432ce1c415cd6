"""The labeller (``iristac label``): saved into the capture and the CSV at every edit, resumable,
atomic; tested over real HTTP, and with real mouse drags in headless Chromium where installed."""

from __future__ import annotations

import http.client
import json
import shutil
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest

from calibration.image_import import read_labels_csv
from calibration.label_page import LabelServer
from calibration.label_session import LabelSession
from calibration.labels import capture_label_circles
from cdp_chromium import Chromium, find_chromium
from pipeline.base import store
from pipeline.base.capture import read_capture
from pipeline.base.errors import UserError
from sim.virtual_sensor import random_sensor, write_sensor_capture


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """A small capture of three presses (no flaws: the detector finds them), written once."""
    path = tmp_path_factory.mktemp("label") / "src.h5"
    out = write_sensor_capture(path, random_sensor(21, shape=(60, 80), num_presses=3, effects="none",
                                                   border_fraction=0.0))
    return path, out.truth


@pytest.fixture
def capture(source, tmp_path):
    path = tmp_path / "cap.h5"
    shutil.copyfile(source[0], path)
    return path


def _get(url):
    with urllib.request.urlopen(url, timeout=30) as r:
        return r.status, r.headers.get("Content-Type"), r.read()


def _post(url, body, kind="application/json"):
    req = urllib.request.Request(url, data=json.dumps(body).encode(), headers={"Content-Type": kind}, method="POST")
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read())


def test_edits_over_http_are_saved_and_resume(capture, source):
    truth = source[1]
    server = LabelServer(LabelSession(capture))
    try:
        code, kind, page = _get(server.url)
        assert code == 200 and kind.startswith("text/html") and b'id="svg"' in page and b"http" not in page.split(
            b"<script>")[0].replace(b'xmlns="http://www.w3.org/2000/svg"', b"")  # no external resources
        state = json.loads(_get(server.url + "api/state")[2])
        assert state["undecided"] == 3 and state["shape"] == [60, 80]
        p0 = json.loads(_get(server.url + "api/press/0")[2])
        det = p0["detected"]
        assert det["accepted"] and abs(det["x"] - truth.center_xy[0, 0]) < 1.5 and det["reason"]
        for kind_ in ("frame", "diff"):
            code, ctype, png = _get(server.url + f"img/{kind_}/1.png")
            img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
            assert ctype == "image/png" and img.shape == (60, 80, 3)
        code, res = _post(server.url + "api/press/0", {"action": "set", "x": 40.25, "y": 30.5, "radius_px": 7.5})
        assert code == 200 and res["press"]["status"] == "labelled"
        cap = read_capture(capture)  # saved before the answer came
        np.testing.assert_allclose(cap.labels["center_xy"][0], [40.25, 30.5])
        assert np.isnan(cap.labels["radius_px"][1]) and not cap.labels["rejected"].any()
        assert _post(server.url + "api/press/1", {"action": "reject"})[0] == 200
        assert _post(server.url + "api/press/2", {"action": "set", "x": 10, "y": 11, "radius_px": 5})[0] == 200
        assert _post(server.url + "api/press/2", {"action": "clear"})[0] == 200
        # bad requests: a clear error each, nothing saved
        assert _post(server.url + "api/press/0", {"action": "set", "x": 500, "y": 3, "radius_px": 5})[0] == 400
        assert "unknown action" in _post(server.url + "api/press/0", {"action": "bogus"})[1]["error"]
        assert _post(server.url + "api/press/0", {"action": "reject"}, kind="text/plain")[0] == 415
        assert _post(server.url + "api/press/9", {"action": "reject"})[0] == 400
        assert json.loads(_get_error(server.url + "api/press/9"))["error"].endswith("0..2)")
        host, port = server.server.server_address[:2]
        conn = http.client.HTTPConnection(host, port, timeout=10)
        conn.request("GET", "/api/state", headers={"Host": f"evil.example:{port}"})
        assert conn.getresponse().status == 403
    finally:
        server.close()
    # reopened: the page's state is what was saved
    again = LabelSession(capture).summary()
    assert [p["status"] for p in again["presses"]] == ["labelled", "rejected", "undecided"]
    assert again["presses"][0]["label"] == {"x": 40.25, "y": 30.5, "radius_px": 7.5}
    lines = (capture.parent / "cap.labels.csv").read_text().splitlines()
    assert lines == ["name,x,y,radius_px", "press0,40.250,30.500,7.500", "press1,,,", "# press2: not labelled"]
    cap = read_capture(capture)
    circles = capture_label_circles(cap, 20.0)
    assert circles[0].accepted and not circles[1].accepted and "rejected by hand" in circles[1].reason


def _get_error(url):
    try:
        urllib.request.urlopen(url, timeout=30)
    except urllib.error.HTTPError as e:
        return e.read()
    raise AssertionError(f"{url} did not fail")


def test_csv_imports_back_with_rejected_presses(tmp_path):
    csv = tmp_path / "l.csv"
    csv.write_text("name,x,y,radius_px\npress0,4.000,5.000,6.000\npress1,,,\n")
    lab = read_labels_csv(csv, ["press0", "press1"])
    assert lab["rejected"].tolist() == [False, True] and np.isnan(lab["radius_px"][1])
    csv.write_text("name,x,y,radius_px\npress0,4.000,5.000,6.000\n# press1: not labelled\n")
    with pytest.raises(UserError, match="no label for press"):
        read_labels_csv(csv, ["press0", "press1"])


def test_a_failed_save_leaves_the_capture_whole(capture, monkeypatch):
    s = LabelSession(capture)
    s.set_label(0, 20.0, 20.0, 6.0)
    before = capture.read_bytes()

    def crash(*_a, **_k):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(store.os, "replace", crash)
    with pytest.raises(OSError, match="simulated"):
        s.set_label(0, 30.0, 30.0, 6.0)
    monkeypatch.undo()
    assert capture.read_bytes() == before  # untouched: the change was made on a copy
    assert not list(capture.parent.glob(".*.tmp.h5"))
    np.testing.assert_allclose(read_capture(capture).labels["center_xy"][0], [20.0, 20.0])


def test_cli_serves_and_reports(capture, capsys):
    from pipeline.cli import main

    LabelSession(capture).reject(2)
    assert main(["label", str(capture), "--port", "0", "--seconds", "0.3", "--json"]) == 0
    out = capsys.readouterr()
    res = json.loads(out.out)
    assert res["rejected"] == 1 and res["undecided"] == 2 and res["saves"] == 0 and "http://127.0.0.1:" in out.err
    assert main(["label", str(capture.parent / "missing.h5"), "--port", "0", "--seconds", "0"]) == 2


# -- the page in a real browser ---------------------------------------------------------------

@pytest.mark.skipif(find_chromium() is None, reason="no headless Chromium installed (apt-get install chromium); the "
                                                  "labeller's endpoints are tested over HTTP regardless")
def test_drag_and_resize_in_headless_chromium(capture):
    session = LabelSession(capture)
    server = LabelServer(session)
    try:
        with Chromium(width=1200, height=900) as browser:
            page = browser.open(server.url + "?press=0",
                                ready="window.labeller !== undefined && window.labeller.ready === true")
            scale = page.evaluate("window.labeller.scale")
            det = page.evaluate("window.labeller.press.detected")
            page.click("#accept")  # the button, clicked with the mouse
            page.wait_for("window.labeller.saved === 1 && window.labeller.saving === 0")
            cx, cy, r = page.evaluate("(() => { const b = document.getElementById('lab').getBoundingClientRect(); "
                                      "return [b.x + b.width / 2, b.y + b.height / 2, b.width / 2]; })()")
            page.drag(cx, cy, cx + 30, cy + 20)  # move: drag inside the circle
            page.wait_for("window.labeller.saved === 2 && window.labeller.saving === 0")
            page.drag(cx + 30 + r, cy + 20, cx + 30 + r + 16, cy + 20)  # resize: drag the handle on the rim
            page.wait_for("window.labeller.saved === 3 && window.labeller.saving === 0")
            page.click("#next")
            page.wait_for("window.labeller.press && window.labeller.press.index === 1")
            page.click("#reject")
            page.wait_for("window.labeller.saved === 4 && window.labeller.saving === 0")
            assert page.evaluate("window.labeller.errors") == 0
            assert page.evaluate("document.getElementById('press-1').className").startswith("rejected")
            assert page.errors == []
    finally:
        server.close()
    lab = read_capture(capture).labels
    np.testing.assert_allclose(lab["center_xy"][0], [det["x"] + 30 / scale, det["y"] + 20 / scale], atol=0.6)
    assert abs(lab["radius_px"][0] - (det["radius_px"] + 16 / scale)) < 0.6
    assert lab["rejected"].tolist() == [False, True, False]
    assert "press1,,," in (capture.parent / "cap.labels.csv").read_text()


def test_a_capture_with_printed_markers_is_detected_as_calibrate_detects_it(tmp_path):
    """The labeller shows the circles calibration uses: markers filled in and left out of the drift
    fit (a capture carrying a marker mask once crashed it on an import)."""
    from calibration.detect import detect_contacts
    from pipeline.base.capture import write_capture
    from pipeline.normals.prepare import fill_markers

    sensor = random_sensor(21, shape=(120, 160), num_presses=3, effects=("markers",), border_fraction=0.0)
    path = tmp_path / "markers.h5"
    out = write_sensor_capture(path, sensor)
    cap = read_capture(path)
    cap.markers = np.asarray(out.truth.markers, bool)
    assert cap.markers.any()
    write_capture(path, cap)
    session = LabelSession(path)
    frames, ref = cap.linear()
    frames, ref = fill_markers(frames, cap.markers), fill_markers(ref, cap.markers)
    expected = detect_contacts(frames[:1], ref, session.ball_radius_px, exclude=cap.markers)[0]
    got = session.detected(0)
    assert got.accepted and np.allclose(got.center_xy, expected.center_xy)
    assert got.radius_px == pytest.approx(expected.radius_px)
