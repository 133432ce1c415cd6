"""``iristac live``: reconstruct a camera stream or the virtual sensor live (calls :func:`pipeline.live.run_live`)."""

from __future__ import annotations

import sys

from pipeline.cli._common import (
    add_drift_flag,
    add_json_flag,
    add_markers_flag,
    add_solver_flags,
    mode_metavar,
    print_json,
    profile_metavar,
    shipped_calibration,
)

#: ``live``'s solver when ``--solver`` is not given (with a profile's shipped calibration, the
#: model it holds: :data:`pipeline.capture.shipped.SHIPPED_SOLVER`).
DEFAULT_SOLVER = "lut"


def chosen_solver(args, shipped: bool = False) -> str:
    """The solver ``live`` runs for its parsed arguments (``shipped``: with a profile's shipped calibration)."""
    from pipeline.capture.shipped import SHIPPED_SOLVER

    return args.solver or (SHIPPED_SOLVER if shipped else DEFAULT_SOLVER)


def _size(text: str) -> tuple[int, int]:
    import argparse

    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--size must be WxH (e.g. 160x120), got {text!r}") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"--size must be at least 8x8, got {text!r}")
    return h, w


def register(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text)
    where = p.add_argument_group("source (one of --camera and --virtual)")
    src = where.add_mutually_exclusive_group()
    src.add_argument("--camera", metavar="SOURCE", help="OpenCV camera index, device, URL or video file, or a camera "
                                                        "name (found in /dev/v4l/by-id, e.g. \"GelSight Mini\")")
    src.add_argument("--virtual", action="store_true",
                     help="the virtual sensor: rendered gel under the emulated ring, scripted ball presses")
    where.add_argument("--profile", default=None, metavar=profile_metavar(),
                       help="sensor profile (a built-in name or a .yaml): its camera (when --camera is not given), "
                            "crop, rotation, size, pixel pitch and lighting mode; without --calibration, the "
                            "calibration shipped with it (digit: solved with --solver mlp, the session's first frame "
                            "as the no-contact reference; its measured error is printed)")
    where.add_argument("--mode", default=None, metavar=mode_metavar(),
                       help="lighting mode: a built-in name or a mode file (default: the profile's, else "
                            "trichromatic)")
    ring = p.add_argument_group("LED ring (multi-pattern modes; one of --port and --emulate)")
    one = ring.add_mutually_exclusive_group()
    one.add_argument("--port", help="serial port of the LED ring (multi-pattern modes)")
    one.add_argument("--emulate", action="store_true", help="drive the ring emulator instead (pty)")
    ring.add_argument("--ring-firmware", metavar="PROGRAM",
                      help="with --emulate/--virtual: serve the ring with the C firmware's host build")
    virt = p.add_argument_group("virtual sensor (--virtual)")
    virt.add_argument("--size", type=_size, default=(120, 160), metavar="WxH", help="virtual sensor image size")
    virt.add_argument("--mm-per-px", type=float, default=0.15, help="virtual sensor pixel pitch")
    virt.add_argument("--fps", type=float, default=None,
                      help="virtual camera frame rate (default 120; 1000 in multi-pattern modes)")
    light = p.add_argument_group("light model (one of --calibration and --illumination)")
    lights = light.add_mutually_exclusive_group()
    lights.add_argument("--calibration", metavar="CAL.h5", help="calibration.h5 (with --virtual: default, calibrate "
                                                                "the virtual sensor first, cached)")
    lights.add_argument("--illumination", metavar="ILL.h5", help="illumination.h5 (per-pixel light matrices)")
    light.add_argument("--reference", choices=["start", "calibration"], default=None,
                       help="no-contact frame of the LUT/MLP: the first one (start with no contact; default with "
                            "--virtual) or the calibration's (default with --camera)")
    solve = p.add_argument_group("solving")
    add_solver_flags(solve, default_solver=DEFAULT_SOLVER, short_help=True)
    p.set_defaults(solver=None)  # chosen_solver: lut, or mlp with a profile's shipped calibration
    add_markers_flag(solve)
    add_drift_flag(solve)
    solve.add_argument("--contact", action="store_true",
                       help="also compute each result's contact mask (colour change against the no-contact frame, "
                            "drift removed, and height): recorded with --record, its mean share of the image in "
                            "--json (contact_fraction)")
    run = p.add_argument_group("how it runs")
    run.add_argument("--frames", type=int, default=None, metavar="N", help="stop after N results")
    run.add_argument("--seconds", type=float, default=None, help="stop after this many seconds")
    run.add_argument("--threads", type=int, default=1, help="threads of the per-frame solver and transforms")
    run.add_argument("--queue", type=int, default=4, help="samples waiting before the oldest is dropped (default 4)")
    run.add_argument("--eager", action="store_true", help="the eager solver even where a fast path exists")
    outs = p.add_argument_group("what is written")
    outs.add_argument("--record", metavar="FILE.h5", help="record frames, normals, depth, timestamps and drops "
                                                          "(valid HDF5 even if the process is killed)")
    outs.add_argument("--view", action="store_true", help="serve a live page on 127.0.0.1 (depth, normals, contact)")
    outs.add_argument("--view-port", type=int, default=8765, help="port of the live page (0: any free port)")
    outs.add_argument("--cache", metavar="DIR", help="store folder (default: $IRISTAC_CACHE or ./iristac-cache)")
    add_json_flag(outs)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from pipeline.live import DEFAULT_MODE, run_live

    quiet = args.json
    log = (lambda m: None) if quiet else (lambda m: print(f"iristac live: {m}", file=sys.stderr, flush=True))

    def ready(info):
        if info.get("view"):
            # Always on stderr (also with --json): the address to open.
            print(f"iristac live: view at {info['view']}", file=sys.stderr, flush=True)

    camera, mode, mm = args.camera, args.mode, args.mm_per_px
    calibration, solver, reference = args.calibration, chosen_solver(args), args.reference
    shipped = None if args.virtual else shipped_calibration("live", args.profile, calibration, args.illumination)
    if shipped is not None:
        # Another unit's calibration: its own no-contact frame is the session's first, not the shipped one.
        calibration, solver, reference = shipped, chosen_solver(args, shipped=True), reference or "start"
    if args.profile or (camera is not None and not args.virtual):
        from pipeline.capture.sensor_profiles import camera_source, load_profile

        prof = load_profile(args.profile) if args.profile else None
        if not args.virtual:
            camera = camera_source(camera, prof)
            if shipped is not None:
                from pipeline.capture.shipped import ColourMatchedCamera, shipped_reference

                camera = ColourMatchedCamera(camera, shipped_reference(shipped), say=log)
        if prof is not None:
            mode, mm = mode or prof.mode, prof.mm_per_px
    res = run_live(mode=mode or DEFAULT_MODE, solver=solver, camera=camera, virtual=args.virtual,
                   calibration=calibration, illumination=args.illumination, port=args.port,
                   emulate=args.emulate, ring_firmware=args.ring_firmware, frames=args.frames, seconds=args.seconds,
                   record=args.record, view=args.view, view_port=args.view_port, queue=args.queue,
                   threads=args.threads, integrator=args.integrator, size=args.size, mm_per_px=mm,
                   fps=args.fps, cache=args.cache, reference=reference, markers=args.markers,
                   fast=not args.eager, contact=args.contact, drift=args.drift, on_ready=ready, log=log)
    s = res.summary
    if res.error:
        print(f"iristac live: stopped: {res.error}"
              + (f"; the recording {s['record']} is closed and holds {s['results']} results" if s.get("record") else ""),
              file=sys.stderr)
    if args.json:
        print_json(s)
    else:
        print(f"{s['results']} results ({s['mode']}, {s['solver']} {s['method']}) at {s['fps']:.1f} /s, latency "
              f"p50 {s['latency_ms_p50']:.1f} ms, p99 {s['latency_ms_p99']:.1f} ms; dropped {s['dropped']}, "
              f"stale {s['stale']}, torn cycles {s['torn']}"
              + (f"; contact {s['contact_fraction']:.1%} of the image" if s.get("contact_fraction") is not None
                 else ""))
    if args.frames is not None and s["results"] < args.frames:
        return 1  # asked for more results than the source gave
    if res.error and not res.end_of_file:
        return 1  # the camera failed mid-stream
    return 0
