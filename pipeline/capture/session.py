"""One capture session end to end: pick the ring and camera, run the plan, report.

:func:`capture` is what ``iristac capture`` (and a pipeline config's ``capture:`` section)
calls: it opens the ring (a serial port, or an emulator it starts behind a pty), the camera
(OpenCV, any :class:`~pipeline.base.camera.Camera`, or the virtual sensor of
:mod:`pipeline.capture.virtual` that renders the gel under the emulator's LEDs), loads the
lighting mode through :func:`pipeline.base.modes.load_mode` and runs
:func:`pipeline.capture.plan.run_capture`.

Examples
--------
>>> import tempfile, os
>>> out = os.path.join(tempfile.mkdtemp(), "capture.h5")
>>> from pipeline.capture.virtual import VirtualSensorSpec
>>> from sim.contacts import contact_surfaces
>>> spec = VirtualSensorSpec(contacts=contact_surfaces("sphere", (30, 40), 0.1, 2), shape=(30, 40),
...                          mm_per_px=0.1, fps=400.0)
>>> r = capture(out, mode="monochromatic", emulate=True, virtual_camera=spec, progress=False)
>>> r.frames, r.patterns, r.mislabeled
(10, 3, 0)
>>> r.record.data["frames"].shape, r.record.data["truth/height"].shape
((2, 3, 30, 40, 3), (2, 30, 40))
"""

from __future__ import annotations

import os
import sys
from typing import TYPE_CHECKING, Callable

import numpy as np

from pipeline.base.errors import UserError
from pipeline.base.modes import load_mode
from pipeline.capture.client import RingClient
from pipeline.capture.emulator import parse_faults
from pipeline.capture.firmware_host import ring_emulator
from pipeline.capture.plan import CaptureResult, CaptureSettings, run_capture

if TYPE_CHECKING:
    from pipeline.base.camera import Camera
    from pipeline.capture.virtual import VirtualSensorSpec

__all__ = ["capture", "virtual_sensor", "open_camera", "json_summary",
           "prompt_contact"]


