"""Where live frames come from: a camera (single-frame modes) or a camera and the ring (multi-pattern).

A source's :meth:`next` returns one :class:`Sample`, the frames of one reconstruction:

- :class:`FrameSource`: every camera frame is a sample (single-frame modes: trichromatic,
  multicolour; the ring, when there is one, shows the mode's one pattern throughout);
- :class:`CycleSource`: the ring is driven through the mode's patterns, one frame per
  pattern, each read only once it was exposed after the ring confirmed the pattern (the
  capture plan's step, :func:`pipeline.capture.plan.grab_pattern`: stale frames rejected by
  their exposure windows; with the emulator, every frame's LED state checked against its
  history). A sample is one *complete* cycle: a cycle whose frames saw different contacts (a
  press that changed mid-cycle, known from a virtual camera) or a wrong LED state is
  discarded and counted, never mixed into a result.

A camera that fails (unplugged, a video file that ends) raises
:class:`pipeline.capture.camera.CameraError` from :meth:`next`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Sample", "FrameSource", "CycleSource", "PressScript"]


@dataclass
class Sample:
    """The frames of one reconstruction.

    Attributes
    ----------
    frames : ndarray, shape (P, H, W, C)
        Integer camera frames (P = 1 in single-frame modes).
    timestamp : float
        ``time.monotonic()`` of the latest frame (middle of its exposure): latency is measured
        from here.
    index : int
        Camera frame counter of the latest frame.
    info : dict
        ``contact`` (virtual cameras), ``mislabeled``.
    """

    frames: np.ndarray
    timestamp: float
    index: int
    info: dict[str, Any] = field(default_factory=dict)


class FrameSource:
    """Every frame of ``camera`` is one sample."""

    def __init__(self, camera):
        self.camera = camera
        self.counters = {"stale": 0, "torn": 0, "mislabeled": 0}

    def next(self) -> Sample:
        f = self.camera.read()
        img = np.asarray(f.image)
        if img.ndim != 3:
            from pipeline.base.errors import UserError

            raise UserError(f"camera frame must be (H, W, C), got {img.shape}")
        return Sample(img[None], float(f.timestamp), int(f.index), {"contact": (f.info or {}).get("contact")})


class CycleSource:
    """One complete pattern cycle of ``patterns`` per sample (see the module docstring).

    Parameters
    ----------
    ring : RingClient
    camera : Camera
    patterns : LightingMode
    truth : object, optional
        The emulator (``states_during``), to check each frame's LED state.
    max_attempts : int
        Cycles tried for one sample before giving up (a press that never stops changing).
    """

    def __init__(self, ring, camera, patterns, *, truth=None, max_attempts: int = 50):
        from pipeline.capture.plan import CaptureSettings

        self.ring, self.camera, self.patterns, self.truth = ring, camera, patterns, truth
        self.settings = CaptureSettings(contacts=1, dark=False)
        self.counters = {"stale": 0, "torn": 0, "mislabeled": 0}
        self.max_attempts = int(max_attempts)

    def next(self) -> Sample:
        from pipeline.base.errors import UserError
        from pipeline.capture.plan import grab_pattern

        for _ in range(self.max_attempts):
            images, contacts, t_last, bad = [], set(), 0.0, False
            for p in range(len(self.patterns.frames)):
                img, windows, cons, wrong = grab_pattern(self.ring, self.camera, self.patterns, p, self.settings,
                                                         self.counters, truth=self.truth)
                images.append(img)
                contacts.update(c for c in cons)
                t_last = max(t_last, float(np.mean(windows[-1])))
                bad = bad or bool(wrong)
            if bad:
                self.counters["mislabeled"] += 1
                continue
            if len(contacts) > 1:  # the press changed during the cycle: a mix, never a result
                self.counters["torn"] += 1
                continue
            c = next(iter(contacts)) if contacts else None
            return Sample(np.stack(images), t_last, int(getattr(self.camera, "frames_read", 0)), {"contact": c})
        raise UserError(f"live: {self.max_attempts} pattern cycles in a row were torn by a changing contact or "
                        f"showed a wrong LED state; the scene must hold still for one cycle")


class PressScript:
    """Scripted presses for the virtual sensor: contact ``k`` for ``press_s`` seconds, then the
    flat gel for ``gap_s``, then the next contact, in a loop (a thread calling
    ``camera.set_contact``); the first ``start_s`` seconds are flat (the reference)."""

    def __init__(self, camera, contacts: int, *, press_s: float = 1.0, gap_s: float = 0.25, start_s: float = 0.0):
        self.camera, self.contacts = camera, int(contacts)
        self.press_s, self.gap_s, self.start_s = float(press_s), float(gap_s), float(start_s)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="iristac-live-presses", daemon=True)

    def start(self) -> "PressScript":
        self.thread.start()
        return self

    def _run(self) -> None:
        self.camera.set_contact(None)
        if self._stop.wait(self.start_s):
            return
        k = 0
        while not self._stop.is_set():
            self.camera.set_contact(k % self.contacts)
            if self._stop.wait(self.press_s):
                break
            self.camera.set_contact(None)
            if self._stop.wait(self.gap_s):
                break
            k += 1

    def stop(self) -> None:
        self._stop.set()
        if self.thread.is_alive():
            self.thread.join(timeout=2.0)
