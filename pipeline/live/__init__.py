"""``iristac live``: reconstruct a camera stream as it happens (Python: :func:`run_live`).

Source: a camera (``camera=``: an OpenCV index, URL or video file, or any
:class:`~pipeline.base.camera.Camera`), or the virtual sensor (``virtual=True``: the rendered
gel under the emulated ring, with scripted presses). Lighting: the mode's number of patterns
decides; a single-frame mode (trichromatic, multicolour) reconstructs every frame, a
multi-pattern mode (point, monochromatic) drives the ring through its patterns over serial
(``port=``) or the emulator (``emulate=True``, the C firmware's host build with
``ring_firmware=``) and reconstructs every complete cycle (:mod:`pipeline.live.sources`).

Lights: ``calibration=`` (or ``illumination=``) through the stage registry's
:func:`pipeline.stages.normals.load_lights`; with ``virtual=True`` and neither, the virtual
sensor is calibrated first the way the demo calibrates (rendered ball presses through the
calibrate stage, :func:`pipeline.stages.calibrate.run`: cached in the store, so only the
first run pays). Solver: a name of the registry; its live path is its registered fast path
(:func:`pipeline.stages.fast_solvers.frame_solver`), else the eager solver. Depth:
:class:`pipeline.depth.fast.FastDST` (``integrator="dst"``), else
:func:`pipeline.depth.integrate`.

Threads and queues::

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

import collections
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.base.errors import UserError

__all__ = ["run_live", "LiveResult", "DropQueue", "JSON_KEYS", "virtual_calibration", "virtual_calibration_key"]

#: The stable key set of ``iristac live --json``.
JSON_KEYS = ("results", "dropped", "fps", "latency_ms_p50", "latency_ms_p99", "mode", "solver", "method", "source",
             "size", "first_result_s", "stale", "torn", "mislabeled", "stopped", "record", "view")


class DropQueue:
    """A bounded FIFO whose :meth:`put` never blocks: when full, the oldest item is dropped and
    counted (:attr:`dropped`).

    Examples
    --------
    >>> q = DropQueue(2)
    >>> for i in range(5):
    ...     q.put(i)
    >>> q.dropped, q.get(0.1), q.get(0.1), q.get(0.01)
    (3, 3, 4, None)
    """

    def __init__(self, maxsize: int):
        if maxsize < 1:
            raise ValueError(f"DropQueue: maxsize must be >= 1, got {maxsize}")
        self._items: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self.maxsize = int(maxsize)
        self.dropped = 0
        self.closed = False

    def put(self, item) -> None:
        with self._cond:
            while len(self._items) >= self.maxsize:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._cond.notify()

    def close(self) -> None:
        """No more items will come: :meth:`get` returns None once the queue is empty."""
        with self._cond:
            self.closed = True
            self._cond.notify_all()

    def get(self, timeout: float | None = None):
        """The oldest item, or None after ``timeout`` seconds (or when closed and empty)."""
        with self._cond:
            end = None if timeout is None else time.monotonic() + timeout
            while not self._items:
                if self.closed:
                    return None
                left = None if end is None else end - time.monotonic()
                if left is not None and left <= 0:
                    return None
                self._cond.wait(left)
            return self._items.popleft()


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


def _needed_models(solver: str, patterns) -> list[str]:
    from pipeline.base.registry import SOLVERS

    needs = str(SOLVERS.get(solver).info.get("needs", ""))
    if needs.startswith("model:"):
        return [needs[6:]]
    return ["far", "near", "traced"]


def _virtual_calibration_section(model, ill_key, mode: str, solver: str, ball_radius_mm: float, presses: int,
                                 noise_dn: float, seed: int):
    """The calibrate section and key inputs of :func:`virtual_calibration`."""
    from pipeline.base.hashing import digest
    from pipeline.base.modes import load_mode
    from pipeline.stages import calibrate as calibrate_stage

    patterns = load_mode(mode)
    p = calibrate_stage.rendered({"presses": presses, "depth_mm": 0.6, "noise_dn": noise_dn, "target_dn": 200.0,
                                  "spread_mm": 0.3 * min(model.shape) * model.mm_per_px, "seed": seed, "mode": mode},
                                 ball_radius_mm=ball_radius_mm, models=_needed_models(solver, patterns))
    # The key holds what the rendering reads besides the parameters: the light field
    # (``ill_key``), the sensor's size and pitch, and the mode's patterns by content (a mode
    # file or a built-in mode that changes must not find the old calibration).
    seen = digest({"shape": list(model.shape), "mm_per_px": float(model.mm_per_px), "drive": patterns.drive,
                   "brightness": patterns.brightness})
    return p, [str(ill_key), "sensor:" + seen]


def virtual_calibration(store, model, ill_key, mode: str, solver: str, *, ball_radius_mm: float = 2.0,
                        presses: int = 8, noise_dn: float = 1.0, seed: int = 11):
    """Calibrate the virtual sensor for ``mode`` as the demo does: ball presses rendered under the
    mode's patterns, fitted through the calibrate stage (cached in ``store``). Returns the
    ``calibration`` Record.

    The models fitted are the one ``solver`` applies (``lut``, ``mlp`` ...), else the light-field
    models (far, near, traced: the light field the near-field and far-field solvers use).
    ``ill_key`` identifies ``model`` (its light field). The store keys the result by the
    rendering's parameters (:func:`pipeline.stages.calibrate.run_rendered`), so a cached
    calibration is found without rendering its presses (live start-up, docs/live.md).
    """
    from pipeline.stages import calibrate as calibrate_stage

    p, inputs = _virtual_calibration_section(model, ill_key, mode, solver, ball_radius_mm, presses, noise_dn, seed)
    rec, _, _ = calibrate_stage.run_rendered(store, p, model, inputs)
    return rec


def virtual_calibration_key(store, model, ill_key, mode: str, solver: str, *, ball_radius_mm: float = 2.0,
                            presses: int = 8, noise_dn: float = 1.0, seed: int = 11):
    """The store key :func:`virtual_calibration` files its result under (same arguments)."""
    from pipeline.stages import calibrate as calibrate_stage

    p, inputs = _virtual_calibration_section(model, ill_key, mode, solver, ball_radius_mm, presses, noise_dn, seed)
    return calibrate_stage.SPEC.key(store, calibrate_stage.params(p), inputs)


def run_live(*, mode: str = "trichromatic", solver: str = "lut", camera=None, virtual: bool = False,
             calibration=None, illumination=None, port: str | None = None, emulate: bool = False,
             ring_firmware=None, frames: int | None = None, seconds: float | None = None, record=None,
             view: bool = False, view_port: int = 0, queue: int = 4, threads: int = 1, integrator: str = "dst",
             size: tuple[int, int] = (120, 160), mm_per_px: float = 0.15, fps: float | None = None, contacts: int = 4,
             press_s: float | None = None, cache=None, reference: str | None = None, markers=None, fast: bool = True,
             max_condition: float = 1e3, contact: bool = False, on_ready=None, on_result=None, log=None) -> LiveResult:
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
        The light model (:func:`pipeline.stages.normals.load_lights`).
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
        ``dst`` (the live path) or another registered integrator (eager).
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
        Also compute each result's contact mask (:func:`pipeline.contact.contact_mask`: the
        colour change against the no-contact frame and the height; the height alone when the
        no-contact frame is the calibration's), passed to ``on_result`` as ``contact`` and kept
        in :attr:`LiveResult.last_contact`; its time counts in the latency. The live page
        shows the contact mask either way (computed when the page asks for it).
    on_ready : callable, optional
        ``on_ready(info)`` once the stream runs (``info``: ``view`` URL, ``method``, ``size``).
    on_result, log : callable, optional
        ``on_result(number, result dict)`` after every result; ``log(message)`` for progress.

    Returns
    -------
    LiveResult
    """
    from pipeline.base.modes import load_mode
    from pipeline.base.registry import INTEGRATORS, SOLVERS
    from pipeline.base.store import Record, StageStore, read_record

    SOLVERS.check(solver)
    INTEGRATORS.check(integrator)
    say = log or (lambda m: None)
    if (camera is None) == (not virtual):
        raise UserError("live: give exactly one of --camera SOURCE and --virtual")
    if frames is not None and frames < 1:
        raise UserError(f"live: --frames must be >= 1, got {frames}")
    patterns = load_mode(mode)
    multi = len(patterns.frames) > 1
    if SOLVERS.get(solver).info.get("patterns") == "one-rgb" and multi:
        raise UserError(f"live: --solver {solver} needs one RGB pattern per frame; mode {patterns.name!r} has "
                        f"{len(patterns.frames)} patterns (use a single-frame mode such as trichromatic)")
    if virtual:
        emulate = True
    if multi and not (port or emulate):
        raise UserError(f"live: mode {patterns.name!r} has {len(patterns.frames)} patterns: the ring must be driven "
                        f"(--port PORT or --emulate)")
    if port and emulate:
        raise UserError("live: give --port or --emulate, not both")
    t_start = time.monotonic()
    store = StageStore(cache) if virtual else None
    cleanup: list = []
    rec = None
    result = LiveResult(summary={})
    try:
        # ---- the ring and the camera -------------------------------------------------------
        emulator = None
        ring = None
        if port or emulate:
            from pipeline.capture.client import RingClient
            from pipeline.capture.firmware_host import ring_emulator

            if emulate:
                emulator = ring_emulator(ring_firmware or None, led_count=patterns.num_leds)
                port = emulator.start()
                cleanup.append(emulator.stop)
            ring = RingClient(port)
            ring.open()
            cleanup.append(ring.close)
        spec = None
        if virtual:
            from pipeline.capture.session import virtual_sensor
            from pipeline.capture.virtual import open_virtual_camera

            fps = fps or (1000.0 if multi else 120.0)
            spec = virtual_sensor(obj="sphere", contacts=contacts, shape=tuple(size), mm_per_px=mm_per_px, fps=fps,
                                  noise_dn=1.0)
            cam = open_virtual_camera(spec, emulator, patterns.drive, patterns.brightness)
        else:
            from pipeline.capture.session import _open_camera

            cam = _open_camera(camera, None)  # an index, URL or video file; or a Camera object, opened here
        cleanup.append(cam.close)
        H, W = cam.shape
        # ---- the light model (through the stage registry) ---------------------------------
        cal = ill = None
        if calibration is not None:
            cal = calibration if isinstance(calibration, Record) else _read(calibration, "calibration")
        if illumination is not None:
            ill = illumination if isinstance(illumination, Record) else _read(illumination, "illumination")
        if virtual and cal is None and ill is None:
            from pipeline.base.hashing import digest

            model = spec.model()
            ill_key = "bare-ring:" + digest(np.asarray(model.V, np.float32))
            say(f"calibrating the virtual sensor for {patterns.name} / {solver} (cached in {store.root})")
            t0 = time.monotonic()
            cal = virtual_calibration(store, model, ill_key, mode, solver)
            say(f"calibration ready in {time.monotonic() - t0:.1f} s")
        C = 3
        probe = _probe_capture(patterns, H, W, C, mm_per_px if spec is None else spec.model().mm_per_px)
        from pipeline.stages.normals import load_lights

        lights = load_lights(probe, cal, ill)
        from pipeline.normals.solve import _check_lights

        _check_lights(solver, lights, len(patterns.frames), C)
        pitch = float(spec.model().mm_per_px) if spec is not None else float((cal.meta if cal is not None else {})
                                                                             .get("mm_per_px") or mm_per_px)
        # ---- sources -------------------------------------------------------------------------
        from pipeline.live.sources import CycleSource, FrameSource, PressScript

        if ring is not None and not multi:
            ring.show_pattern(patterns.drive[0], float(patterns.brightness[0]))
            if hasattr(cam, "flush"):
                cam.flush()
        source = (CycleSource(ring, cam, patterns, truth=emulator) if multi else FrameSource(cam))
        want_ref = reference or ("start" if virtual else "calibration")
        ref = None
        if want_ref == "start":
            if virtual:
                cam.set_contact(None)
            ref = source.next().frames.astype(np.float32)
        script = None
        if virtual:
            script = PressScript(cam, len(spec.contacts), press_s=press_s or (4.0 if multi else 1.0)).start()
            cleanup.append(script.stop)
        marks = None
        if markers is not None and markers != "none":
            from calibration.markers import resolve_markers

            marks = resolve_markers(markers, ref if ref is not None else np.zeros((1, H, W, C), np.float32))
        # ---- the per-frame solver and integrator --------------------------------------------
        from pipeline.stages.fast_solvers import frame_solver

        t0 = time.monotonic()
        fs = frame_solver(solver, lights, shape=(H, W), channels=C, reference=ref, markers=marks,
                          max_condition=max_condition, fast=fast)
        if integrator == "dst":
            from pipeline.depth.fast import FastDST

            dst = FastDST((H, W), pitch, workers=threads)
            integrate = lambda n, m: dst.integrate(n, m)  # noqa: E731
        else:
            from pipeline.depth import integrate as integ

            integrate = lambda n, m: integ(n, pitch, m, method=integrator)  # noqa: E731
        if fs.method == "fast":
            # Warm up on a dark frame before the capture thread starts: loading the compiled
            # kernels from the disk cache takes ~0.5 s, and the camera's frames of that time
            # would otherwise be dropped (and counted as if processing fell behind).
            blank = np.zeros((len(patterns.frames), H, W, C), np.uint8)
            integrate(fs.solve(blank, threads=threads).normals, np.zeros((H, W), bool))
        prepare_s = time.monotonic() - t0
        say(f"solver {solver} ({fs.method}) ready in {prepare_s:.2f} s")
        # ---- outputs ------------------------------------------------------------------------
        if record is not None:
            from pipeline.live.recorder import LiveRecorder

            rec = LiveRecorder(record, {"mode": patterns.name, "solver": solver, "mm_per_px": pitch,
                                        "source": "virtual" if virtual else str(camera)})
        lv = None
        if view:
            from pipeline.live.view import LiveView

            lv = LiveView(view_port)
            cleanup.append(lv.close)
            lv.set_stats(mode=patterns.name, solver=solver, source="virtual" if virtual else str(camera),
                         size=[H, W])
            say(f"live view: {lv.url}")
        # ---- run ----------------------------------------------------------------------------
        q = DropQueue(queue)
        stop = threading.Event()
        error: list[str] = []

        def capture_loop():
            try:
                while not stop.is_set():
                    q.put(source.next())
            except UserError as exc:
                error.append(str(exc))
            except Exception as exc:  # noqa: BLE001 - reported, never a silent dead thread
                error.append(f"{type(exc).__name__}: {exc}")
            finally:
                q.close()

        producer = threading.Thread(target=capture_loop, name="iristac-live-capture", daemon=True)
        if on_ready is not None:
            on_ready({"view": None if lv is None else lv.url, "method": fs.method, "size": [H, W]})
        producer.start()
        # One BLAS thread per caller (the MLP's small GEMMs run on the solver's own threads;
        # OpenBLAS workers on top would fight them for the cores).
        from pipeline.base.threads import limit_threads

        blas_one = limit_threads(blas=1)
        blas_one.__enter__()
        cleanup.append(lambda: blas_one.__exit__(None, None, None))
        lat: list[float] = []
        n = 0
        t_first = None
        last = None
        while frames is None or n < frames:
            if seconds is not None and time.monotonic() - t_start > seconds:
                break
            sample = q.get(timeout=0.5)
            if sample is None:
                if q.closed:
                    break
                continue
            res = fs.solve(sample.frames, threads=threads)
            depth = integrate(res.normals, res.mask)
            touch = live_contact(sample.frames, ref, depth) if contact else None
            t_done = time.monotonic()
            n += 1
            if t_first is None:
                t_first = t_done
            latency = 1e3 * (t_done - sample.timestamp)
            lat.append(latency)
            last = (sample, res, depth)
            if rec is not None:
                rec.add(frames=sample.frames, normals=res.normals, mask=res.mask, height=depth.height,
                        timestamp=sample.timestamp, latency_ms=latency, index=sample.index, dropped=q.dropped)
            stats = _stats(n, q.dropped, t_first, t_done, lat)
            if lv is not None:
                lv.publish(n, res.normals, depth.mask, depth.height, stats, contact=touch, frames=sample.frames,
                           reference=ref)
            if on_result is not None:
                on_result(n, {"latency_ms": latency, **stats, **({"contact": touch} if contact else {})})
            result.last_contact = touch
        stop.set()
        q.close()
        producer.join(timeout=5.0)
        stopped = (error[0] if error else ("frames" if frames is not None and n >= frames else
                                           "seconds" if seconds is not None else "end"))
        if rec is not None:
            rec.close(stopped=stopped, dropped=q.dropped)
            rec = None
        s = _stats(n, q.dropped, t_first, time.monotonic() if t_first else None, lat)
        counters = getattr(source, "counters", {})
        result.summary = {**s, "mode": patterns.name, "solver": solver, "method": fs.method,
                          "source": "virtual" if virtual else str(camera), "size": [int(H), int(W)],
                          "first_result_s": None if t_first is None else round(t_first - t_start, 3),
                          "stale": int(counters.get("stale", 0)), "torn": int(counters.get("torn", 0)),
                          "mislabeled": int(counters.get("mislabeled", 0)), "stopped": stopped,
                          "record": None if record is None else str(Path(record)),
                          "view": None if lv is None else lv.url}
        result.error = error[0] if error else None
        result.end_of_file = bool(error) and bool(getattr(cam, "is_file", False))
        result.last = last
        result.latencies_ms = lat
        if lv is not None:
            lv.set_stats(running=False, message=stopped)
        return result
    finally:
        if rec is not None:  # interrupted (Ctrl-C) or failed: what was recorded is still closed properly
            try:
                rec.close(stopped="interrupted")
            except Exception:  # noqa: BLE001 - the index file on disk stays valid regardless
                pass
        for fn in reversed(cleanup):
            try:
                fn()
            except Exception:  # noqa: BLE001 - closing what is left; the first error is the one to see
                pass