def capture(
    out: str | os.PathLike,
    *,
    mode: str,
    port: str | None = None,
    emulate: bool = False,
    faults: str | None = None,
    ring_firmware: str | os.PathLike | None = None,
    camera: int | str | Camera | None = None,
    virtual_camera: bool | VirtualSensorSpec = False,
    frames_per_pattern: int = 1,
    contacts: int | None = None,
    settle_s: float | None = None,
    mm_per_px: float | None = None,
    exposure: float | None = None,
    baudrate: int = 115200,
    timeout: float = 0.1,
    retries: int = 8,
    emulate_baud: bool = False,
    seed: int = 0,
    on_contact: Callable[[int], None] | None = None,
    progress: bool = True,
) -> CaptureResult:
    """Capture a lighting mode to ``out`` (resuming an interrupted capture of the same file).

    Parameters
    ----------
    out : path-like
        The ``capture.h5`` to write.
    mode : str
        Lighting mode name (:func:`pipeline.base.modes.list_modes`) or mode file.
    port : str, optional
        Serial port of the ring. Exactly one of ``port`` and ``emulate``.
    emulate : bool
        Start a ring emulator behind a pty instead (``faults``: its fault spec;
        ``emulate_baud``: model the wire time at ``baudrate``).
    ring_firmware : path-like, optional
        With ``emulate``: serve the ring with this host build of the C firmware
        (``make -C firmware host``, :class:`~pipeline.capture.firmware_host.FirmwareEmulator`)
        instead of the Python emulator.
    camera : int, str or Camera, optional
        OpenCV camera index, device path or video file, or any object implementing
        :class:`~pipeline.base.camera.Camera` (opened here and closed at the end).
        Exactly one of ``camera`` and ``virtual_camera``.
    virtual_camera : bool or VirtualSensorSpec
        Render the gel under the emulated ring's LEDs (needs ``emulate``) with
        :class:`~pipeline.capture.virtual.ContactCamera`; True uses
        :func:`virtual_sensor` (``contacts`` spheres on a 60 x 80 image). The
        capture then carries ``truth/height``, ``truth/normals`` and ``truth/albedo``.
    frames_per_pattern, settle_s
        See :class:`~pipeline.capture.plan.CaptureSettings`.
    contacts : int, optional
        K contact instances. Default: the spec's number of contacts, else 1.
    mm_per_px : float, optional
        Image scale recorded in the capture. Default: the virtual sensor's, else 0.1.
    exposure : float, optional
        Camera exposure (virtual camera: the gain ``mu`` in DN per unit radiance, default
        fitted to the mode; OpenCV: backend units).
    baudrate, timeout, retries
        Serial settings of the ring client.
    seed : int
        Seed of the emulator's fault injection.
    on_contact : callable, optional
        Called with k before contact instance k (e.g. :func:`prompt_contact` for a real
        camera; with the virtual camera it is called after the camera's contact is set).
    progress : bool
        Show a progress bar.

    Returns
    -------
    CaptureResult
        ``mislabeled`` is counted when the ring is emulated.
    """
    _check_sources(port, emulate, camera, virtual_camera, faults, ring_firmware)
    spec, contacts, mm_per_px = (_virtual_spec(virtual_camera, contacts, mm_per_px, seed)
                                 if virtual_camera is not False else (None, contacts, mm_per_px))
    settings = CaptureSettings(frames_per_pattern=frames_per_pattern,
                               contacts=1 if contacts is None else contacts, settle_s=settle_s,
                               mm_per_px=0.1 if mm_per_px is None else mm_per_px)
    patterns = load_mode(mode)
    emulator = None
    if emulate:
        emulator = ring_emulator(ring_firmware or None, led_count=patterns.num_leds, faults=parse_faults(faults),
                                 baudrate=baudrate if emulate_baud else None, seed=seed)
        port = emulator.start()
    try:
        with RingClient(port, baudrate=baudrate, timeout=timeout, retries=retries) as ring:  # type: ignore[arg-type]
            cam, extra, on_contact = (_open_virtual(spec, emulator, patterns, exposure, on_contact) if spec is not None
                                      else (open_camera(camera, exposure), {}, on_contact))
            try:
                return run_capture(patterns, ring, cam, out, settings, truth=emulator, on_contact=on_contact,
                                   source="virtual" if spec is not None else "camera",
                                   device_info={"emulated_ring": bool(emulate), "faults": faults or ""},
                                   progress=progress, **extra)
            finally:
                cam.close()
    finally:
        if emulator is not None:
            emulator.stop()


def _check_sources(port, emulate: bool, camera, virtual_camera, faults, ring_firmware) -> None:
    """A UserError unless exactly one ring (port or emulator) and one camera (real or virtual)
    are given, and the emulator's options come with the emulator."""
    if bool(port) == bool(emulate):
        raise UserError("capture: give exactly one of --port PORT and --emulate")
    if (camera is None) == (virtual_camera is False):
        raise UserError("capture: give exactly one of --camera ID and --virtual-camera")
    if virtual_camera is not False and not emulate:
        raise UserError("capture: --virtual-camera renders the gel under the emulated ring's LEDs; "
                        "it needs --emulate")
    if faults and not emulate:
        raise UserError("capture: --faults applies to the emulator; it needs --emulate")
    if ring_firmware and not emulate:
        raise UserError("capture: --ring-firmware serves the emulated ring; it needs --emulate")


def _virtual_spec(virtual_camera, contacts: int | None, mm_per_px: float | None, seed: int):
    """``(spec, contacts, mm_per_px)`` of the virtual sensor: the given spec or :func:`virtual_sensor`'s,
    its number of contacts and its illumination model's scale (a UserError where they disagree
    with the ones given)."""
    from pipeline.capture.virtual import VirtualSensorSpec  # loads torch: only when needed

    if virtual_camera is True:
        spec = virtual_sensor(contacts=contacts, mm_per_px=mm_per_px, seed=seed)
    elif isinstance(virtual_camera, VirtualSensorSpec):
        spec = virtual_camera
    else:
        raise UserError(f"capture: virtual_camera must be True or a VirtualSensorSpec, got "
                        f"{type(virtual_camera).__name__}")
    n = len(spec.contacts)
    if contacts is not None and contacts != n:
        raise UserError(f"capture: --contacts {contacts} but the virtual sensor has {n} contacts")
    model_pitch = spec.model().mm_per_px
    if mm_per_px is not None and not np.isclose(mm_per_px, model_pitch):
        raise UserError(f"capture: --mm-per-px {mm_per_px} differs from the illumination "
                        f"model's {model_pitch}")
    return spec, n, model_pitch


