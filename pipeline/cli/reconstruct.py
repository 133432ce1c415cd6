"""``iristac reconstruct CAPTURE``: normals and depth (calls :func:`pipeline.workflows.reconstruct.reconstruct`)."""

from __future__ import annotations

import sys

from pipeline.cli._common import (
    add_heal_flag,
    add_json_flag,
    add_light_flags,
    add_output_flags,
    add_solving_group,
    add_threads_flag,
    print_json,
    profile_metavar,
    shipped_calibration,
    threads_arg,
)

#: The stable key set of ``--json`` (truth errors only when the capture carries truth).
JSON_KEYS = ("solver", "integrator", "seconds", "valid_fraction", "cached", "markers", "drift", "contact_fraction",
             "outputs")


def register(sub, name, help_text):
    from pipeline.frame_pipeline.outputs import DEFAULT_RECONSTRUCT

    p = sub.add_parser(name, help=help_text, description=help_text)
    p.add_argument("capture", metavar="CAPTURE", help="capture.h5 or a video (.mp4, .avi, ...)")
    add_light_flags(p, "calibration.h5 (light_field / light_vectors / LUT)", "illumination.h5 (V or light_matrices)")
    p.add_argument("--profile", default=None, metavar=profile_metavar(),
                   help="sensor profile of the capture (a built-in name or a .yaml): its pixel pitch for a video and, "
                        "without --calibration or --illumination, the calibration shipped with it (digit: solved with "
                        "--solver mlp; its measured error is printed; the capture's colours are matched to it from its "
                        "no-contact frame, a chunk at a time)")
    solve = add_solving_group(p)
    p.set_defaults(solver=None)  # lstsq, or mlp with a profile's shipped calibration (_run)
    solve.add_argument("--ratio", action="store_true", help="divide by the no-contact reference first")
    solve.add_argument("--max-condition", type=float, default=1e3, help="mask pixels whose light matrix is worse")
    run = p.add_argument_group("where it runs")
    run.add_argument("--device", default="cpu", help="torch device of the eager solvers (cpu, cuda)")
    run.add_argument("--compile", action="store_true",
                     help="lstsq: torch.compile the far-field solver (a few seconds once; ~4x faster per frame)")
    add_threads_flag(run, "threads of the frame pipeline: frames in parallel on the fast paths, torch's or BLAS's "
                     "threads on the eager ones (default 1; 0: every core)")
    outs = p.add_argument_group("what is written")
    add_output_flags(outs, DEFAULT_RECONSTRUCT)
    outs.add_argument("--out", metavar="DIR", required=True, help="output folder (links to the store's files)")
    outs.add_argument("--no-images", action="store_true", help="write only normals.h5, depth.h5 and contact.h5")
    outs.add_argument("--force", action="store_true", help="recompute even if the store has the result")
    outs.add_argument("--cache", metavar="DIR", help="store folder (default: $IRISTAC_CACHE or ./iristac-cache)")
    add_heal_flag(outs)
    add_json_flag(outs)
    p.set_defaults(func=_run)


def _run(args) -> int:
    threads = threads_arg(args)
    # Announced before the run (its measured error on another unit); the workflow uses the same file.
    shipped_calibration("reconstruct", args.profile, args.calibration, args.illumination)
    res = _reconstruct(args, threads)
    if "colour_gain" in res.summary and not args.json:
        print("iristac reconstruct: colours matched to the " + ("shipped calibration's" if "shipped_calibration" in
              res.summary else "light model's") + " from the capture's no-contact frame (gain per channel "
              + " / ".join(f"{g:.3f}" for g in res.summary["colour_gain"]) + ")", file=sys.stderr)
    s = res.summary
    if args.json:
        print_json(s)
        return 0
    line = (f"{s['solver']} + {s['integrator']}: {s['valid_fraction']:.1%} valid pixels, {s['seconds']:.3f} s"
            + (" (cached)" if s["cached"] else "") + f"; contact {s['contact_fraction']:.1%} of the image"
            + (f"; drift removed ({s['drift']})" if s["drift"] != "none" else ""))
    if "normal_mean_error_deg" in s:
        line += f"; normals {s['normal_mean_error_deg']:.3f} deg mean error"
    if "depth_rmse_mm" in s:
        line += f"; depth RMSE {s['depth_rmse_mm'] * 1000:.1f} um"
    print(line)
    print(f"wrote {len(res.files)} files to {args.out}")
    return 0


def _reconstruct(args, threads):
    from pipeline.workflows.reconstruct import reconstruct

    return reconstruct(args.capture, calibration=args.calibration, illumination=args.illumination,
                       solver=args.solver, integrator=args.integrator, out=args.out, store=args.cache,
                       ratio=args.ratio, max_condition=args.max_condition, device=args.device,
                       images=not args.no_images, force=args.force, compile=args.compile, heal=not args.no_heal,
                       mask=args.mask, markers=args.markers, threads=threads, drift=args.drift, save=args.save,
                       precision=args.precision, progress=_bar(args), reference=args.reference,
                       mm_per_px=args.mm_per_px, profile=args.profile)


def _bar(args):
    """A frames progress bar on a terminal (None with --json or when stderr is not one)."""
    if args.json or not sys.stderr.isatty():
        return None
    from pipeline.capture.video_frames import is_video, video_frame_count
    from pipeline.streaming.inputs import read_capture
    from pipeline.workflows.task_pool import progress_bar

    if is_video(args.capture):  # the frames but the reference
        frames = video_frame_count(args.capture)[0] - (args.reference != "build")
    else:
        frames = int(read_capture(args.capture).data["frames"].shape[0])
    bar = progress_bar(frames, True, unit="frame", desc="reconstruct")
    return bar.update
