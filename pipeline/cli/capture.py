"""``iristac capture``: frames for every pattern of a lighting mode (calls
:func:`pipeline.capture.session.capture`)."""

from __future__ import annotations

import sys

from pipeline.cli._common import add_json_flag, mode_metavar, object_help, print_json


def register(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text + ". Rerunning an "
                       "interrupted capture with the same arguments resumes it.")
    r = p.add_argument_group("ring (one of --port and --emulate)")
    ring = r.add_mutually_exclusive_group(required=True)
    ring.add_argument("--port", help="serial port of the LED ring (e.g. /dev/ttyACM0)")
    ring.add_argument("--emulate", action="store_true", help="use a ring emulator behind a pty")
    r.add_argument("--faults", help="emulator faults, e.g. drop=0.05,corrupt=0.05,delay=0.02,"
                   "delay-s=0.05,disconnect-after=N")
    r.add_argument("--ring-firmware", metavar="BIN",
                   help="with --emulate: serve the ring with this host build of the C firmware "
                   "(make -C firmware host: firmware/build/host/iristac-ring-host) instead of "
                   "the Python emulator")
    c = p.add_argument_group("camera (one of --camera and --virtual-camera)")
    cam = c.add_mutually_exclusive_group(required=True)
    cam.add_argument("--camera", help="OpenCV camera index, device path or video file")
    cam.add_argument("--virtual-camera", action="store_true",
                     help="render the gel under the emulated ring's LEDs (needs --emulate); the "
                     "capture then carries truth/height, truth/normals, truth/albedo")
    w = p.add_argument_group("what to capture")
    w.add_argument("--mode", required=True, metavar=mode_metavar(), help="lighting mode: a built-in name or a mode file")
    w.add_argument("--frames-per-pattern", type=int, default=1, metavar="N",
                   help="frames averaged per stored frame (default 1)")
    w.add_argument("--contacts", type=int, default=None, metavar="K",
                   help="contact instances (presses) after the references (default 1, or the "
                   "number of maps in an --object stack)")
    w.add_argument("--settle", type=float, default=None, metavar="S",
                   help="seconds to wait after a pattern change before flushing the camera")
    w.add_argument("--exposure", type=float, default=None,
                   help="camera exposure (virtual: gain mu in DN per unit radiance, default "
                   "fitted to the mode; OpenCV: backend units)")
    w.add_argument("--mm-per-px", type=float, default=None,
                   help="image scale (default 0.1, or the --illumination file's)")
    link = p.add_argument_group("serial link and emulator")
    link.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
    link.add_argument("--timeout", type=float, default=0.1,
                   help="seconds to wait for the ring's first reply (default 0.1)")
    link.add_argument("--retries", type=int, default=8, help="retransmissions per command")
    link.add_argument("--emulate-baud", action="store_true",
                   help="the emulator models the wire time at --baud")
    link.add_argument("--seed", type=int, default=0, help="seed of the emulator's faults")
    v = p.add_argument_group("virtual camera (--virtual-camera)")
    v.add_argument("--object", default="sphere", metavar="OBJ", help=object_help("sphere"))
    v.add_argument("--illumination", metavar="FILE",
                   help="illumination.h5 (schema illumination) to render with; default: the "
                   "bare LED ring in closed form")
    v.add_argument("--camera-fps", type=float, default=60.0, help="frame rate (default 60)")
    v.add_argument("--camera-size", type=int, nargs=2, default=(60, 80), metavar=("H", "W"),
                   help="image size without --illumination (default 60 80)")
    v.add_argument("--noise", type=float, default=1.0, metavar="DN",
                   help="read noise in DN (default 1)")
    v.add_argument("--bit-depth", type=int, default=8, choices=(0, 8, 10, 12, 16),
                   help="frame bit depth; 0 = float32 (default 8)")
    o = p.add_argument_group("output")
    o.add_argument("--no-prompt", action="store_true",
                   help="do not wait for Enter before each contact with a real camera")
    o.add_argument("--out", required=True, help="capture file to write (.h5)")
    add_json_flag(o)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from pipeline.capture.session import json_summary, prompt_contact

    prompt = None
    if args.camera is not None and not args.no_prompt and sys.stdin.isatty():
        prompt = prompt_contact
    if args.faults:
        from pipeline.capture.emulator import parse_faults

        parse_faults(args.faults)  # a bad spec fails before the renderer is loaded
    from pipeline.base.threads import limit_threads

    # The virtual camera renders one frame at a time, a few small matrix products: with more
    # threads torch's pool spins on busy cores (measured several times slower on 2 shared cores).
    with limit_threads(torch=1 if args.virtual_camera else None):
        result = _capture(args, prompt)
    summary = json_summary(result, emulated=args.emulate)
    if args.json:
        print_json(summary)
    else:
        extra = f", {summary['mislabeled']} mislabeled" if "mislabeled" in summary else ""
        resumed = f" (resumed {result.resumed_steps} saved frames)" if result.resumed_steps else ""
        print(f"wrote {result.path}: {summary['frames']} frames, {summary['patterns']} patterns, "
              f"{summary['retries']} retries, {summary['seconds']:.2f} s{extra}{resumed}")
    return 0


def _capture(args, prompt):
    from pipeline.capture.session import capture, virtual_sensor

    virtual = False
    if args.virtual_camera:
        virtual = virtual_sensor(
            obj=args.object, contacts=args.contacts, illumination=args.illumination,
            shape=tuple(args.camera_size), mm_per_px=args.mm_per_px, fps=args.camera_fps,
            noise_dn=args.noise, bit_depth=args.bit_depth or None, seed=args.seed)
    return capture(
        args.out,
        mode=args.mode,
        port=args.port,
        emulate=args.emulate,
        faults=args.faults,
        ring_firmware=args.ring_firmware,
        camera=args.camera,
        virtual_camera=virtual,
        frames_per_pattern=args.frames_per_pattern,
        contacts=args.contacts,
        settle_s=args.settle,
        mm_per_px=args.mm_per_px,
        exposure=args.exposure,
        baudrate=args.baud,
        timeout=args.timeout,
        retries=args.retries,
        emulate_baud=args.emulate_baud,
        seed=args.seed,
        on_contact=prompt,
        progress=not args.json,
    )
