"""``iristac label CAPTURE.h5``: label contact circles in a browser page (calls
:func:`calibration.label_page.serve_labeller`)."""

from __future__ import annotations

from pipeline.cli._common import add_json_flag, print_json


def register(sub, name, help_text):
    p = sub.add_parser(name, help=help_text,
                       description="Serve a page on 127.0.0.1 showing each press (frame, difference to the reference, "
                                   "the detected circle and why it was accepted or rejected) where you accept, move, "
                                   "resize or reject circles with the mouse. Every edit is saved at once into the "
                                   "capture (labels/*) and a CSV beside it (name,x,y,radius_px, as import images "
                                   "--labels reads); reopening resumes. Then: iristac calibrate CAPTURE --circles "
                                   "labels.")
    p.add_argument("capture", help="capture.h5 to label (labels are saved into it)")
    p.add_argument("--ball-radius", type=float, default=None, metavar="MM",
                   help="pressed ball's radius (default: the capture's ball_radius_mm)")
    p.add_argument("--csv", default=None, metavar="PATH", help="labels CSV (default: CAPTURE.labels.csv beside it)")
    p.add_argument("--port", type=int, default=8766, help="port on 127.0.0.1 (default 8766; 0: any free port)")
    p.add_argument("--open", action="store_true", help="open the page in the default browser")
    p.add_argument("--seconds", type=float, default=None, help="stop after this many seconds (default: Ctrl-C)")
    add_json_flag(p)
    p.set_defaults(func=_run)


def _run(args) -> int:
    import sys

    from calibration.label_page import serve_labeller

    res = serve_labeller(args.capture, port=args.port, ball_radius_mm=args.ball_radius, csv_path=args.csv,
                         open_browser=args.open, seconds=args.seconds,
                         announce=lambda line: print(line, file=sys.stderr, flush=True))
    if args.json:
        print_json(res)
        return 0
    print(f"{res['labelled']} labelled, {res['rejected']} rejected, {res['undecided']} undecided of "
          f"{len(res['presses'])} presses ({res['saves']} edits saved this run) in {res['capture']} and {res['csv']}")
    return 0