def _open_virtual(spec, emulator, patterns, exposure, on_contact):
    """``(camera, run_capture's extra arguments, on_contact)`` of a virtual sensor: the camera
    that renders the gel under the emulated ring, the truth and render settings the capture
    carries, and ``on_contact`` after the camera's own contact is set."""
    from pipeline.capture.virtual import open_virtual_camera, truth_data

    cam = open_virtual_camera(spec, emulator, patterns.drive, patterns.brightness, exposure)
    extra = dict(
        extra_data=truth_data(spec), scene=spec.fingerprint(),
        extra_meta={"render_settings": cam.settings.to_dict(),
                    "illumination": _scalars(spec.model().meta)},
    )
    return cam, extra, _then(cam.set_contact, on_contact)


def virtual_sensor(
    *,
    obj: str = "sphere",
    contacts: int | None = None,
    illumination: str | os.PathLike | None = None,
    shape: tuple[int, int] = (60, 80),
    mm_per_px: float | None = None,
    fps: float = 60.0,
    noise_dn: float = 1.0,
    bit_depth: int | None = 8,
    seed: int = 0,
) -> VirtualSensorSpec:
    """The virtual sensor of ``iristac capture --virtual-camera`` from its options.

    Parameters
    ----------
    obj : str
        A contact object name or a height-map file (:func:`sim.contacts.contact_surfaces`).
    contacts : int, optional
        K (default 1, or the number of maps in a ``.npy`` stack).
    illumination : path, optional
        ``illumination.h5``; default the bare LED ring at ``shape`` and ``mm_per_px``.
    shape : (H, W)
        Image size without ``illumination``.
    mm_per_px : float, optional
        Pixel pitch without ``illumination`` (default 0.1); with it, must agree with the file.
    fps, noise_dn, bit_depth, seed
        See :class:`~pipeline.capture.virtual.VirtualSensorSpec`.

    Examples
    --------
    >>> spec = virtual_sensor(obj="indenters", contacts=3, shape=(20, 30))
    >>> len(spec.contacts), spec.model().shape, spec.model().mm_per_px
    (3, (20, 30), 0.1)
    """
    from pipeline.capture.virtual import VirtualSensorSpec, illumination_option
    from sim.contacts import contact_surfaces

    model = illumination_option(illumination) if illumination is not None else None
    if model is not None and mm_per_px is not None and not np.isclose(mm_per_px, model.mm_per_px):
        raise UserError(f"--mm-per-px {mm_per_px} differs from {illumination}'s mm_per_px "
                        f"{model.mm_per_px}")
    spec = VirtualSensorSpec(illumination=model, shape=tuple(shape),
                             mm_per_px=0.1 if mm_per_px is None else float(mm_per_px), fps=fps,
                             noise_dn=noise_dn, bit_depth=bit_depth, seed=seed)
    m = spec.model()
    spec.contacts = contact_surfaces(obj, m.shape, m.mm_per_px, contacts, seed=seed)
    return spec


def _scalars(meta: dict) -> dict:
    return {k: v for k, v in meta.items() if isinstance(v, (str, int, float, bool))}


def _then(first: Callable[[int], None], second: Callable[[int], None] | None):
    """``first(k)`` then ``second(k)`` (set the virtual contact, then tell the caller)."""
    if second is None:
        return first

    def both(k: int) -> None:
        first(k)
        second(k)

    return both


def open_camera(camera, exposure: float | None = None):
    """An opened camera: ``camera`` as given when it is a :class:`~pipeline.base.camera.Camera`
    (its exposure set when given), else an OpenCV camera (an index, a device, a URL or a video
    file)."""
    from pipeline.base.camera import Camera

    if isinstance(camera, Camera):
        cam = camera
        if exposure is not None:
            cam.set_exposure(exposure)
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
