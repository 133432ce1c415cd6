"""The capture plan over a real pty and the rendering virtual camera: labels, stale frames,
resume after a disconnect, the journal."""

from __future__ import annotations

import re
import time

import numpy as np
import pytest

from pipeline.base.errors import UserError
from pipeline.base.modes import LightingMode
from pipeline.base.store import read_record
from pipeline.capture.client import RingClient, RingDisconnected
from pipeline.capture.emulator import FaultSpec, parse_faults
from pipeline.capture.plan import (
    CaptureSettings,
    _fingerprint,
    _Journal,
    journal_path,
    plan_steps,
    run_capture,
)
from pipeline.capture.protocol import quantize_state
from pipeline.capture.virtual import ContactCamera, VirtualSensorSpec, open_virtual_camera
from sim.render import RenderSettings, bare_ring_illumination, render_images
from sim.virtual_camera import ring_led_state

SHAPE = (4, 6)


@pytest.fixture(autouse=True)
def one_torch_thread():
    """The renderer's tiny matrix products spin torch's thread pool on shared cores: one thread
    is several times faster here (see ``iristac bench render``)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
# Noise-free float frames: every pixel is an exact function of the LED state and the surface,
# so a stored frame can be checked against a rendering of the pattern it is labelled with.
EXACT = RenderSettings(exposure=1e5)


def random_patterns(n: int, seed: int = 0, leds: int = 24) -> LightingMode:
    rng = np.random.default_rng(seed)
    return LightingMode.from_arrays("random", [f"p{i}" for i in range(n)], rng.random((n, leds, 3)),
                                    rng.uniform(0.2, 1.0, n))


def levels_of(patterns: LightingMode, p: int):
    """The 8-bit state pattern ``p`` puts on the wire."""
    return quantize_state(patterns.drive[p], float(patterns.brightness[p]))


def spec_for(patterns: LightingMode, contacts: int = 0, fps: float = 2000.0) -> VirtualSensorSpec:
    from sim.contacts import contact_surfaces

    model = bare_ring_illumination(SHAPE, 1.0, count=patterns.num_leds)
    return VirtualSensorSpec(illumination=model, settings=EXACT, fps=fps,
                             contacts=contact_surfaces("sphere", SHAPE, 1.0, contacts))


def expected(spec: VirtualSensorSpec, patterns: LightingMode, k: int = -1) -> np.ndarray:
    """Noise-free renderings (P, H, W, 3) of every pattern, as the ring latched it, on contact
    ``k`` (-1: the flat gel)."""
    levels = np.stack([levels_of(patterns, p)[0] for p in range(len(patterns.frames))]) / 255.0
    b = np.array([levels_of(patterns, p)[1] for p in range(len(patterns.frames))]) / 255.0
    surface = spec.surfaces()[k] if k >= 0 else None
    return render_images(spec.model(), surface, levels, b, settings=EXACT)


def decoded_ok(image: np.ndarray, want: np.ndarray) -> bool:
    """Is ``image`` the rendering ``want`` (up to float32 rounding)?"""
    return np.allclose(image, want, rtol=1e-4, atol=1e-3)


def capture_with(emu, patterns, out, settings, timeout=0.005, fps=2000.0, warm_up=0.0):
    spec = spec_for(patterns, settings.contacts, fps)
    with RingClient(emu.path, timeout=timeout, retries=25) as ring:
        cam = open_virtual_camera(spec, emu, patterns.drive, patterns.brightness)
        try:
            time.sleep(warm_up)  # let the camera's queue fill, as a webcam left running does
            return run_capture(patterns, ring, cam, out, settings, truth=emu, progress=False,
                               source="virtual", on_contact=cam.set_contact)
        finally:
            cam.close()


def test_1000_pattern_changes_with_drops_and_corruption_zero_mislabeled(tmp_path, ring_backend):
    patterns = random_patterns(1000)
    out = tmp_path / "capture.h5"
    faults = parse_faults("drop=0.05,corrupt=0.05")
    with ring_backend.emulator(faults=faults, seed=5) as emu:
        result = capture_with(emu, patterns, out, CaptureSettings(contacts=0))
        st = emu.stats
    assert st.dropped_in + st.dropped_out > 50 and st.corrupted_in + st.corrupted_out > 50
    assert result.retries > 50
    assert result.mislabeled == 0 and result.frames == 1001
    rec = read_record(out, schema="capture")
    ref = rec.data["reference"]
    # Independent of the timestamps: every stored frame is the rendering of its own pattern.
    want = expected(spec_for(patterns), patterns)
    assert all(decoded_ok(ref[p], want[p]) for p in range(1000))
    assert not rec.data["dark"].any()
    assert not journal_path(out).exists()


def test_skipping_the_stale_frame_flush_is_caught(tmp_path, ring_backend):
    """Without flushing, the webcam-like queue of the virtual camera hands back frames from
    the previous pattern: the emulator's history and the rendered pixels both say so."""
    patterns = random_patterns(12, seed=1)
    settings = CaptureSettings(contacts=0, dark=False, stale_frame_guard=False)
    with ring_backend.emulator() as emu:
        # A camera left running has a full queue of frames from before the capture; once it
        # is drained, a read waits for the frame being exposed, which began (and sampled the
        # LEDs) before the pattern changed. So every unflushed frame is stale.
        cam = dict(fps=100.0, warm_up=0.06)
        bad = capture_with(emu, patterns, tmp_path / "bad.h5", settings, **cam)
        good = capture_with(emu, patterns, tmp_path / "good.h5",
                            CaptureSettings(contacts=0, dark=False), **cam)
    want = expected(spec_for(patterns), patterns)
    assert bad.mislabeled == 12
    ref = read_record(tmp_path / "bad.h5").data["reference"]
    assert sum(not decoded_ok(ref[p], want[p]) for p in range(12)) >= 10
    assert good.mislabeled == 0
    ref = read_record(tmp_path / "good.h5").data["reference"]
    assert all(decoded_ok(ref[p], want[p]) for p in range(12))


