"""The OpenCV camera wrapper on a real video file, and the LED-state virtual camera's buffer."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from pipeline.capture.camera import CameraError, CameraSettingWarning, OpenCVCamera
from pipeline.capture.camera_api import Camera
from pipeline.capture.emulator import ShownState
from pipeline.capture.led_camera import LedStateCamera


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


def _state(t, value, leds=2):
    return ShownState(t, np.full((leds, 3), value, np.uint8), 255)


def test_exposure_spanning_a_change_mixes_the_states():
    hist = _History([_state(-1e9, 0)])
    cam = LedStateCamera(hist, shape=(2, 2), fps=50.0, exposure_s=0.01, buffer_size=2)
    cam.open()
    t0 = cam._t0
    # Frame 1 is exposed over [t0 + 0.02, t0 + 0.03]; the LEDs switch 30 % into it.
    hist.states.append(_state(t0 + 0.023, 200))
    cam.read()  # frame 0: all dark
    f1 = cam.read()
    assert f1.index == 1 and f1.info["states_in_exposure"] == 2
    assert np.allclose(f1.image, 0.7 * 200, atol=1)
    f2 = cam.read()
    assert np.all(f2.image == 200) and f2.info["states_in_exposure"] == 1


def test_queue_is_stale_until_flushed():
    hist = _History([_state(-1e9, 0)])
    cam = LedStateCamera(hist, shape=(2, 2), fps=200.0, buffer_size=3)
    cam.open()
    time.sleep(8 * cam.frame_period)
    hist.states.append(_state(time.monotonic(), 255))
    assert cam.read().image.max() == 0  # the queued frames predate the change
    time.sleep(2 * cam.frame_period)
    assert cam.flush() == 3  # the queue was full; newer frames were dropped by the "driver"
    assert cam.dropped_by_driver > 0
    assert cam.read().image.min() == 255
