"""One capture session end to end: pick the ring and camera, run the plan, report.

:func:`capture` is what ``iristac capture`` (and a pipeline config's ``capture:`` section)
calls: it opens the ring (a serial port, or an emulator it starts behind a pty), the camera
(OpenCV, or a virtual camera that images the emulator's LEDs), loads the lighting mode and
runs :func:`pipeline.capture.plan.run_capture`.

Examples
--------
>>> import tempfile, os
>>> out = os.path.join(tempfile.mkdtemp(), "capture.h5")
>>> r = capture(out, mode="point", emulate=True, virtual_camera=True, camera_fps=500.0,
...             camera_shape=(8, 12), progress=False)
>>> r.frames, r.patterns, r.mislabeled
(49, 24, 0)
"""

from __future__ import annotations

import os
import sys
from typing import Callable

import numpy as np

from pipeline.capture.client import RingClient
from pipeline.capture.emulator import RingEmulator, parse_faults
from pipeline.capture.plan import CaptureResult, CaptureSettings, PatternSet, run_capture
from pipeline.errors import UserError

__all__ = ["load_patterns", "patterns_from_mode", "capture", "json_summary", "prompt_contact"]


def load_patterns(mode: str) -> PatternSet:
    """The patterns of a lighting mode, by name or file path, as a :class:`PatternSet`.

    Uses ``sim.modes`` (``load_mode`` and ``mode_drive``). Until that module exists the
    only mode available is ``point`` (one LED at a time, white, full brightness).

    >>> load_patterns("point").drive.shape
    (24, 24, 3)
    """
    try:
        from sim.modes import load_mode, mode_drive  # type: ignore[import-not-found]
    except ModuleNotFoundError as exc:
        if exc.name != "sim.modes":
            raise  # sim.modes exists but is broken: say so, do not fall back silently
        return _builtin_mode(mode)
    m = load_mode(mode)
    return patterns_from_mode(m, mode_drive(m))


def patterns_from_mode(mode, drive: np.ndarray) -> PatternSet:
    """Adapt a ``sim.modes.LightingMode`` (``.name``, ``.frames`` of (name, drive,
    brightness)) and its ``mode_drive`` (P, L, 3) to a :class:`PatternSet`."""
    names = [f[0] for f in mode.frames]
    bright = [f[2] for f in mode.frames]
    return PatternSet(str(mode.name), names, np.asarray(drive), bright)


def _builtin_mode(mode: str) -> PatternSet:
    if mode != "point":
        raise UserError(f"--mode {mode!r}: lighting modes are not available yet (sim.modes); "
                        "only 'point' is built in")
    leds = 24
    return PatternSet("point", [f"led{i:02d}" for i in range(leds)],
                      np.repeat(np.eye(leds)[:, :, None], 3, axis=2), np.ones(leds))


