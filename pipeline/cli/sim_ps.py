"""``iristac sim ps-object``: a synthetic photometric-stereo capture (calls :func:`sim.ps_objects.write_ps_capture`)."""

from __future__ import annotations

from pipeline.cli._common import add_json_flag, print_json


def register(group):
    text = ("render a sphere or a bumpy object under far-field lights (DiLiGenT-like, 96 by default) with "
            "highlights, cast shadows, noise and 16-bit quantisation, as a capture file")
    p = group.add_parser("ps-object", help=text, description=text)
    obj = p.add_argument_group("object")
    obj.add_argument("--object", choices=["sphere", "bumpy"], default="sphere")
    obj.add_argument("--size", type=int, default=160, help="object window, pixels (default 160)")
    obj.add_argument("--radius-px", type=float, default=71.0,
                     help="object radius, pixels (default 71: 15.8k pixels)")
    obj.add_argument("--frame", nargs=2, type=int, metavar=("H", "W"), help="place it in a black frame of this size")
    lights = p.add_argument_group("lights")
    lights.add_argument("--lights", nargs=2, type=int, default=(8, 12), metavar=("ROWS", "COLS"),
                        help="light grid (default 8 12 = 96 lights)")
    lights.add_argument("--max-angle", type=float, default=45.0, help="corner lights' angle from the view axis, deg")
    refl = p.add_argument_group("highlights and shadows")
    refl.add_argument("--specular", type=float, default=0.04, help="Fresnel F0 of the specular lobe (0: Lambertian)")
    refl.add_argument("--roughness", type=float, default=0.3, help="GGX roughness of the lobe")
    refl.add_argument("--no-cast-shadows", action="store_true")
    noise = p.add_argument_group("camera noise and seed")
    noise.add_argument("--read-noise", type=float, default=20.0, help="DN (default 20)")
    noise.add_argument("--shot-noise", type=float, default=1.0, help="DN per electron (default 1)")
    noise.add_argument("--seed", type=int, default=0,
                       help="seed of the bumpy object, the lights and the noise (default 0)")
    outs = p.add_argument_group("what is written")
    outs.add_argument("--out", required=True, metavar="capture.h5")
    add_json_flag(outs)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from sim.ps_objects import write_ps_capture

    r = write_ps_capture(args.out, args.object, size=args.size, radius_px=args.radius_px, frame=args.frame,
                         lights=args.lights, max_angle_deg=args.max_angle, specular=args.specular,
                         roughness=args.roughness, cast_shadows=not args.no_cast_shadows,
                         read_noise=args.read_noise, shot_noise=args.shot_noise, seed=args.seed)
    if args.json:
        print_json(r)
    else:
        print(f"wrote {r['out']}: {r['object']} under {r['lights']} lights, {r['width']}x{r['height']}, "
              f"{r['mask_pixels']} object pixels; effects {', '.join(r['effects'])}")
    return 0
