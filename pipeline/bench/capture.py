"""``iristac bench capture``: pattern changes per second and seconds per full mode capture.

Measured over the ring emulator behind a real pty (the real pyserial client), with and
without faults, and with and without the emulator's baud-rate model (which makes every frame
cost its 10 bits per byte on the wire). The protocol's own overhead per pattern change is the
measured time minus the wire time of the bytes actually exchanged (with the baud model) or the
whole measured time (without it, the wire is free). A full mode capture (the ``point`` mode:
dark, 24 references and 24 contact frames of a sphere press) uses the rendering virtual camera
(:mod:`pipeline.capture.virtual`, 60 x 80, bare LED ring) at a webcam's frame rate, to show
whether the ring or the camera bounds the capture.

Both ring implementations are measured: the Python emulator and the C firmware's host build
(``firmware/``, :class:`~pipeline.capture.firmware_host.FirmwareEmulator`), which is compiled
first (its build time is reported apart); without make or a C compiler its rows are left out
with the reason.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.base.modes import load_mode
from pipeline.capture import protocol as P
from pipeline.capture.client import RingClient
from pipeline.capture.emulator import parse_faults
from pipeline.capture.firmware_host import build_host_firmware, ring_emulator
from pipeline.capture.plan import CaptureSettings, run_capture

FAULTS = "drop=0.05,corrupt=0.05,delay=0.02"
BAUD = 115200


def add_arguments(parser) -> None:
    parser.add_argument("--changes", type=int, default=500, help="pattern changes per setting")
    parser.add_argument("--camera-fps", type=float, default=30.0,
                        help="virtual camera frame rate for the full mode capture")
    parser.add_argument("--timeout", type=float, default=0.03,
                        help="client reply timeout in seconds")
    parser.add_argument("--backends", default="python,c",
                        help="ring implementations to measure: python (the emulator), c (the C "
                        "firmware's host build, compiled first); default python,c")


def _changes(faults: str, baud: float | None, n: int, timeout: float, seed: int,
             firmware: Path | None = None) -> dict:
    rng = np.random.default_rng(seed)
    drives = rng.random((n, 24, 3))
    with ring_emulator(firmware, faults=parse_faults(faults), baudrate=baud, seed=seed) as emu, \
            RingClient(emu.path, timeout=timeout, retries=30) as ring:
        sent0, recv0 = ring.stats.bytes_sent, ring.stats.bytes_received
        retries0 = ring.stats.retries
        t = time.perf_counter()
        for i in range(n):
            ring.show_pattern(drives[i], 1.0)
        seconds = time.perf_counter() - t
        wire_bytes = ring.stats.bytes_sent - sent0 + ring.stats.bytes_received - recv0
        retries = ring.stats.retries - retries0
    per = seconds / n
    wire = P.wire_seconds(wire_bytes / n, baud) if baud else 0.0
    return {"seconds_per_change": per, "changes_per_s": 1 / per, "wire_ms": wire * 1e3,
            "overhead_ms": (per - wire) * 1e3, "retries": retries}


def _full_mode(faults: str, baud: float | None, fps: float, timeout: float, seed: int,
               firmware: Path | None = None) -> dict:
    patterns = load_mode("point")
    out = Path(tempfile.mkdtemp(prefix="iristac-bench-capture-")) / "capture.h5"
    from pipeline.capture.virtual import VirtualSensorSpec, open_virtual_camera
    from sim.contacts import contact_surfaces

    shape, mm = (60, 80), 0.1
    spec = VirtualSensorSpec(shape=shape, mm_per_px=mm, fps=fps,
                             contacts=contact_surfaces("sphere", shape, mm, 1, seed=seed))
    with ring_emulator(firmware, faults=parse_faults(faults), baudrate=baud, seed=seed) as emu, \
            RingClient(emu.path, timeout=timeout, retries=30) as ring:
        cam = open_virtual_camera(spec, emu, patterns.drive, patterns.brightness)
        try:
            t = time.perf_counter()
            r = run_capture(patterns, ring, cam, out, CaptureSettings(contacts=1), truth=emu,
                            progress=False, source="virtual", on_contact=cam.set_contact)
            seconds = time.perf_counter() - t
        finally:
            cam.close()
    out.unlink()
    out.parent.rmdir()
    return {"seconds": seconds, "frames": r.frames, "mislabeled": r.mislabeled,
            "retries": r.retries}


def run(args) -> dict:
    from pipeline.base.threads import limit_threads

    # The virtual camera renders one small frame at a time: torch's thread pool only spins.
    with limit_threads(torch=1):
        return _run(args)


def _run(args) -> dict:
    quick = bool(getattr(args, "quick", False))
    n = 100 if quick else int(getattr(args, "changes", 500))
    fps = 120.0 if quick else float(getattr(args, "camera_fps", 30.0))
    timeout = float(getattr(args, "timeout", 0.03))
    backends, notes = _backends(str(getattr(args, "backends", "python,c")))
    settings = []
    for faults in ("", FAULTS):
        for baud in (None, BAUD):
            # Backends interleaved per setting: a burst of load elsewhere hits both alike.
            for name, firmware in backends:
                c = _changes(faults, baud, n, timeout, seed=1, firmware=firmware)
                m = _full_mode(faults, baud, fps, timeout, seed=2, firmware=firmware)
                settings.append({"backend": name, "faults": faults or "none",
                                 "baud_model": baud or "off", **c,
                                 "mode_seconds": m["seconds"], "mode_frames": m["frames"],
                                 "mode_mislabeled": m["mislabeled"], "mode_retries": m["retries"]})
    clean = P.wire_seconds(79 + 7 + 6 + 17, BAUD) * 1e3
    rows = [
        {"knob": "capture: pattern change",
         "setting": f"{s['backend']}, faults {s['faults']}, baud {s['baud_model']}",
         "seconds": s["seconds_per_change"], "error": s["mode_mislabeled"],
         "error_unit": "mislabeled frames (full mode)"}
        for s in settings
    ]
    return {"changes": n, "camera_fps": fps, "timeout_s": timeout, "faults_spec": FAULTS,
            "clean_wire_ms_at_115200": clean, "backends": [b for b, _ in backends],
            "notes": notes, "settings": settings, "rows": rows}


def _backends(spec: str) -> tuple[list[tuple[str, Path | None]], list[str]]:
    """The (name, host program or None) pairs to measure, and notes on what was left out."""
    from pipeline.base.errors import UserError

    out: list[tuple[str, Path | None]] = []
    notes: list[str] = []
    for name in [b.strip() for b in spec.split(",") if b.strip()]:
        if name == "python":
            out.append((name, None))
        elif name == "c":
            build = Path(tempfile.mkdtemp(prefix="iristac-bench-firmware-"))
            t = time.perf_counter()
            try:
                out.append((name, build_host_firmware(build)))
                notes.append(f"c: host build compiled in {time.perf_counter() - t:.2f} s "
                             "(not in the figures)")
            except UserError as exc:
                notes.append(f"c: left out ({exc})")
        else:
            raise UserError(f"bench capture: --backends {spec!r}: unknown backend {name!r} "
                            "(expected python and/or c)")
    return out, notes


def format_table(result: dict) -> str:
    head = (f"{'ring':<6} {'faults':<34} {'baud':>6} {'changes/s':>10} {'ms/change':>10} {'wire ms':>8} "
            f"{'overhead ms':>11} {'retries':>7} {'mode s':>7} {'frames':>6} {'mislabeled':>10}")
    lines = [
        f"ring emulators over a pty: {result['changes']} pattern changes (SET_ALL + SHOW) per "
        f"setting; full mode = point (dark + 24 references + 24 contacts) with a "
        f"{result['camera_fps']:g} fps virtual camera; client timeout {result['timeout_s']} s",
        f"clean exchange on the wire at 115200 baud: {result['clean_wire_ms_at_115200']:.2f} ms",
        *result.get("notes", []),
        head,
        "-" * len(head),
    ]
    for s in result["settings"]:
        lines.append(
            f"{s.get('backend', 'python'):<6} {s['faults']:<34} {str(s['baud_model']):>6} {s['changes_per_s']:>10.1f} "
            f"{s['seconds_per_change'] * 1e3:>10.3f} {s['wire_ms']:>8.3f} {s['overhead_ms']:>11.3f} "
            f"{s['retries']:>7d} {s['mode_seconds']:>7.2f} {s['mode_frames']:>6d} "
            f"{s['mode_mislabeled']:>10d}"
        )
    return "\n".join(lines)
