"""The OpenCV camera wrapper on a real video file, and the virtual camera's buffer and contacts."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from helpers import wait_until
from pipeline.base.camera import Camera
from pipeline.capture.camera import CameraError, CameraSettingWarning, OpenCVCamera
from pipeline.capture.emulator import ShownState
from pipeline.capture.virtual import ContactCamera
from sim.render import RenderSettings, bare_ring_illumination
from sim.virtual_camera import ring_led_state


@pytest.fixture
def video(tmp_path):
    """A lossless 5-frame clip whose frame i is BGR (10 i, 100, 200)."""
    path = str(tmp_path / "clip.avi")
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"FFV1"), 30, (40, 32))
    assert writer.isOpened()
    for i in range(5):
        writer.write(np.full((32, 40, 3), (10 * i, 100, 200), np.uint8))
    writer.release()
    return path


def test_video_file_frames_rgb_in_order_with_warnings(video):
    cam = OpenCVCamera(video, exposure=-5, gain=0)
    with pytest.warns(CameraSettingWarning):
        cam.open()
    assert isinstance(cam, Camera) and cam.shape == (32, 40)
    assert any("exposure" in w for w in cam.warnings) and any("gain" in w for w in cam.warnings)
    assert cam.flush() == 0  # a file has no driver queue: nothing is skipped
    frames = [cam.read() for _ in range(5)]
    for i, f in enumerate(frames):
        assert f.image.dtype == np.uint8 and f.image.shape == (32, 40, 3)
        assert f.image[0, 0].tolist() == [200, 100, 10 * i]  # RGB, not BGR
    assert [f.index for f in frames] == list(range(5))
    assert all(b.timestamp >= a.timestamp for a, b in zip(frames, frames[1:]))
    with pytest.raises(CameraError, match="end of the video file"):
        cam.read()
    assert cam.describe()["warnings"] == cam.warnings
    cam.close()


def test_missing_camera_is_a_clear_error(tmp_path):
    with pytest.raises(CameraError, match="no such device or video file; video devices here"):
        OpenCVCamera(str(tmp_path / "nope.avi")).open()


class _History:
    """A fixed LED history (a real implementation of ``states_during``)."""

    def __init__(self, states):
        self.states = states

    def states_during(self, t0, t1):
        before = [s for s in self.states if s.t <= t0][-1:]
        return before + [s for s in self.states if t0 < s.t <= t1]


def _state(t, value, leds=24):
    return ShownState(t, np.full((leds, 3), value, np.uint8), 255)


def _camera(hist, fps, buffer_size=4, contacts=()):
    model = bare_ring_illumination((4, 6), 1.0)
    return ContactCamera(model, ring_led_state(hist), list(contacts),
                         settings=RenderSettings(exposure=1e5), fps=fps, buffer_size=buffer_size)


def test_virtual_camera_queue_is_stale_until_flushed():
    hist = _History([_state(-1e9, 0)])
    # 20 ms frames: the camera's thread may be woken a frame late on a loaded machine and still
    # have every exposure after the change begin after it.
    cam = _camera(hist, fps=50.0, buffer_size=3)
    cam.open()
    try:
        wait_until(lambda: cam.buffered == 3)
        t_change = time.monotonic()
        hist.states.append(_state(t_change, 255))
        assert cam.read().image.max() == 0  # the queued frames predate the change
        dropped = cam.dropped
        wait_until(lambda: cam.dropped > dropped)
        assert cam.flush() == 3  # the queue was full: older frames were pushed out
        frame = cam.read()
        assert frame.info["exposure_window"][0] >= t_change and frame.image.min() > 0
    finally:
        cam.close()


def test_virtual_camera_shows_the_contact_it_is_told_from_the_next_exposure():
    from sim.geometry import sphere

    hist = _History([_state(-1e9, 255)])
    ball = sphere((4, 6), 1.0, radius=3.0, depth=1.0)
    cam = _camera(hist, fps=500.0, contacts=[ball])
    cam.open()
    try:
        flat = cam.read()
        assert flat.info["contact"] == -1
        t_set = time.monotonic()
        cam.set_contact(0)
        cam.flush()
        frame = cam.read()
        while frame.info["exposure_window"][0] < t_set:  # begun before the press: flat gel
            assert frame.info["contact"] == -1
            frame = cam.read()
        assert frame.info["contact"] == 0
        # The ball tilts the gel under it: the pixels change where it presses, not elsewhere.
        diff = np.abs(frame.image - flat.image).max(axis=2)
        assert diff[ball.contact].min() > 1e-3 * flat.image.max()
        assert np.allclose(diff[~ball.contact], 0, atol=1e-3 * flat.image.max())
        with pytest.raises(ValueError, match=r"k must be in \[-1, 1\)"):
            cam.set_contact(1)
    finally:
        cam.close()
