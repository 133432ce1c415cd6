"""``iristac emulate-ring``: the LED-ring MCU emulator behind a pseudo-terminal (calls
:func:`pipeline.capture.emulator.serve_forever`)."""

from __future__ import annotations


def register(sub, name, help_text):
    p = sub.add_parser(name, help=help_text, description=help_text + ". Prints the device "
                       "path to open (e.g. iristac capture --port PATH) and serves until Ctrl-C.")
    p.add_argument("--leds", type=int, default=24, help="LED count (default 24)")
    p.add_argument("--faults", help="drop=P,corrupt=P,delay=P,delay-s=S,disconnect-after=N")
    p.add_argument("--baud", type=float, default=None,
                   help="model the wire time of every frame at this baud rate")
    p.add_argument("--protocol-version", type=int, default=None,
                   help="protocol version to report (to test a host's version check)")
    p.add_argument("--seed", type=int, default=0, help="seed of the fault injection")
    p.add_argument("--duration", type=float, default=None,
                   help="stop after this many seconds (default: until Ctrl-C)")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from pipeline.capture.emulator import parse_faults, serve_forever

    return serve_forever(
        led_count=args.leds,
        faults=parse_faults(args.faults),
        baudrate=args.baud,
        version=args.protocol_version,
        seed=args.seed,
        duration=args.duration,
    )