def capture(
    out: str | os.PathLike,
    *,
    mode: str,
    port: str | None = None,
    emulate: bool = False,
    faults: str | None = None,
    camera: int | str | None = None,
    virtual_camera: bool = False,
    frames_per_pattern: int = 1,
    contacts: int = 1,
    settle_s: float | None = None,
    mm_per_px: float = 0.1,
    exposure: float | None = None,
    baudrate: int = 115200,
    timeout: float = 0.1,
    retries: int = 8,
    emulate_baud: bool = False,
    seed: int = 0,
    camera_fps: float = 60.0,
    camera_shape: tuple[int, int] = (60, 80),
    on_contact: Callable[[int], None] | None = None,
    progress: bool = True,
) -> CaptureResult:
    """Capture a lighting mode to ``out`` (resuming an interrupted capture of the same file).

    Parameters
    ----------
    out : path-like
        The ``capture.h5`` to write.
    mode : str
        Lighting mode name or file.
    port : str, optional
        Serial port of the ring. Exactly one of ``port`` and ``emulate``.
    emulate : bool
        Start a ring emulator behind a pty instead (``faults``: its fault spec;
        ``emulate_baud``: model the wire time at ``baudrate``).
    camera : int or str, optional
        OpenCV camera index, device path or video file. Exactly one of ``camera`` and
        ``virtual_camera``.
    virtual_camera : bool
        Image the emulated ring's LEDs (needs ``emulate``) at ``camera_fps`` and
        ``camera_shape`` (H, W).
    frames_per_pattern, contacts, settle_s, mm_per_px
        See :class:`~pipeline.capture.plan.CaptureSettings`.
    exposure : float, optional
        Camera exposure (seconds for the virtual camera, backend units for OpenCV).
    baudrate, timeout, retries
        Serial settings of the ring client.
    seed : int
        Seed of the emulator's fault injection.
    on_contact : callable, optional
        Called with k before contact instance k.
    progress : bool
        Show a progress bar.

    Returns
    -------
    CaptureResult
        ``mislabeled`` is counted when the ring is emulated.
    """
    if bool(port) == bool(emulate):
        raise UserError("capture: give exactly one of --port PORT and --emulate")
    if (camera is None) == (not virtual_camera):
        raise UserError("capture: give exactly one of --camera ID and --virtual-camera")
    if virtual_camera and not emulate:
        raise UserError("capture: --virtual-camera images the emulated ring's LEDs; it needs "
                        "--emulate")
    if faults and not emulate:
        raise UserError("capture: --faults applies to the emulator; it needs --emulate")
    settings = CaptureSettings(frames_per_pattern=frames_per_pattern, contacts=contacts,
                               settle_s=settle_s, mm_per_px=mm_per_px)
    patterns = load_patterns(mode)
    emulator = None
    if emulate:
        emulator = RingEmulator(led_count=patterns.led_count, faults=parse_faults(faults),
                                baudrate=baudrate if emulate_baud else None, seed=seed)
        port = emulator.start()
    try:
        with RingClient(port, baudrate=baudrate, timeout=timeout, retries=retries) as ring:  # type: ignore[arg-type]
            cam = _open_camera(camera, virtual_camera, emulator, camera_fps, camera_shape,
                               exposure)
            try:
                return run_capture(
                    patterns, ring, cam, out, settings,
                    truth=emulator,
                    on_contact=on_contact,
                    source="virtual" if virtual_camera else "camera",
                    device_info={"emulated_ring": bool(emulate),
                                 "faults": faults or ""},
                    progress=progress,
                )
            finally:
                cam.close()
    finally:
        if emulator is not None:
            emulator.stop()


def _open_camera(camera, virtual_camera, emulator, fps, shape, exposure):
    if virtual_camera:
        from pipeline.capture.led_camera import LedStateCamera

        try:
            cam = LedStateCamera(emulator, shape=shape, fps=fps, exposure_s=exposure)
        except ValueError as exc:
            raise UserError(f"--virtual-camera with --camera-fps {fps} and --exposure "
                            f"{exposure}: {exc}") from None
    else:
        from pipeline.capture.camera import OpenCVCamera

        cam = OpenCVCamera(camera, exposure=exposure)
    cam.open()
    return cam


def json_summary(result: CaptureResult, emulated: bool) -> dict:
    """The stable ``--json`` keys of ``iristac capture``.

    >>> from pathlib import Path
    >>> sorted(json_summary(CaptureResult(Path("c.h5"), 3, 1, 0, 0.5, 0), True))
    ['frames', 'mislabeled', 'patterns', 'retries', 'seconds']
    """
    summary = {
        "frames": int(result.frames),
        "patterns": int(result.patterns),
        "retries": int(result.retries),
        "seconds": round(float(result.seconds), 4),
    }
    if emulated:
        # None only when part of the capture was resumed from a run without ground truth.
        summary["mislabeled"] = None if result.mislabeled is None else int(result.mislabeled)
    return summary


def prompt_contact(k: int) -> None:
    """Ask the operator to press contact instance ``k`` (reads a line from stdin)."""
    print(f"press contact {k + 1} on the sensor, hold it, then hit Enter", file=sys.stderr)
    sys.stdin.readline()
