"""The virtual camera behaves like a webcam: a small FIFO buffer makes frames stale after a pattern change."""

import numpy as np
import pytest

from helpers import wait_until
from pipeline.base.camera import Camera
from pipeline.base.modes import mode_drive
from sim.geometry import sphere
from sim.render import Renderer, RenderSettings, auto_exposure, bare_ring_illumination
from sim.virtual_camera import VirtualCamera, ring_led_state

SHAPE = (12, 16)
PX = 0.5
FPS = 50.0


@pytest.fixture(scope="module")
def model():
    return bare_ring_illumination(SHAPE, PX)


class Ring:
    """The LED state a test sets (what the ring shows)."""

    def __init__(self, drive):
        self.drive = np.asarray(drive, float)

    def __call__(self):
        return self.drive, 1.0


def test_stale_frame_without_flush_and_fresh_with_flush_and_settle(model):
    A, B = mode_drive("monochromatic")[0], mode_drive("monochromatic")[1]
    ring = Ring(A)
    s = RenderSettings(exposure=1e5, read_noise=1.0, bit_depth=8, seed=3)
    cam = VirtualCamera(model, ring, settings=s, fps=FPS, buffer_size=4)
    assert isinstance(cam, Camera)
    cam.open()
    try:
        wait_until(lambda: cam.buffered == 4)  # buffer full of pattern A
        ring.drive = B  # the ring changes pattern
        stale = cam.read()  # forgot to flush: the oldest buffered frame is still pattern A
        np.testing.assert_array_equal(stale.info["drive"], A)
        # and its pixels really are pattern A (deterministic: the seed of that frame index)
        ref = Renderer(model, s)
        np.testing.assert_array_equal(stale.image, ref.render(A, 1.0, seed=cam.frame_seed(stale.index)))
        # Settle: two more frames queued (the second overflows the queue), so the frame exposing
        # during the change has finished, whenever the camera's thread gets to run.
        dropped = cam.dropped
        wait_until(lambda: cam.dropped > dropped)
        assert cam.flush() >= 1
        fresh = cam.read()
        np.testing.assert_array_equal(fresh.info["drive"], B)
        assert fresh.index > stale.index and fresh.timestamp > stale.timestamp
        assert not np.array_equal(fresh.image, stale.image)
    finally:
        cam.close()


def test_buffer_drops_oldest_and_indices_count_frames(model):
    cam = VirtualCamera(model, Ring(np.ones((24, 3))), settings=RenderSettings(exposure=1e5), fps=200.0,
                        buffer_size=2)
    cam.open()
    try:
        wait_until(lambda: cam.dropped >= 3)
        with cam._cond:  # freeze the producer to look at the queue: the newest frames, in order
            kept = [e.index for e in cam._buffer]
            assert kept == [cam.dropped, cam.dropped + 1]
        a = cam.read()
        b = cam.read()
        assert a.index >= 3 and b.index > a.index
    finally:
        cam.close()
    with pytest.raises(RuntimeError, match="not open"):
        cam.read()


def test_scripted_contact_and_seeded_frames(model):
    press = sphere(SHAPE, PX, 2.0, 0.8)
    drive = mode_drive("monochromatic")[0]  # one sector: strong shading contrast on the bump
    s = RenderSettings(exposure=auto_exposure(model, drive, target_dn=200.0), read_noise=2.0, seed=11)
    cam = VirtualCamera(model, Ring(drive), script=[(0.0, None), (0.06, press)], settings=s, fps=FPS)
    assert cam.contact_at(0.0) == 0 and cam.contact_at(0.07) == 1 and cam.contact_at(-1.0) == -1
    cam.open()
    try:
        frames = [cam.read() for _ in range(6)]
    finally:
        cam.close()
    contacts = [f.info["contact"] for f in frames]
    assert contacts[0] == 0 and contacts[-1] == 1 and contacts == sorted(contacts)
    ref = Renderer(model, s)
    for f in frames:
        ref.set_surface(press if f.info["contact"] == 1 else None)
        np.testing.assert_array_equal(f.image, ref.render(drive, 1.0, seed=cam.frame_seed(f.index)))
    flat = next(f for f in frames if f.info["contact"] == 0).image
    pressed = next(f for f in frames if f.info["contact"] == 1).image
    assert np.abs(pressed - flat)[press.contact].mean() > 5 * 2.0


def test_ring_emulator_state_adapter():
    class Shown:
        levels = np.array([[255, 0, 51]] * 24, np.uint8)
        brightness = 128

    class FakeHistory:
        def states_during(self, t0, t1):
            return [Shown()]

    drive, b = ring_led_state(FakeHistory())()
    assert drive.shape == (24, 3) and drive[0].tolist() == [1.0, 0.0, 0.2] and b == pytest.approx(128 / 255)


def test_bad_script_is_rejected(model):
    with pytest.raises(ValueError, match="must not decrease"):
        VirtualCamera(model, Ring(np.ones((24, 3))), script=[(1.0, None), (0.5, None)])
    with pytest.raises(ValueError, match=r"shape \(12, 16\)"):
        VirtualCamera(model, Ring(np.ones((24, 3))), script=[(0.0, sphere((5, 5), PX, 1.0, 0.2))])