def test_disconnect_mid_capture_then_resume(tmp_path, ring_backend):
    patterns = random_patterns(8, seed=2)
    settings = CaptureSettings(contacts=2)
    out = tmp_path / "capture.h5"
    steps = plan_steps(8, settings)
    with ring_backend.emulator(faults=parse_faults("disconnect-after=20")) as emu:
        with pytest.raises(RingDisconnected) as err:
            capture_with(emu, patterns, out, settings)
    msg = str(err.value)
    assert "disconnected during" in msg and "rerun the same command to resume" in msg
    journal = _Journal(journal_path(out), _fingerprint(patterns, settings, SHAPE), out)
    saved = {s.id: journal.load(s)["image"] for s in steps if journal.done(s) is not None}
    assert 5 <= len(saved) < len(steps)
    assert not out.exists()

    with ring_backend.emulator(faults=FaultSpec()) as emu:
        result = capture_with(emu, patterns, out, settings)
        latches = len(emu.history()) - 1
    assert result.resumed_steps == len(saved)
    assert result.frames == len(steps) and result.mislabeled == 0
    # The second run captured only what was missing (one latch per step, plus the final OFF).
    assert latches == len(steps) - len(saved) + 1
    rec = read_record(out, schema="capture")
    assert rec.meta["runs"] == 2
    for s in steps:  # nothing already recorded was lost or replaced
        if s.id in saved:
            img = rec.data["dark"] if s.kind == "dark" else (
                rec.data["reference"][s.p] if s.kind == "reference" else rec.data["frames"][s.k, s.p])
            assert np.array_equal(img, saved[s.id]), s.id
    spec = spec_for(patterns, 2)
    for k in range(2):
        want = expected(spec, patterns, k)
        assert all(decoded_ok(rec.data["frames"][k, p], want[p]) for p in range(8))


def test_journal_of_another_plan_is_refused_and_torn_line_ignored(tmp_path, ring_backend):
    patterns = random_patterns(3, seed=3)
    out = tmp_path / "c.h5"
    with ring_backend.emulator(faults=parse_faults("disconnect-after=6")) as emu:
        with pytest.raises(RingDisconnected):
            capture_with(emu, patterns, out, CaptureSettings(contacts=1))
    with open(journal_path(out), "ab") as fh:
        fh.write(b"ITJ1\x40\x00\x00\x00junk")  # a record torn by a crash
    with ring_backend.emulator() as emu:
        with pytest.raises(UserError, match="belongs to a different capture"):
            capture_with(emu, patterns, out, CaptureSettings(contacts=1, frames_per_pattern=2))
        result = capture_with(emu, patterns, out, CaptureSettings(contacts=1))
    assert result.frames == 7 and result.mislabeled == 0 and result.resumed_steps >= 1


def test_averaging_and_record_contents(tmp_path, ring_backend):
    patterns = random_patterns(2, seed=4, leds=5)
    out = tmp_path / "c.h5"
    with ring_backend.emulator(led_count=5) as emu:
        result = capture_with(emu, patterns, out, CaptureSettings(contacts=1, frames_per_pattern=3,
                                                                  mm_per_px=0.05))
    rec = read_record(out, schema="capture")
    d = rec.data
    assert d["frames"].dtype == np.float32 and d["frames"].shape == (1, 2, *SHAPE, 3)
    assert d["drive"].shape == (2, 5, 3) and d["brightness"].shape == (2,)
    levels, b = levels_of(patterns, 1)
    assert np.allclose(d["drive"][1], levels / 255) and np.isclose(d["brightness"][1], b / 255)
    assert decoded_ok(d["frames"][0, 1], expected(spec_for(patterns, 1), patterns, k=0)[1])
    assert d["timing/exposure"].shape == (5, 3, 2)
    # Every averaged exposure began after its step's acknowledgement.
    assert np.all(d["timing/exposure"][:, :, 0] >= d["timing/ack"][:, None])
    m = rec.meta
    assert m["pattern_names"] == ["p0", "p1"] and m["source"] == "virtual" and m["bit_depth"] == 32
    assert m["mm_per_px"] == 0.05 and m["device"]["ring"]["led_count"] == 5
    assert result.mislabeled == 0


