"""Video recordings through ``iristac batch`` and ``iristac reconstruct`` without converting them
first (:mod:`pipeline.capture.video_frames`): a real video written with OpenCV from rendered
frames, against the same frames written as a capture file.

The video is FFV1 in AVI: lossless in this OpenCV build (a probe wrote and read back random frames
bit for bit; MJPG and mp4v lose up to 240 DN on such frames), so the two runs must agree exactly.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from helpers import run_cli
from pipeline.base.store import Record, read_record, write_record

SHAPE, PX, FRAMES = (24, 32), 0.25, 12


def _write_video(path, frames_rgb):
    import cv2

    H, W = frames_rgb.shape[1:3]
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 10.0, (W, H))
    assert w.isOpened()
    for f in frames_rgb:
        w.write(np.ascontiguousarray(f[..., ::-1]))
    w.release()


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    """``rec.avi``: the no-contact frame, then the presses; ``rec.h5``: the same frames as a
    capture file (as ``iristac import images`` writes a video); a far-field calibration of three
    colour lights (with ``mm_per_px``, which the video takes)."""
    from pipeline.base.capture import write_capture
    from sim.contacts import contact_surfaces
    from sim.render import bare_ring_illumination
    from sim.rendered_capture import render_capture

    d = tmp_path_factory.mktemp("video")
    model = bare_ring_illumination(SHAPE, PX)
    surfaces = contact_surfaces("sphere", SHAPE, PX, FRAMES, size_mm=2.0, depth_mm=0.4, spread_mm=1.5, seed=3)
    cap = render_capture(model, "trichromatic", surfaces, seed=5)
    frames, ref = cap.data["frames"], cap.data["reference"]
    _write_video(d / "rec.avi", np.concatenate([ref, frames[:, 0]]))
    from pipeline.capture.video_frames import video_capture

    vc = video_capture(d / "rec.avi", mm_per_px=PX)  # the rendered frames with the video capture's attributes
    write_capture(d / "rec_h5.h5", Record("capture", {**vc.data, "frames": frames, "reference": ref}, dict(vc.meta)))
    az = np.deg2rad([90.0, 210.0, 330.0])
    lv = np.stack([np.cos(az), np.sin(az), np.ones(3)], -1) / np.sqrt(2)
    cal = write_record(d / "cal.h5", Record("calibration", {"circles": np.zeros((0, 4), np.float32),
                                                            "light_vectors": lv[None].astype(np.float32)},
                                            {"mm_per_px": PX, "ball_radius_mm": 1.0, "models": []}))
    return {"dir": d, "avi": d / "rec.avi", "h5": d / "rec_h5.h5", "cal": cal, "frames": frames, "ref": ref}


def _batch(recs, video, store, *extra, ok=True):
    r = run_cli("batch", *recs, "--calibration", video["cal"], "--solver", "lstsq", "--cache", store,
                "--threads", "1", "--json", *extra)
    assert (r.returncode == 0) == ok, r.stderr
    return json.loads(r.stdout)


def test_the_video_reader_reads_any_range_in_rgb_and_leaves_the_reference_out(video):
    from pipeline.capture.video_frames import video_capture

    cap = video_capture(video["avi"], reference=0, mm_per_px=PX)
    frames = cap.data["frames"]
    assert frames.shape == (FRAMES, 1) + SHAPE + (3,) and frames.dtype == np.uint8
    np.testing.assert_array_equal(cap.data["reference"], video["ref"])
    np.testing.assert_array_equal(frames[3:7], video["frames"][3:7])
    np.testing.assert_array_equal(frames[1:2], video["frames"][1:2])  # an earlier range: reopened
    with frames.reader() as r:
        dst = np.empty((4, 1) + SHAPE + (3,), np.uint8)
        r.read_into(dst, 8, 12)
        np.testing.assert_array_equal(dst, video["frames"][8:12])
    # Video frame 5 (rendered press 4) as the reference is left out: frames 3, 4, 5 are video frames 3, 4, 6.
    mid = video_capture(video["avi"], reference=5, mm_per_px=PX)
    np.testing.assert_array_equal(mid.data["reference"], video["frames"][4:5, 0])
    np.testing.assert_array_equal(mid.data["frames"][3:6], video["frames"][[2, 3, 5]])
    np.testing.assert_array_equal(mid.data["frames"][0][0], video["ref"][0])


def test_a_video_batches_as_its_frames_written_as_a_capture_file(video, tmp_path):
    out = _batch([video["avi"], video["h5"]], video, tmp_path / "store", "--out", tmp_path / "out")
    assert out["failed"] == 0, out
    a, b = out["items"]
    assert a["result"]["frames"] == b["result"]["frames"] == FRAMES
    assert a["result"]["normals_sha256"] == b["result"]["normals_sha256"]  # lossless codec: the same normals
    assert a["result"]["depth_sha256"] == b["result"]["depth_sha256"]
    n_v = read_record(tmp_path / "out" / "rec" / "normals.h5", "normals").data["normals"]
    assert n_v.shape == (FRAMES,) + SHAPE + (3,)
    # A rerun is read from the store; another reference is other work.
    again = _batch([video["avi"]], video, tmp_path / "store")
    assert again["frames_solved"] == 0 and again["items"][0]["method"] == "cached"
    other = _batch([video["avi"]], video, tmp_path / "store", "--reference", "3")
    assert other["frames_solved"] == FRAMES
    assert other["items"][0]["result"]["normals_key"] != a["result"]["normals_key"]


def test_reconstruct_takes_a_video_and_a_built_reference(video, tmp_path):
    r = run_cli("reconstruct", video["avi"], "--calibration", video["cal"], "--solver", "lstsq", "--reference",
                "build", "--mm-per-px", str(PX), "--cache", tmp_path / "store", "--out", tmp_path / "out",
                "--no-images", "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["frames"] == FRAMES + 1 and s["valid_fraction"] > 0.5  # built: every frame is a recording frame
    from pipeline.capture.video_frames import video_capture

    built = video_capture(video["avi"], reference="build", mm_per_px=PX)
    # Most pixels of the built reference are the no-contact gel's.
    close = np.abs(built.data["reference"].astype(int) - video["ref"].astype(int)).max(-1) <= 3
    assert close.mean() > 0.9, close.mean()


def test_a_truncated_video_fails_alone_in_one_line(video, tmp_path):
    data = video["avi"].read_bytes()
    bad = tmp_path / "cut.avi"
    bad.write_bytes(data[: len(data) // 2])
    out = _batch([bad, video["h5"]], video, tmp_path / "store", ok=False)
    assert out["failed"] == 1 and out["processed"] == 1
    err = out["items"][0]["error"]
    assert "cut.avi" in err and "truncated" in err and "\n" not in err, err


def test_a_video_needs_a_pixel_pitch(video, tmp_path):
    from pipeline.base.errors import UserError
    from pipeline.streaming.inputs import read_capture

    with pytest.raises(UserError, match="rec.avi: a video needs the pixel pitch"):
        read_capture(video["avi"], {"reference": 0})


def test_with_workers_a_video_runs_in_the_planning_process_and_equals_a_serial_run(video, tmp_path):
    serial = _batch([video["avi"], video["h5"]], video, tmp_path / "a")
    spread = _batch([video["avi"], video["h5"]], video, tmp_path / "b", "--workers", "2")
    assert spread["failed"] == 0, spread
    for s, w in zip(serial["items"], spread["items"]):
        assert s["result"]["normals_sha256"] == w["result"]["normals_sha256"]
    assert spread["items"][0]["ok"] and spread["frames_solved"] == 2 * FRAMES
