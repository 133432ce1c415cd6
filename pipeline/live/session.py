"""A live session: the set-up of one ``iristac live`` run, then its loop (:class:`LiveSession`).

Set-up (:meth:`LiveSession.open`), each step one method:

1. the ring (a serial port or the emulator) when the mode has several patterns or the
   virtual sensor is used, and the camera (OpenCV, a :class:`~pipeline.base.camera.Camera`,
   or the virtual sensor);
2. the light model: ``calibration=`` or ``illumination=`` through the normals stage's
   :func:`pipeline.solving.light_files.load_lights` (for the mode's patterns and the camera's image
   size); the virtual sensor without either is calibrated first
   (:func:`pipeline.live.virtual.virtual_calibration`, cached in the store);
3. the source of samples (:mod:`pipeline.live.sources`), the no-contact reference and the
   virtual sensor's scripted presses;
4. the per-frame solver and integrator, both from their registries: the registered fast path
   (:func:`pipeline.solving.frame_solvers.frame_solver`,
   :func:`pipeline.depth.frame_integrator`), else the eager one, in the frame pipeline
   ``reconstruct`` and ``batch`` run (:class:`pipeline.frame_pipeline.FramePipeline`), warmed up
   before the camera runs.

The loop (:meth:`LiveSession.run`)::

    capture thread ──► DropQueue (maxsize, oldest dropped and counted) ──► processing (caller's thread)
      camera.read / ring cycles                                              normals + depth
                                                                            ├─► LiveRecorder (segments)
                                                                            └─► LiveView (latest result) ◄── HTTP threads

The capture thread never waits for processing: when the queue is full the *oldest* sample
is dropped (a live view wants the newest) and counted in ``dropped``. A camera that fails
stops the capture thread; the processing loop finishes what is queued, the recording is
closed (valid, consolidated) and :class:`LiveResult` carries the message.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.base.errors import UserError
from pipeline.live.queue import DropQueue

__all__ = ["LiveSession", "LiveResult", "run_live", "JSON_KEYS", "DEFAULT_MODE"]

#: The lighting mode ``iristac live`` runs when neither ``--mode`` nor a sensor profile names one.
DEFAULT_MODE = "trichromatic"

#: The stable key set of ``iristac live --json``.
JSON_KEYS = ("results", "dropped", "fps", "latency_ms_p50", "latency_ms_p99", "mode", "solver", "method", "source",
             "size", "first_result_s", "stale", "torn", "mislabeled", "stopped", "record", "view", "drift",
             "contact_fraction")


@dataclass
class LiveResult:
    """What a live run did (``summary`` has :data:`JSON_KEYS`)."""

    summary: dict[str, Any]
    error: str | None = None
    #: The source was a video file and it ended (a normal end of input, not a failure).
    end_of_file: bool = False
    last: Any = None
    latencies_ms: list[float] = field(default_factory=list)
    #: The last result's contact mask ``(H, W)`` bool (with ``contact=True``).
    last_contact: Any = None


class LiveSession:
    """One live reconstruction (see the module docstring); a context manager that closes what it
    opened. Parameters as :func:`run_live`'s set-up ones.

    Examples
    --------
    >>> LiveSession(mode="point", solver="lut", virtual=True)
    Traceback (most recent call last):
    ...
    pipeline.base.errors.UserError: live: --solver lut needs one RGB pattern per frame; mode 'point' has 24 \