def test_pattern_set_and_settings_validation():
    with pytest.raises(UserError, match=r"drive must have shape \(P=2, L, 3\), got \(2, 4\)"):
        LightingMode.from_arrays("m", ["a", "b"], np.zeros((2, 4)), np.ones(2))
    with pytest.raises(UserError, match="pattern 'b'.*in \\[0, 1\\]"):
        LightingMode.from_arrays("m", ["a", "b"], np.stack([np.zeros((3, 3)), np.full((3, 3), 2.0)]), np.ones(2))
    with pytest.raises(UserError, match="unique"):
        LightingMode.from_arrays("m", ["a", "a"], np.zeros((2, 3, 3)), np.ones(2))
    with pytest.raises(UserError, match="--frames-per-pattern"):
        CaptureSettings(frames_per_pattern=0)


def test_led_count_mismatch(tmp_path, ring_backend):
    with ring_backend.emulator(led_count=24) as emu:
        with pytest.raises(UserError, match="drives 5 LEDs but the ring .* has 24"):
            capture_with(emu, random_patterns(2, leds=5), tmp_path / "c.h5", CaptureSettings())


def test_ctrl_c_between_presses_then_resume(tmp_path, ring_backend):
    """Ctrl-C while the operator is asked for press 1: the references and press 0 are kept;
    the rerun asks only for press 1 and completes."""
    patterns = random_patterns(3, seed=6)
    settings = CaptureSettings(contacts=2)
    out = tmp_path / "c.h5"
    asked = []
    spec = spec_for(patterns, 2)

    with ring_backend.emulator() as emu, RingClient(emu.path) as ring:
        cam = open_virtual_camera(spec, emu, patterns.drive, patterns.brightness)

        def interrupt_at_1(k):
            asked.append(k)
            if k == 1:
                raise KeyboardInterrupt
            cam.set_contact(k)

        def press(k):
            asked.append(k)
            cam.set_contact(k)

        with pytest.raises(KeyboardInterrupt):
            run_capture(patterns, ring, cam, out, settings, truth=emu, on_contact=interrupt_at_1,
                        progress=False)
        asked.clear()
        result = run_capture(patterns, ring, cam, out, settings, truth=emu, on_contact=press,
                             progress=False)
        cam.close()
    assert asked == [1]
    assert result.resumed_steps == 1 + 3 + 3 and result.frames == 10 and result.mislabeled == 0


class _DyingCamera(ContactCamera):
    """The virtual camera, unplugged after a number of reads (as a USB camera can be)."""

    def __init__(self, *a, reads_left: int, **kw):
        super().__init__(*a, **kw)
        self.reads_left = reads_left

    def read(self):
        from pipeline.capture.camera import CameraError

        if self.reads_left == 0:
            raise CameraError("camera 'test': no frame (the device stopped delivering)")
        self.reads_left -= 1
        return super().read()


def test_camera_lost_mid_capture_keeps_steps_and_says_how_to_resume(tmp_path, ring_backend):
    from pipeline.capture.camera import CameraError

    patterns = random_patterns(4, seed=7)
    out = tmp_path / "c.h5"
    with ring_backend.emulator() as emu, RingClient(emu.path) as ring:
        cam = _DyingCamera(bare_ring_illumination(SHAPE, 1.0), ring_led_state(emu), settings=EXACT,
                           fps=2000.0, reads_left=3)
        cam.open()
        # A settle of 4 frame periods makes most reads fresh (one read per step); under load a
        # read can still be rejected as stale, so the test reads how many steps were saved.
        with pytest.raises(CameraError, match=r"(\d) of 9 steps are saved .* rerun the same command") as err:
            run_capture(patterns, ring, cam, out, CaptureSettings(settle_s=0.002), truth=emu,
                        progress=False)
        saved = int(re.search(r"(\d) of 9 steps are saved", str(err.value)).group(1))
        assert 1 <= saved <= 3  # three reads: at most one step each
        cam.close()
        result = capture_with(emu, patterns, out, CaptureSettings())
    assert result.resumed_steps == saved and result.frames == 9 and result.mislabeled == 0


def test_a_lighting_mode_is_the_capture_plans_pattern_type():
    """The plan takes the one pattern type, :class:`pipeline.base.modes.LightingMode`."""
    from pipeline.base.modes import ModeFrame

    drives = [np.eye(24, 3), np.eye(24, 3)[::-1]]
    mode = LightingMode("two", [ModeFrame("a", drives[0], 1.0), ModeFrame("b", drives[1], 0.5)])
    assert mode.name == "two" and mode.pattern_names == ["a", "b"] and mode.brightness.tolist() == [1.0, 0.5]
    assert levels_of(mode, 1)[1] == 128 and mode.drive.shape == (2, 24, 3)
