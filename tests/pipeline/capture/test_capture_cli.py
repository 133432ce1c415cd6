"""``iristac capture`` and ``iristac emulate-ring`` through a subprocess."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import numpy as np

from helpers import REPO, run_cli
from pipeline.base.store import read_record
from pipeline.capture.client import RingClient

FAST = ["--emulate", "--virtual-camera", "--mode", "point", "--camera-fps", "500",
        "--camera-size", "6", "8", "--timeout", "0.01"]


def test_capture_json_keys_with_faults(tmp_path):
    out = tmp_path / "capture.h5"
    r = run_cli("capture", *FAST, "--faults", "drop=0.05,corrupt=0.05", "--seed", "3",
                "--out", out, "--json", timeout=120)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert sorted(summary) == ["frames", "mislabeled", "patterns", "retries", "seconds"]
    assert summary["frames"] == 49 and summary["patterns"] == 24
    assert summary["mislabeled"] == 0 and summary["retries"] > 0
    rec = read_record(out, schema="capture")
    assert rec.meta["mode"] == "point" and rec.data["reference"].shape == (24, 6, 8, 3)
    assert rec.data["truth/height"].shape == (1, 6, 8) and rec.meta["source"] == "virtual"
    # The point mode lights one LED at a time: LED 0 sits at +x (right of the image), LED 12
    # at -x, so the right column is brighter under LED 0 and the left one under LED 12.
    ref = rec.data["reference"].astype(float).mean(axis=3)
    assert ref[0][:, -1].mean() > ref[0][:, 0].mean() and ref[12][:, 0].mean() > ref[12][:, -1].mean()


def test_objects_from_a_height_map_stack_and_the_indenter_set(tmp_path):
    stack = np.zeros((2, 6, 8))
    stack[1, 2:4, 3:5] = 0.3
    np.save(tmp_path / "h.npy", stack)
    out = tmp_path / "c.h5"
    r = run_cli("capture", *FAST, "--mode", "trichromatic", "--object", tmp_path / "h.npy",
                "--bit-depth", "0", "--noise", "0", "--out", out, "--json", timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["frames"] == 1 + 1 + 2
    d = read_record(out, schema="capture").data
    assert np.array_equal(d["truth/height"], stack.astype(np.float32))
    # Noise-free: the flat contact renders exactly as the reference, the bump does not.
    assert np.allclose(d["frames"][0, 0], d["reference"][0])
    assert not np.allclose(d["frames"][1, 0], d["reference"][0])


def test_disconnect_then_rerun_resumes(tmp_path):
    out = tmp_path / "capture.h5"
    r = run_cli("capture", *FAST, "--faults", "disconnect-after=31", "--out", out, "--json",
                timeout=120)
    assert r.returncode == 2
    err = r.stderr.strip().splitlines()[-1]
    # Without retransmissions the 31st frame on the wire falls in step 16; a reply timeout on a
    # loaded machine makes the client resend, which uses up frames sooner. Either way, what was
    # saved must be exactly what the rerun takes over.
    saved = re.search(r"(\d+) of 49 steps are saved", err)
    assert "disconnected during" in err and saved and 1 <= int(saved.group(1)) <= 15, err
    assert "rerun the same command to resume" in err and not out.exists()
    r = run_cli("capture", *FAST, "--out", out, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "49 frames" in r.stdout and "0 mislabeled" in r.stdout
    assert f"resumed {saved.group(1)} saved frames" in r.stdout
    assert read_record(out, schema="capture").meta["runs"] == 2


def test_bad_arguments_are_one_line_errors(tmp_path):
    r = run_cli("capture", "--port", "/dev/ttyIRISTAC-NOPE", "--camera", "0", "--mode", "point",
                "--out", tmp_path / "c.h5")
    assert r.returncode == 2
    assert r.stderr.strip().startswith("iristac capture: error: serial port "
                                       "'/dev/ttyIRISTAC-NOPE' does not exist")
    r = run_cli("capture", *FAST, "--faults", "drop=7", "--out", tmp_path / "c.h5")
    assert r.returncode == 2 and "--faults: drop=7.0 must be a probability" in r.stderr


def test_emulate_ring_serves_a_pty_until_stopped():
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen(
        [sys.executable, "-m", "pipeline", "emulate-ring", "--leds", "12", "--duration", "20"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO,
    )
    try:
        path = proc.stdout.readline().strip()
        assert path.startswith("/dev/"), path
        with RingClient(path, timeout=0.2) as ring:
            assert ring.info.led_count == 12
            ring.show_pattern(np.ones((12, 3)), 0.5)
            assert ring.status().latch_count == 1
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_emulate_ring_wrong_version_is_caught_by_the_host():
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen(
        [sys.executable, "-m", "pipeline", "emulate-ring", "--protocol-version", "9",
         "--duration", "20"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO,
    )
    try:
        path = proc.stdout.readline().strip()
        r = run_cli("capture", "--port", path, "--camera", "0", "--mode", "point",
                    "--out", "/tmp/never-written.h5")
        assert r.returncode == 2
        assert "speaks ring protocol version 9, this host speaks version 1" in r.stderr
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_capture_with_an_opencv_video_file_as_camera(tmp_path):
    """The OpenCV path end to end: a recorded video stands in for the webcam."""
    import cv2

    clip = str(tmp_path / "clip.avi")
    writer = cv2.VideoWriter(clip, cv2.VideoWriter_fourcc(*"FFV1"), 30, (40, 32))
    for i in range(60):
        writer.write(np.full((32, 40, 3), (i, 2 * i, 3 * i), np.uint8))  # BGR
    writer.release()
    out = tmp_path / "c.h5"
    r = run_cli("capture", "--emulate", "--camera", clip, "--mode", "point", "--settle", "0",
                "--timeout", "0.01", "--out", out, "--json", timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["frames"] == 49
    rec = read_record(out, schema="capture")
    assert rec.meta["source"] == "camera" and rec.meta["device"]["camera"]["kind"] == "opencv"
    # Frames are stored in capture order, RGB: dark = video frame 0, reference p = frame 1 + p.
    assert rec.data["dark"][0, 0].tolist() == [0, 0, 0]
    assert rec.data["reference"][4][0, 0].tolist() == [15, 10, 5]
    assert rec.data["frames"][0, 0][0, 0].tolist() == [75, 50, 25]