patterns (use a single-frame mode such as trichromatic)
    """

    def __init__(self, *, mode: str = "trichromatic", solver: str = "lut", camera=None, virtual: bool = False,
                 calibration=None, illumination=None, port: str | None = None, emulate: bool = False,
                 ring_firmware=None, integrator: str = "dst", size: tuple[int, int] = (120, 160),
                 mm_per_px: float = 0.15, fps: float | None = None, contacts: int = 4, press_s: float | None = None,
                 cache=None, reference: str | None = None, markers=None, fast: bool = True,
                 max_condition: float = 1e3, threads: int = 1, drift: str = "auto", log=None):
        from pipeline.base.modes import load_mode
        from pipeline.base.registry import INTEGRATORS, SOLVERS

        self.t_start = time.monotonic()
        self.solver, self.integrator = SOLVERS.check(solver), INTEGRATORS.check(integrator)
        if (camera is None) == (not virtual):
            raise UserError("live: give exactly one of --camera SOURCE and --virtual")
        self.patterns = load_mode(mode)
        self.multi = len(self.patterns.frames) > 1
        if SOLVERS.get(solver).info.get("patterns") == "one-rgb" and self.multi:
            raise UserError(f"live: --solver {solver} needs one RGB pattern per frame; mode {self.patterns.name!r} "
                            f"has {len(self.patterns.frames)} patterns (use a single-frame mode such as trichromatic)")
        emulate = emulate or virtual
        if self.multi and not (port or emulate):
            raise UserError(f"live: mode {self.patterns.name!r} has {len(self.patterns.frames)} patterns: the ring "
                            f"must be driven (--port PORT or --emulate)")
        if port and emulate:
            raise UserError("live: give --port or --emulate, not both")
        self.mode, self.camera_arg, self.virtual = mode, camera, bool(virtual)
        self.calibration, self.illumination = calibration, illumination
        self.port, self.emulate, self.ring_firmware = port, bool(emulate), ring_firmware
        self.size, self.mm_per_px, self.fps, self.contacts, self.press_s = size, mm_per_px, fps, contacts, press_s
        self.cache, self.reference_kind, self.markers_spec = cache, reference, markers
        self.fast, self.max_condition, self.threads = bool(fast), float(max_condition), int(threads)
        from pipeline.normals.drift import check_drift

        self.drift = check_drift(drift)
        self.say = log or (lambda m: None)
        self.source_name = "virtual" if virtual else str(camera)
        self.emulator = self.ring = self.spec = self.cam = self.lights = self.source = None
        self.reference = self.solve_frames = self.depth = self.pipe = None
        #: The no-contact frames the solver's model stores (the LUT's and the MLP's), or None.
        self.model_reference: np.ndarray | None = None
        self._contact_drift: tuple | None = None
        self.pitch = float(mm_per_px)
        self._cleanup: list = []

    # ---- set-up ---------------------------------------------------------------------------

    def open(self) -> LiveSession:
        """Open the ring and the camera, load the lights, start the source, build the solver."""
        self._open_ring()
        self._open_camera()
        self._load_lights()
        self._open_source()
        self._build_solver()
        return self

    def _open_ring(self) -> None:
        if not (self.port or self.emulate):
            return
        from pipeline.capture.client import RingClient
        from pipeline.capture.firmware_host import ring_emulator

        port = self.port
        if self.emulate:
            self.emulator = ring_emulator(self.ring_firmware or None, led_count=self.patterns.num_leds)
            port = self.emulator.start()
            self._cleanup.append(self.emulator.stop)
        self.ring = RingClient(port)
        self.ring.open()
        self._cleanup.append(self.ring.close)

    def _open_camera(self) -> None:
        if self.virtual:
            from pipeline.capture.session import virtual_sensor
            from pipeline.capture.virtual import open_virtual_camera

            self.fps = self.fps or (1000.0 if self.multi else 120.0)
            self.spec = virtual_sensor(obj="sphere", contacts=self.contacts, shape=tuple(self.size),
                                       mm_per_px=self.mm_per_px, fps=self.fps, noise_dn=1.0)
            self.cam = open_virtual_camera(self.spec, self.emulator, self.patterns.drive, self.patterns.brightness)
        else:
            from pipeline.capture.session import open_camera

            self.cam = open_camera(self.camera_arg)  # an index, URL or video file; or a Camera object
        self._cleanup.append(self.cam.close)

    def _load_lights(self) -> None:
        from pipeline.normals.lights import check_lights
        from pipeline.solving.light_files import load_lights

        cal = None if self.calibration is None else _read(self.calibration, "calibration")
        ill = None if self.illumination is None else _read(self.illumination, "illumination")
        if self.virtual and cal is None and ill is None:
            cal = self._calibrate_virtual_sensor()
        H, W = self.cam.shape
        self.lights = load_lights(cal, ill, mode=self.patterns, shape=(H, W), channels=3)
        check_lights(self.solver, self.lights, len(self.patterns.frames), 3)
        self.model_reference = self.lights.stored_reference(self.solver)
        if self.spec is not None:
            self.pitch = float(self.spec.model().mm_per_px)
        elif cal is not None and cal.meta.get("mm_per_px"):
            self.pitch = float(cal.meta["mm_per_px"])

    def _calibrate_virtual_sensor(self):
        from pipeline.base.hashing import digest
        from pipeline.base.store import StageStore
        from pipeline.live.virtual import virtual_calibration

        store = StageStore(self.cache)
        model = self.spec.model()
        ill_key = "bare-ring:" + digest(np.asarray(model.V, np.float32))
        self.say(f"calibrating the virtual sensor for {self.patterns.name} / {self.solver} (cached in {store.root})")
        t0 = time.monotonic()
        cal = virtual_calibration(store, model, ill_key, self.mode, self.solver)
        self.say(f"calibration ready in {time.monotonic() - t0:.1f} s")
        return cal

    def _open_source(self) -> None:
        from pipeline.live.sources import CycleSource, FrameSource, PressScript

        if self.ring is not None and not self.multi:
            self.ring.show_pattern(self.patterns.drive[0], float(self.patterns.brightness[0]))
            if hasattr(self.cam, "flush"):
                self.cam.flush()
        self.source = (CycleSource(self.ring, self.cam, self.patterns, truth=self.emulator) if self.multi
                       else FrameSource(self.cam))
        if (self.reference_kind or ("start" if self.virtual else "calibration")) == "start":
            if self.virtual:
                self.cam.set_contact(None)
            self.reference = self.source.next().frames.astype(np.float32)
        if self.virtual:
            script = PressScript(self.cam, len(self.spec.contacts),
                                 press_s=self.press_s or (4.0 if self.multi else 1.0)).start()
            self._cleanup.append(script.stop)

    def _markers(self, shape) -> np.ndarray | None:
        if self.markers_spec is None or self.markers_spec == "none":
            return None
        from calibration.markers import resolve_markers

        ref = self.reference if self.reference is not None else np.zeros(tuple(shape) + (3,), np.float32)[None]
        return resolve_markers(self.markers_spec, ref)

    def _build_solver(self) -> None:
        from pipeline.depth import frame_integrator
        from pipeline.solving.frame_solvers import frame_solver

        H, W = self.cam.shape
        t0 = time.monotonic()
        self.solve_frames = frame_solver(self.solver, self.lights, shape=(H, W), channels=3,
                                         reference=self.reference, markers=self._markers((H, W)),
                                         max_condition=self.max_condition, fast=self.fast, drift=self.drift)
        self.depth = frame_integrator(self.integrator, (H, W), self.pitch, workers=self.threads)
        from pipeline.frame_pipeline import FramePipeline

        # The frame pipeline reconstruct and batch run, a frame set at a time (its pixels split
        # over the threads: live wants each result soon, not many at once).
        self.pipe = FramePipeline(self.solve_frames, self.depth, threads=self.threads)
        self._cleanup.append(self.pipe.close)
        if self.solve_frames.method == "fast":
            # Warm up on a dark frame before the capture thread starts: loading the compiled
            # kernels from the disk cache takes ~0.5 s, and the camera's frames of that time
            # would otherwise be dropped (and counted as if processing fell behind).
            self.process(np.zeros((len(self.patterns.frames), H, W, 3), np.uint8))
        reset = getattr(self.solve_frames, "reset_drift", None)
        if reset is not None:
            reset()  # the drift of the first real frame, not of the warm-up frame
        self.say(f"solver {self.solver} ({self.solve_frames.method}) ready in {time.monotonic() - t0:.2f} s"
                 + (f", drift removed ({self.drift_model})" if self.drift_model != "none" else ""))

    @property
    def drift_model(self) -> str:
        """The drift model the per-frame solver removes (``none`` if none)."""
        fs = self.solve_frames
        est = getattr(fs, "drift", None) if fs is not None and fs.method == "fast" else \
            getattr(getattr(fs, "prep", None), "estimator", None)
        return "none" if est is None else str(est.model)

    def contact_reference(self) -> np.ndarray | None:
        """The no-contact frames the contact mask's colour change is taken against: the session's
        (``reference="start"``), else the one the solver's model stores (the calibration's, whose
        drift against the frames the contact mask removes), else None (the height alone)."""
        return self.reference if self.reference is not None else self.model_reference

    def process(self, frames):
        """``(NormalResult, DepthResult)`` of one sample's frames ``(P, H, W, C)``
        (:meth:`pipeline.frame_pipeline.FramePipeline.one`)."""
        return self.pipe.one(frames)

    def close(self) -> None:
        """Close what :meth:`open` opened, last first (errors there are not the ones to see)."""
        for fn in reversed(self._cleanup):
            try:
                fn()
            except Exception:  # noqa: BLE001 - closing what is left; the first error is the one to see
                pass
        self._cleanup = []

    def __enter__(self) -> LiveSession:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- the loop ---------------------------------------------------------------------------

    def contact(self, frames, depth) -> np.ndarray:
        """A result's contact mask ``(H, W)`` (:func:`pipeline.frame_pipeline.contact.contact_mask`): colour (drift
        removed) and height against :meth:`contact_reference`, the height alone without one."""
        from pipeline.frame_pipeline.contact import contact_mask

        ref = self.contact_reference()
        if ref is None or np.shape(ref) != np.shape(frames):
            return contact_mask(height=depth.height, valid=depth.mask)
        if self._contact_drift is None or self._contact_drift[0] is not ref:
            from pipeline.frame_pipeline.contact import contact_reference_level, drift_estimator

            # Built once per reference, not per frame.
            self._contact_drift = (ref, drift_estimator(ref), contact_reference_level(ref))
        _, est, level = self._contact_drift
        return contact_mask(frames, ref, depth.height, valid=depth.mask, estimator=est, reference_level=level)

    def run(self, *, frames: int | None = None, seconds: float | None = None, record=None, view: bool = False,
            view_port: int = 0, queue: int = 4, contact: bool = False, on_ready=None, on_result=None) -> LiveResult:
        """Reconstruct until ``frames`` results, ``seconds`` since the session began, or the
        source ends (parameters as :func:`run_live`'s)."""
        if frames is not None and frames < 1:
            raise UserError(f"live: --frames must be >= 1, got {frames}")
        loop = _Loop(self, DropQueue(queue), record, view, view_port, contact)
        try:
            return loop.run(frames, seconds, on_ready, on_result)
        finally:
            loop.close_recording("interrupted")


class _Loop:
    """The processing loop of one :meth:`LiveSession.run`: outputs, the capture thread, stats."""

    def __init__(self, session: LiveSession, q: DropQueue, record, view: bool, view_port: int,
                 contact: bool = False):
        self.s, self.q, self.record, self.want_contact = session, q, record, bool(contact)
        self.last_contact = None
        self.contact_sum = 0.0
        self.error: list[str] = []
        self.stop = threading.Event()
        self.lat: list[float] = []
        self.rec = self.lv = None
        H, W = session.cam.shape
        if record is not None:
            from pipeline.live.recorder import LiveRecorder

            self.rec = LiveRecorder(record, {"mode": session.patterns.name, "solver": session.solver,
                                             "mm_per_px": session.pitch, "source": session.source_name,
                                             "drift": session.drift_model}, contact=self.want_contact)
        if view:
            from pipeline.live.view import LiveView

            self.lv = LiveView(view_port)
            session._cleanup.append(self.lv.close)
            self.lv.set_stats(mode=session.patterns.name, solver=session.solver, source=session.source_name,
                              size=[H, W])
            session.say(f"live view: {self.lv.url}")

    def capture(self) -> None:
        try:
            while not self.stop.is_set():
                self.q.put(self.s.source.next())
        except UserError as exc:
            self.error.append(str(exc))
        except Exception as exc:  # noqa: BLE001 - reported, never a silent dead thread
            self.error.append(f"{type(exc).__name__}: {exc}")
        finally:
            self.q.close()

    def run(self, frames, seconds, on_ready, on_result) -> LiveResult:
        from pipeline.base.threads import limit_threads

        s = self.s
        H, W = s.cam.shape
        producer = threading.Thread(target=self.capture, name="iristac-live-capture", daemon=True)
        if on_ready is not None:
            on_ready({"view": None if self.lv is None else self.lv.url, "method": s.solve_frames.method,
                      "size": [H, W]})
        producer.start()
        # One BLAS thread per caller (the MLP's small GEMMs run on the solver's own threads;
        # OpenBLAS workers on top would fight them for the cores).
        with limit_threads(blas=1):
            n, t_first, last = self.process(frames, seconds, on_result)
        self.stop.set()
        self.q.close()
        producer.join(timeout=5.0)
        stopped = (self.error[0] if self.error else ("frames" if frames is not None and n >= frames else
                                                     "seconds" if seconds is not None else "end"))
        self.close_recording(stopped)
        return self.result(n, t_first, last, stopped)

    def process(self, frames, seconds, on_result):
        n, t_first, last = 0, None, None
        while frames is None or n < frames:
            if seconds is not None and time.monotonic() - self.s.t_start > seconds:
                break
            sample = self.q.get(timeout=0.5)
            if sample is None:
                if self.q.closed:
                    break
                continue
            res, depth = self.s.process(sample.frames)
            touch = self.s.contact(sample.frames, depth) if self.want_contact else None
            t_done = time.monotonic()
            n += 1
            t_first = t_first or t_done
            latency = 1e3 * (t_done - sample.timestamp)
            self.lat.append(latency)
            last = (sample, res, depth)
            if touch is not None:
                self.contact_sum += float(np.mean(touch))
            if self.rec is not None:
                self.rec.add(frames=sample.frames, normals=res.normals, mask=res.mask, height=depth.height,
                             timestamp=sample.timestamp, latency_ms=latency, index=sample.index,
                             dropped=self.q.dropped, contact=touch)
            stats = _stats(n, self.q.dropped, t_first, t_done, self.lat)
            if self.lv is not None:
                self.lv.publish(n, res.normals, depth.mask, depth.height, stats, contact=touch,
                                frames=sample.frames, reference=self.s.contact_reference())
            if on_result is not None:
                on_result(n, {"latency_ms": latency, **stats, **({"contact": touch} if self.want_contact else {})})
            self.last_contact = touch
        return n, t_first, last

    def close_recording(self, stopped: str) -> None:
        """Close the recording (once): after the loop with why it stopped, or, interrupted (Ctrl-C)
        or failed, with what was recorded still closed properly."""
        rec, self.rec = self.rec, None
        if rec is None:
            return
        if stopped != "interrupted":
            rec.close(stopped=stopped, dropped=self.q.dropped)
            return
        try:
            rec.close(stopped="interrupted")
        except Exception:  # noqa: BLE001 - the index file on disk stays valid regardless
            pass

    def result(self, n: int, t_first, last, stopped: str) -> LiveResult:
        s = self.s
        H, W = s.cam.shape
        counters = getattr(s.source, "counters", {})
        summary = {**_stats(n, self.q.dropped, t_first, time.monotonic() if t_first else None, self.lat),
                   "mode": s.patterns.name, "solver": s.solver, "method": s.solve_frames.method,
                   "source": s.source_name, "size": [int(H), int(W)],
                   "first_result_s": None if t_first is None else round(t_first - s.t_start, 3),
                   "stale": int(counters.get("stale", 0)), "torn": int(counters.get("torn", 0)),
                   "mislabeled": int(counters.get("mislabeled", 0)), "stopped": stopped,
                   "record": None if self.record is None else str(Path(self.record)),
                   "view": None if self.lv is None else self.lv.url, "drift": s.drift_model,
                   "contact_fraction": round(self.contact_sum / n, 5) if self.want_contact and n else None}
        if self.lv is not None:
            self.lv.set_stats(running=False, message=stopped)
        return LiveResult(summary=summary, error=self.error[0] if self.error else None,
                          end_of_file=bool(self.error) and bool(getattr(s.cam, "is_file", False)), last=last,
                          latencies_ms=self.lat, last_contact=self.last_contact)


def run_live(*, mode: str = DEFAULT_MODE, solver: str = "lut", camera=None, virtual: bool = False,
             calibration=None, illumination=None, port: str | None = None, emulate: bool = False,
             ring_firmware=None, frames: int | None = None, seconds: float | None = None, record=None,
             view: bool = False, view_port: int = 0, queue: int = 4, threads: int = 1, integrator: str = "dst",
             size: tuple[int, int] = (120, 160), mm_per_px: float = 0.15, fps: float | None = None, contacts: int = 4,
             press_s: float | None = None, cache=None, reference: str | None = None, markers=None, fast: bool = True,
             max_condition: float = 1e3, contact: bool = False, drift: str = "auto", on_ready=None, on_result=None,
             log=None) -> LiveResult:
    """Reconstruct a stream until ``frames`` results, ``seconds`` elapsed, or the source ends.

    Parameters
    ----------
    mode : str
        Lighting mode (a built-in name or a mode file); one pattern: single-frame mode.
    solver : str
        A name in :data:`pipeline.base.registry.SOLVERS`.
    camera : int, str or Camera, optional
        OpenCV camera index, URL or video file, or a Camera object. Exactly one of ``camera``
        and ``virtual``.
    virtual : bool
        The virtual sensor (bare LED ring, ``size`` pixels at ``mm_per_px``, camera at ``fps``,
        ``contacts`` scripted ball presses of ``press_s`` seconds each) behind the emulated ring.
        Defaults: 120 fps and 1 s presses in single-frame modes; 1000 fps (short exposures, so
        a cycle of P patterns is quick) and 4 s presses in multi-pattern modes.
    calibration, illumination : path or Record, optional
        The light model (:func:`pipeline.solving.light_files.load_lights`).
    port, emulate, ring_firmware
        The ring for multi-pattern modes: a serial port, or the emulator (the C firmware's
        host build with ``ring_firmware``). ``virtual`` implies the emulator.
    frames, seconds : optional
        Stop after this many results / seconds.
    record : path, optional
        ``FILE.h5`` (:class:`pipeline.live.recorder.LiveRecorder`).
    view : bool
        Serve the live page on 127.0.0.1:``view_port`` (:class:`pipeline.live.view.LiveView`).
    queue : int
        Samples waiting for processing before the oldest is dropped.
    threads : int
        Threads of the per-frame solver and the depth transforms.
    integrator : str
        A name in :data:`pipeline.base.registry.INTEGRATORS`: its registered fast path (``dst``),
        else the eager integrator.
    cache : path, optional
        Stage store (the virtual sensor's calibration is cached there).
    reference : {"start", "calibration"}, optional
        The no-contact frame the LUT and MLP key on: the first sample (``start``: begin with no
        contact; default for the virtual sensor, whose presses start after it) or the
        calibration's own (default for a camera).
    markers : optional
        Printed gel markers (``auto``/``none``/mask file); with markers the eager solver runs.
    fast : bool
        False: the eager solver even where a fast path is registered (a reference).
    contact : bool
        Also compute each result's contact mask (:func:`pipeline.frame_pipeline.contact.contact_mask`: the
        colour change, drift removed, against the no-contact frame, the session's or else the
        calibration model's, and the height), passed to ``on_result`` as ``contact``, kept in
        :attr:`LiveResult.last_contact`, recorded (``contact`` in the recording) and summarised
        (``contact_fraction``: the mean share of the image in contact); its time counts in the
        latency. The live page shows the contact mask either way (computed when the page asks
        for it).
    drift : str
        Illumination drift removed from each frame before the solve
        (:func:`pipeline.solving.frame_solvers.frame_solver`): ``auto`` (default: a per-channel
        gain and offset against the reference the LUT and the MLP key on, in their fast paths
        too), ``none``, or a model of :data:`pipeline.normals.drift.DRIFT_MODELS`.
    on_ready : callable, optional
        ``on_ready(info)`` once the stream runs (``info``: ``view`` URL, ``method``, ``size``).
    on_result, log : callable, optional
        ``on_result(number, result dict)`` after every result; ``log(message)`` for progress.

    Returns
    -------
    LiveResult
    """
    if frames is not None and frames < 1:
        raise UserError(f"live: --frames must be >= 1, got {frames}")
    with LiveSession(mode=mode, solver=solver, camera=camera, virtual=virtual, calibration=calibration,
                     illumination=illumination, port=port, emulate=emulate, ring_firmware=ring_firmware,
                     integrator=integrator, size=size, mm_per_px=mm_per_px, fps=fps, contacts=contacts,
                     press_s=press_s, cache=cache, reference=reference, markers=markers, fast=fast,
                     max_condition=max_condition, threads=threads, drift=drift, log=log) as session:
        return session.open().run(frames=frames, seconds=seconds, record=record, view=view, view_port=view_port,
                                  queue=queue, contact=contact, on_ready=on_ready, on_result=on_result)


def _stats(n: int, dropped: int, t_first, t_now, lat: list[float]) -> dict:
    fps = (n - 1) / (t_now - t_first) if n > 1 and t_now and t_now > t_first else 0.0
    recent = np.asarray(lat[-2000:]) if lat else np.zeros(1)
    return {"results": int(n), "dropped": int(dropped), "fps": round(float(fps), 2),
            "latency_ms_p50": round(float(np.percentile(recent, 50)), 2),
            "latency_ms_p99": round(float(np.percentile(recent, 99)), 2)}


def _read(path_or_record, schema: str):
    """A Record as given, or the file at ``path`` (UserError naming it when absent)."""
    from pipeline.base.store import Record, read_record

    if isinstance(path_or_record, Record):
        return path_or_record
    if not Path(path_or_record).is_file():
        raise UserError(f"{path_or_record}: {schema} file not found")
    return read_record(path_or_record, schema=schema)
