"""The capture plan: dark, references and contact frames for every pattern, resumable.

A capture is a list of *steps*, each one LED state and one stored (averaged) frame:

1. ``dark``: all LEDs off (optional);
2. ``reference/p``: no-contact frame under pattern ``p``, for every pattern;
3. ``contact/k/p``: contact instance ``k`` (a press) under pattern ``p``.

For every step the ring is told to show the state and must confirm it (SET_ALL + SHOW, the
ring reports the CRC of what it latched); then the camera's stale buffered frames are dropped
(wait the settle time, flush, and reject any frame whose exposure began before the ring's
acknowledgement), and N frames are read and averaged.

Nothing recorded is lost and nothing is recorded twice: each finished step (its frame, label
and timing) is appended to the journal ``<out>.journal`` and fsynced before the next step
starts, so an interrupted capture (unplugged ring, Ctrl-C) restarts after the last completed
step; a record torn by a crash is detected by its CRC and that step is captured again. The
journal carries a fingerprint of the plan; a rerun with different patterns or settings
refuses to mix the two. When every step is done the final ``capture.h5`` is written
atomically by :func:`pipeline.base.capture.write_capture`, and only then is the journal removed.

Examples
--------
>>> import tempfile, os
>>> from pipeline.capture.emulator import RingEmulator
>>> from pipeline.capture.client import RingClient
>>> from pipeline.capture.virtual import VirtualSensorSpec, open_virtual_camera
>>> from pipeline.base.modes import LightingMode
>>> patterns = LightingMode.from_arrays("demo", ["a", "b"], np.stack([np.eye(24, 3), np.eye(24, 3)[::-1]]),
...                                     np.array([1.0, 0.5]))
>>> out = os.path.join(tempfile.mkdtemp(), "capture.h5")
>>> spec = VirtualSensorSpec(shape=(4, 6), mm_per_px=1.0, contacts=[np.zeros((4, 6))], fps=400.0)
>>> with RingEmulator() as emu, RingClient(emu.path) as ring:
...     cam = open_virtual_camera(spec, emu, patterns.drive, patterns.brightness)
...     result = run_capture(patterns, ring, cam, out, truth=emu, on_contact=cam.set_contact,
...                          progress=False)
...     cam.close()
>>> result.frames, result.patterns, result.mislabeled
(5, 2, 0)
>>> from pipeline.base.store import read_record
>>> read_record(out, schema="capture").data["frames"].shape
(1, 2, 4, 6, 3)
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import struct
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipeline.base.camera import Camera, CameraFrame
from pipeline.base.errors import UserError
from pipeline.base.modes import LightingMode
from pipeline.base.store import fsync_dir
from pipeline.capture import protocol as P
from pipeline.capture.client import RingClient, RingError
from pipeline.capture.emulator import ShownState

__all__ = [
    "CaptureSettings",
    "CaptureResult",
    "Step",
    "plan_steps",
    "run_capture",
    "grab_pattern",
    "journal_path",
    "StaleFrameError",
]

JOURNAL_VERSION = 1


@dataclass
class CaptureSettings:
    """How to capture.

    Attributes
    ----------
    frames_per_pattern : int
        N frames averaged per stored frame (N = 1 keeps the camera's dtype, else float32).
    contacts : int
        K contact instances (presses) captured after the references.
    dark : bool
        Capture an all-off dark frame first.
    settle_s : float or None
        Wait after the ring confirms a pattern, before flushing the camera. None: 0 for a
        camera whose frames carry their exposure window (``reports_exposure``), else the
        camera's ``settle_s``, else one frame period plus the exposure when the camera states
        them (``frame_period``, ``exposure_s``), else 0.1 s.
    stale_frame_guard : bool
        Flush the camera and reject frames exposed before the ring's ACK. Only tests turn
        this off, to show that a capture without it stores mislabeled frames.
    mm_per_px : float
        Image scale recorded in the capture.
    max_stale_frames : int
        Stale frames rejected in a row before giving up on a step.
    """

    frames_per_pattern: int = 1
    contacts: int = 1
    dark: bool = True
    settle_s: float | None = None
    stale_frame_guard: bool = True
    mm_per_px: float = 0.1
    max_stale_frames: int = 50

    def __post_init__(self) -> None:
        if self.frames_per_pattern < 1:
            raise UserError(f"--frames-per-pattern must be >= 1, got {self.frames_per_pattern}")
        if self.contacts < 0:
            raise UserError(f"--contacts must be >= 0, got {self.contacts}")
        if self.settle_s is not None and self.settle_s < 0:
            raise UserError(f"--settle must be >= 0 seconds, got {self.settle_s}")
        if not self.mm_per_px > 0:
            raise UserError(f"--mm-per-px must be > 0, got {self.mm_per_px}")


@dataclass(frozen=True)
class Step:
    """One stored frame: ``kind`` is dark, reference or contact; ``k`` press, ``p`` pattern."""

    kind: str
    k: int = -1
    p: int = -1

    @property
    def id(self) -> str:
        """Stable name, used in the journal and file names."""
        if self.kind == "dark":
            return "dark"
        if self.kind == "reference":
            return f"reference-{self.p:04d}"
        return f"contact-{self.k:04d}-{self.p:04d}"


def plan_steps(n_patterns: int, settings: CaptureSettings) -> list[Step]:
    """The steps of a capture in order.

    >>> [s.id for s in plan_steps(2, CaptureSettings(contacts=1))]
    ['dark', 'reference-0000', 'reference-0001', 'contact-0000-0000', 'contact-0000-0001']
    """
    steps = [Step("dark")] if settings.dark else []
    steps += [Step("reference", p=p) for p in range(n_patterns)]
    steps += [Step("contact", k, p) for k in range(settings.contacts) for p in range(n_patterns)]
    return steps


@dataclass
class CaptureResult:
    """Summary of a finished capture (the CLI's ``--json`` keys plus detail).

    ``frames`` stored frames in the file, ``patterns`` P, ``retries`` ring retransmissions
    over every run of this capture, ``seconds`` wall time over every run, ``mislabeled``
    stored frames whose exposure saw another LED state than their label (None without
    ground truth), ``resumed_steps`` steps taken over from an interrupted run.
    """

    path: Path
    frames: int
    patterns: int
    retries: int
    seconds: float
    mislabeled: int | None
    resumed_steps: int = 0
    stale_frames_dropped: int = 0
    record: Any = field(default=None, repr=False)


class StaleFrameError(UserError):
    """The camera kept delivering frames exposed before the pattern was confirmed."""


def journal_path(out: str | os.PathLike) -> Path:
    """Where an unfinished capture keeps its journal of finished steps (``<out>.journal``)."""
    out = Path(out)
    return out.with_name(out.name + ".journal")


# ---------------------------------------------------------------------------- the journal
def _levels(patterns: LightingMode, p: int) -> tuple[np.ndarray, int]:
    """The 8-bit state pattern ``p`` puts on the wire."""
    return P.quantize_state(patterns.drive[p], float(patterns.brightness[p]))


def _fingerprint(patterns: LightingMode, settings: CaptureSettings, shape: tuple[int, int],
                 scene: str = "") -> str:
    """Hash of the plan; ``scene`` fingerprints anything else the frames depend on (a virtual
    camera's contacts and light), so a rerun cannot mix frames of two different scenes."""
    h = hashlib.sha256()
    for p in range(len(patterns.frames)):
        levels, b = _levels(patterns, p)
        h.update(patterns.pattern_names[p].encode() + b"\0" + levels.tobytes() + bytes((b,)))
    h.update(json.dumps([patterns.name, settings.frames_per_pattern, settings.contacts,
                         settings.dark, list(shape)] + ([scene] if scene else [])).encode())
    return h.hexdigest()


_MAGIC = b"ITJ1"
_REC = struct.Struct("<4sII")  # magic, body length, CRC-32 of the body


class _Journal:
    """Append-only log of finished steps in one file, fsynced after every record.

    A record is ``magic, length, CRC-32, body`` where the body is a JSON line, optionally
    followed by an ``.npz`` with the step's frame and timing. The first record holds the plan's
    fingerprint; then one record per finished step, and ``{"totals": ...}`` when a run ends.
    One append and one fsync per step keeps a step's cost O(1); a record torn by a crash fails
    its length or CRC check, is cut off on reopening, and that step is simply captured again.
    """

    def __init__(self, path: Path, fingerprint: str, out: Path) -> None:
        self.path = path
        self.steps: dict[str, dict] = {}
        self.state: dict[str, Any] = {"runs": 0, "retries": 0, "seconds": 0.0,
                                      "stale_frames_dropped": 0}
        self.torn = 0
        if path.exists():
            self._load(fingerprint, out)
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._append({"version": JOURNAL_VERSION, "fingerprint": fingerprint})
            fsync_dir(path.parent)

    def _load(self, fingerprint: str, out: Path) -> None:
        try:
            raw = self.path.read_bytes()
        except OSError as exc:
            raise UserError(f"capture journal {self.path} is unreadable ({exc}); move it away "
                            f"to start {out} afresh") from None
        pos, entries = 0, []
        while pos + _REC.size <= len(raw):
            magic, length, crc = _REC.unpack_from(raw, pos)
            body = raw[pos + _REC.size : pos + _REC.size + length]
            if magic != _MAGIC or len(body) != length or zlib.crc32(body) != crc:
                break
            head, _, blob = body.partition(b"\n")
            entry = json.loads(head)
            if blob:
                entry["_offset"] = pos + _REC.size + len(head) + 1
                entry["_length"] = len(blob)
            entries.append(entry)
            pos += _REC.size + length
        if pos != len(raw):
            self.torn = 1
            with open(self.path, "r+b") as fh:  # cut the torn tail so appends stay readable
                fh.truncate(pos)
                os.fsync(fh.fileno())
        head = entries[0] if entries else {}
        if head.get("version") != JOURNAL_VERSION or head.get("fingerprint") != fingerprint:
            raise UserError(
                f"capture journal {self.path} belongs to a different capture (other mode, "
                f"patterns, frames per pattern, contacts or image size); finish it with its "
                f"original settings, or move it away to start {out} afresh"
            )
        for e in entries[1:]:
            if "step" in e:
                self.steps[e["step"]] = e
            elif "totals" in e:
                for k, v in e["totals"].items():
                    self.state[k] = self.state.get(k, 0) + v

    def _append(self, obj: dict, blob: bytes = b"") -> int:
        body = json.dumps(obj).encode() + (b"\n" + blob if blob else b"")
        with open(self.path, "ab") as fh:
            start = fh.tell()
            fh.write(_REC.pack(_MAGIC, len(body), zlib.crc32(body)) + body)
            fh.flush()
            os.fsync(fh.fileno())
        return start + _REC.size + len(body) - len(blob)

    def done(self, step: Step) -> dict | None:
        return self.steps.get(step.id)

    def record(self, step: Step, entry: dict, image: np.ndarray, windows: np.ndarray,
               t_ack: float, t_wall: float) -> None:
        buf = io.BytesIO()
        np.savez(buf, image=image, windows=windows, t_ack=np.float64(t_ack),
                 t_wall=np.float64(t_wall))
        blob = buf.getvalue()
        entry = {"step": step.id, **entry}
        offset = self._append(entry, blob)
        self.steps[step.id] = {**entry, "_offset": offset, "_length": len(blob)}

    def load(self, step: Step) -> dict[str, np.ndarray]:
        e = self.steps[step.id]
        with open(self.path, "rb") as fh:
            fh.seek(e["_offset"])
            blob = fh.read(e["_length"])
        with np.load(io.BytesIO(blob)) as z:
            return {k: z[k] for k in ("image", "windows", "t_ack", "t_wall")}

    def add_totals(self, **totals: float) -> None:
        self._append({"totals": totals})
        for k, v in totals.items():
            self.state[k] = self.state.get(k, 0) + v


# ---------------------------------------------------------------------------- one step
def _exposure_window(frame: CameraFrame, camera: Camera) -> tuple[tuple[float, float], bool]:
    """The frame's exposure (start, end) and whether the camera reported it exactly.

    Only a reported window can prove a frame fresh; a webcam's read time says nothing about
    when a queued frame was exposed, so for those the settle time and flush must do.
    """
    info = frame.info or {}
    # sim.virtual_camera names it exposure_window (its "exposure" is the gain mu).
    window = info.get("exposure_window", info.get("exposure"))
    if window is not None and np.ndim(window) == 1 and len(window) == 2:
        return (float(window[0]), float(window[1])), True
    half = 0.5 * float(getattr(camera, "exposure_s", 0.0) or 0.0)
    return (frame.timestamp - half, frame.timestamp + half), False


def _mislabeled(truth, windows: np.ndarray, levels: np.ndarray, brightness: int) -> bool:
    for t0, t1 in windows:
        states: list[ShownState] = truth.states_during(float(t0), float(t1))
        if not states or any(not s.same_as(levels, brightness) for s in states):
            return True
    return False


def _settle_time(camera: Camera, settings: CaptureSettings) -> float:
    if settings.settle_s is not None:
        return settings.settle_s
    if getattr(camera, "reports_exposure", False):
        # Every frame carries its exposure window, so frames begun before the ACK are
        # rejected one by one; no blind wait is needed.
        return 0.0
    if getattr(camera, "settle_s", None) is not None:
        return float(camera.settle_s)  # type: ignore[attr-defined]
    period = getattr(camera, "frame_period", None)
    if period:
        return float(period) + float(getattr(camera, "exposure_s", 0.0) or 0.0)
    return 0.1


def _grab(camera: Camera, n: int, t_ack: float, settle: float, settings: CaptureSettings,
          counters: dict) -> tuple[np.ndarray, np.ndarray, list]:
    """Read N fresh frames after the ACK at ``t_ack``; return (image, windows (N, 2), the
    ``info["contact"]`` of each frame (None where the camera does not say))."""
    if settings.stale_frame_guard:
        # Frames already exposing when the LEDs changed finish within the settle time; they
        # and any older queued frames are dropped by the flush.
        time.sleep(max(0.0, t_ack + settle - time.monotonic()))
        counters["stale"] += camera.flush()
    images, windows, contacts = [], [], []
    rejected = 0
    while len(images) < n:
        frame = camera.read()
        window, exact = _exposure_window(frame, camera)
        if settings.stale_frame_guard and exact and window[0] < t_ack:
            rejected += 1
            counters["stale"] += 1
            if rejected > settings.max_stale_frames:
                raise StaleFrameError(
                    f"the camera delivered {rejected} frames exposed before the pattern was "
                    f"confirmed; its buffer is deeper than flush() drains or its clock is "
                    f"off: raise --settle (now {settle:.3f} s)"
                )
            continue
        image = np.asarray(frame.image)
        if image.ndim != 3 or image.shape[2] != 3:
            raise UserError(f"camera frame must have shape (H, W, 3), got {image.shape}")
        images.append(image)
        windows.append(window)
        contacts.append((frame.info or {}).get("contact"))
    if n == 1:
        return images[0], np.asarray(windows, np.float64), contacts
    return (np.mean(np.stack(images).astype(np.float32), axis=0), np.asarray(windows, np.float64),
            contacts)


def grab_pattern(ring, camera: Camera, patterns: LightingMode, p: int, settings: CaptureSettings, counters: dict,
                 *, truth=None, settle: float | None = None):
    """One step of the plan for a caller that streams (``iristac live``): show pattern ``p``,
    then read ``settings.frames_per_pattern`` frames exposed after the ring's ACK (stale ones
    rejected by their exposure windows and counted in ``counters["stale"]``, as
    :func:`run_capture` does).

    Returns ``(image (H, W, 3), windows (N, 2), contacts (N,), mislabeled)``; ``mislabeled``
    is None without ``truth`` (the emulator's LED history), else whether any frame's exposure
    saw another LED state.
    """
    levels, b = _levels(patterns, p)
    ring.show_pattern(patterns.drive[p], float(patterns.brightness[p]))
    t_ack = time.monotonic()
    image, windows, contacts = _grab(camera, settings.frames_per_pattern, t_ack,
                                     _settle_time(camera, settings) if settle is None else settle, settings, counters)
    bad = None if truth is None else _mislabeled(truth, windows, levels, b)
    return image, windows, contacts, bad


# ---------------------------------------------------------------------------- the plan
def run_capture(
    patterns: LightingMode,
    ring: RingClient,
    camera: Camera,
    out: str | os.PathLike,
    settings: CaptureSettings | None = None,
    *,
    truth=None,
    on_contact: Callable[[int], None] | None = None,
    source: str = "camera",
    device_info: dict | None = None,
    extra_data: dict[str, np.ndarray] | None = None,
    extra_meta: dict | None = None,
    scene: str = "",
    progress: bool = True,
) -> CaptureResult:
    """Capture every step of the plan (resuming an interrupted run) and write ``out``.

    Parameters
    ----------
    patterns : LightingMode
        The lighting patterns, P of them with L LEDs each (L must match the ring).
    ring : RingClient
        An open ring client.
    camera : Camera
        An open camera.
    out : path-like
        The capture file to write (schema ``capture``).
    settings : CaptureSettings, optional
    truth : object with ``states_during(t0, t1)``, optional
        The emulator's ground truth; when given, ``mislabeled`` is counted.
    on_contact : callable, optional
        Called with ``k`` before the first pattern of contact instance ``k`` that this run
        captures (to prompt the operator to press, or to set a virtual camera's contact); a
        resumed run calls it again for the instance it resumes in.
    source : str
        Recorded ``source`` attribute (``camera`` or ``virtual``).
    device_info : dict, optional
        Extra device description stored in the ``device`` attribute.
    extra_data, extra_meta : dict, optional
        More datasets (e.g. ``truth/height``) and attributes for the capture file.
    scene : str
        Fingerprint of anything else the frames depend on (a virtual scene); a journal
        written with another scene is refused.
    progress : bool
        Show a progress bar on stderr.

    Returns
    -------
    CaptureResult

    Raises
    ------
    RingError, CameraError
        The ring or camera failed (the message says how many steps are saved and that
        rerunning resumes).
    UserError
        The journal belongs to another capture, or the patterns do not fit the ring.
    """
    settings = settings or CaptureSettings()
    out = Path(out)
    if ring.info is not None and ring.info.led_count != patterns.num_leds:
        raise UserError(f"mode {patterns.name!r} drives {patterns.num_leds} LEDs but the ring "
                        f"on {ring.port!r} has {ring.info.led_count}")
    shape = tuple(camera.shape)
    jpath = journal_path(out)
    journal = _Journal(jpath, _fingerprint(patterns, settings, shape, scene), out)
    steps = plan_steps(len(patterns.frames), settings)
    resumed = sum(journal.done(s) is not None for s in steps)
    runner = _StepRunner(patterns, ring, camera, settings, shape, truth, on_contact)
    retries0 = ring.stats.retries
    t_start = time.monotonic()

    def flush_totals() -> None:
        journal.add_totals(runs=1, retries=ring.stats.retries - retries0,
                           seconds=time.monotonic() - t_start,
                           stale_frames_dropped=runner.counters["stale"])

    bar = _progress(len(steps), resumed, progress, out)
    try:
        for step in steps:
            if journal.done(step) is not None:
                continue
            runner.capture(step, journal)
            bar.update(1)
    except UserError as exc:  # ring or camera failed mid-capture
        flush_totals()
        raise _resume_error(exc, sum(journal.done(s) is not None for s in steps), len(steps), jpath) from None
    except BaseException:
        flush_totals()
        raise
    finally:
        bar.close()
    flush_totals()
    _leds_off(ring)
    record = _assemble(patterns, settings, journal, steps, shape, source, camera, ring,
                       device_info)
    record.data.update(extra_data or {})
    record.meta.update(extra_meta or {})
    return _write_capture_file(out, record, journal, steps, len(patterns.frames), resumed)



def _leds_off(ring: RingClient) -> None:
    """Turn the ring's LEDs off after a complete capture (a failure there is not worth failing it)."""
    try:
        ring.off()
    except RingError:
        pass

class _StepRunner:
    """Captures one step of the plan: asks for its contact, shows its pattern (or turns the ring
    off for ``dark``), grabs its frames after the settle time and journals them with whether
    they are mislabeled (with the emulator's ``truth``)."""

    def __init__(self, patterns: LightingMode, ring: RingClient, camera: Camera, settings: CaptureSettings,
                 shape: tuple, truth, on_contact: Callable[[int], None] | None) -> None:
        self.patterns, self.ring, self.camera, self.settings = patterns, ring, camera, settings
        self.shape, self.truth, self.on_contact = shape, truth, on_contact
        self.settle = _settle_time(camera, settings)
        self.counters = {"stale": 0}
        self.reports_contact = bool(getattr(camera, "reports_contact", False))
        self.pressed: int | None = None  # the contact instance this run has asked for

    def capture(self, step: Step, journal: _Journal) -> None:
        patterns, ring, settings = self.patterns, self.ring, self.settings
        if step.kind == "contact" and step.k != self.pressed:
            if self.on_contact is not None:
                self.on_contact(step.k)
            self.pressed = step.k
        if step.kind == "dark":
            ring.off()
            levels, b = np.zeros((patterns.num_leds, 3), np.uint8), 0
        else:
            levels, b = _levels(patterns, step.p)
            ring.show_pattern(patterns.drive[step.p], float(patterns.brightness[step.p]))
        t_ack = time.monotonic()
        image, windows, contacts = _grab(self.camera, settings.frames_per_pattern, t_ack, self.settle,
                                         settings, self.counters)
        if image.shape[:2] != self.shape:
            raise UserError(f"camera frame has shape {image.shape}, expected {self.shape} + (3,)")
        bad = None
        if self.truth is not None:
            # A frame is mislabeled if its exposure saw another LED state, or (for a camera
            # that reports it) another contact than the step's.
            want = step.k if step.kind == "contact" else -1
            bad = _mislabeled(self.truth, windows, levels, b) or (
                self.reports_contact and any(c != want for c in contacts))
        journal.record(step, {"mislabeled": bad}, image, windows, t_ack, time.time())


def _resume_error(exc: UserError, done: int, total: int, jpath: Path) -> UserError:
    """``exc`` (of its own class where it can be) with how many steps are saved and that rerunning resumes."""
    msg = (f"{exc}; {done} of {total} steps are saved in {jpath}: rerun the same "
           "command to resume")
    try:
        return type(exc)(msg)
    except TypeError:  # an error class with another constructor
        return UserError(msg)


def _write_capture_file(out: Path, record, journal: _Journal, steps: list[Step], patterns: int,
                        resumed: int) -> CaptureResult:
    """Write the capture file, then remove the journal; the run's :class:`CaptureResult`."""
    from pipeline.base.capture import write_capture

    write_capture(out, record)
    flags = [journal.done(s).get("mislabeled") for s in steps]
    result = CaptureResult(
        path=out,
        frames=len(steps),
        patterns=patterns,
        retries=int(journal.state["retries"]),
        seconds=float(journal.state["seconds"]),
        mislabeled=None if any(f is None for f in flags) else int(sum(flags)),
        resumed_steps=resumed,
        stale_frames_dropped=int(journal.state["stale_frames_dropped"]),
        record=record,
    )
    journal.path.unlink()  # only now that capture.h5 is safely in place
    return result


def _assemble(patterns, settings, journal, steps, shape, source, camera, ring,
              device_info):
    from pipeline.base.store import Record

    loaded = {s.id: journal.load(s) for s in steps}
    first = loaded[steps[0].id]["image"]
    p_count, k_count = len(patterns.frames), settings.contacts
    frames = np.zeros((k_count, p_count, *first.shape), first.dtype)
    reference = np.zeros((p_count, *first.shape), first.dtype)
    n = settings.frames_per_pattern
    ack = np.zeros(len(steps), np.float64)
    wall = np.zeros(len(steps), np.float64)
    windows = np.zeros((len(steps), n, 2), np.float64)
    data: dict[str, np.ndarray] = {}
    for i, s in enumerate(steps):
        d = loaded[s.id]
        if s.kind == "dark":
            data["dark"] = d["image"]
        elif s.kind == "reference":
            reference[s.p] = d["image"]
        else:
            frames[s.k, s.p] = d["image"]
        ack[i], wall[i], windows[i] = d["t_ack"], d["t_wall"], d["windows"]
    drive = np.stack([_levels(patterns, p)[0] for p in range(p_count)]).astype(np.float32) / 255
    bright = np.array([_levels(patterns, p)[1] for p in range(p_count)], np.float32) / 255
    data.update({
        "frames": frames, "reference": reference, "drive": drive, "brightness": bright,
        "timing/ack": ack, "timing/wall": wall, "timing/exposure": windows,
    })
    exposure = getattr(camera, "exposure_s", None)
    if exposure is None:
        exposure = getattr(camera, "exposure", None)  # backend units (OpenCV)
    exposure = float(exposure or 0.0)
    bit_depth = {np.dtype(np.uint8): 8, np.dtype(np.uint16): 16}.get(np.dtype(first.dtype), 32)
    ring_info = ring.info
    device = {
        "ring": {
            "port": ring.port,
            "protocol_version": ring_info.version if ring_info else None,
            "led_count": ring_info.led_count if ring_info else None,
            "firmware": ring_info.firmware if ring_info else None,
        },
        "camera": camera.describe() if hasattr(camera, "describe") else {"kind": type(camera).__name__},
        **(device_info or {}),
    }
    meta = {
        "mm_per_px": float(settings.mm_per_px),
        "pattern_names": patterns.pattern_names,
        "mode": patterns.name,
        "exposure": exposure,
        "bit_depth": bit_depth,
        "source": source,
        "device": device,
        "frames_per_pattern": n,
        "settle_s": _settle_time(camera, settings),
        "steps": [s.id for s in steps],
        "runs": int(journal.state["runs"]),
        "retries": int(journal.state["retries"]),
        "seconds": float(journal.state["seconds"]),
    }
    return Record(schema="capture", data=data, meta=meta)


class _NoBar:
    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


def _progress(total: int, initial: int, enabled: bool, out: Path):
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, desc=f"capture {out.name}", unit="frame",
                leave=False)
