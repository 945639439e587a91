"""`matcap gallery RESULT/ --envs DIR --out gallery/`: environment grid, light orbit and a static index.html."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser(
        "gallery",
        help="build a static HTML gallery: maps, renders under environment maps, a light-orbit animation",
        description="Render SVBRDF maps (capture result or texture set) under each environment map and under a "
                    "light circling the object; write contact sheets, orbit.gif (+ mp4 or webp) and index.html.",
    )
    p.add_argument("source",
                   help="capture result folder (normal.exr ...) or texture set (basecolor, arm/orm, normal_gl)")
    p.add_argument("--envs", nargs="+", metavar="ENV_DIR_OR_FILE",
                   help="environment maps (.exr/.hdr) or folders of them (default: the bundled studio map)")
    p.add_argument("--orbit", type=int, default=36, metavar="N", help="orbit frames (default 36; 0 = none)")
    p.add_argument("--orbit-light", choices=("directional", "point"), default="directional",
                   help="light that circles the object (default directional)")
    p.add_argument("--elevation", type=float, default=40.0, metavar="DEG",
                   help="orbit light elevation above the surface plane (default 40)")
    p.add_argument("--rotate", type=float, default=0.0, metavar="DEG", help="turn the environments about +y")
    p.add_argument("--exposure", type=float, default=0.0, metavar="EV", help="scale every light by 2**EV")
    p.add_argument("--spp", type=int, help="samples per pixel for environment renders (default 16)")
    p.add_argument("--orbit-spp", type=int, default=4, help="samples per pixel for orbit frames (default 4)")
    p.add_argument("--size", default="512", metavar="N|WxH", help="render size; one number = longer side (default 512)")
    p.add_argument("--fps", type=float, default=12.0, help="orbit animation frame rate (default 12)")
    p.add_argument("--tonemap", choices=("aces", "clip"), default="aces", help="tone mapping (default aces)")
    p.add_argument("--out", required=True, help="gallery folder to create")
    p.add_argument("--overwrite", action="store_true", help="replace an existing, non-empty --out folder")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def run(args) -> int:
    from matcap.gallery import gallery
    from matcap.results import check_output_dir

    check_output_dir(args.out, args.overwrite)  # fail before rendering anything
    info = gallery(
        args.source, envs=args.envs, orbit=args.orbit, out=args.out, size=args.size, spp=args.spp,
        orbit_spp=args.orbit_spp, orbit_light=args.orbit_light, elevation=args.elevation, rotate=args.rotate,
        exposure=args.exposure, fps=args.fps, tonemap_mode=args.tonemap, overwrite=args.overwrite,
        progress=not args.quiet,
    )
    print(f"wrote {args.out}/index.html ({len(info['renders'])} environment render(s), "
          f"{info['orbit']['frames']} orbit frames, {info['timings']['total_s']:.1f} s)")
    return 0