def live_contact(frames, reference, depth) -> np.ndarray:
    """A live result's contact mask (:func:`pipeline.contact.contact_mask`): colour and height
    against ``reference`` (the no-contact sample), the height alone without one."""
    from pipeline.contact import contact_mask

    if reference is None:
        return contact_mask(height=depth.height, valid=depth.mask)
    return contact_mask(frames, reference, depth.height, valid=depth.mask)


def _stats(n: int, dropped: int, t_first, t_now, lat: list[float]) -> dict:
    fps = (n - 1) / (t_now - t_first) if n > 1 and t_now and t_now > t_first else 0.0
    recent = np.asarray(lat[-2000:]) if lat else np.zeros(1)
    return {"results": int(n), "dropped": int(dropped), "fps": round(float(fps), 2),
            "latency_ms_p50": round(float(np.percentile(recent, 50)), 2),
            "latency_ms_p99": round(float(np.percentile(recent, 99)), 2)}


def _read(path, schema: str):
    from pipeline.base.store import read_record

    if not Path(path).is_file():
        raise UserError(f"{path}: {schema} file not found")
    return read_record(path, schema=schema)


def _probe_capture(patterns, H: int, W: int, C: int, mm_per_px: float):
    """A frameless stand-in capture Record of the live shape (what load_lights checks lights against)."""
    from pipeline.base.store import Record

    P = len(patterns.frames)
    return Record("capture", {"frames": np.zeros((0, P, H, W, C), np.uint8), "drive": patterns.drive,
                              "brightness": patterns.brightness},
                  {"mm_per_px": float(mm_per_px), "exposure": 1.0}, path=None)
