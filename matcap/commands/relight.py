"""`matcap relight RESULT/`: render SVBRDF maps under environment maps, point or directional lights."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser(
        "relight",
        help="render recovered (or any) SVBRDF maps under new light with Mitsuba 3",
        description="Relight a capture result folder (or a PBR texture set folder) with Mitsuba 3's Principled BSDF. "
                    "Writes relight_<name>.exr (linear) and relight_<name>.png (ACES-fit tone mapped sRGB, "
                    "transparent background) per environment map.",
    )
    p.add_argument("source", help="capture result folder (normal.exr ...), a `matcap export` folder, a texture set "
                                  "(Substance / Poly Haven / basecolor, arm/orm, normal_gl names) or a .glb "
                                  "(docs/formats.md)")
    p.add_argument("--env", action="append", metavar="EXR_OR_HDR",
                   help="equirectangular environment map, or a folder of them (repeatable; default: the bundled "
                        "studio map unless --point/--directional is given)")
    p.add_argument("--rotate", type=float, default=0.0, metavar="DEG", help="turn the environment about +y (up)")
    p.add_argument("--exposure", type=float, default=0.0, metavar="EV", help="scale every light by 2**EV")
    p.add_argument("--point", metavar="X,Y,Z", help="add a point light (camera space; the surface spans x in [-1, 1])")
    p.add_argument("--intensity", metavar="W|R,G,B",
                   help="point light intensity in W/sr (default pi*|P|^2: irradiance pi at the centre)")
    p.add_argument("--directional", metavar="X,Y,Z", help="add a directional light coming from this direction")
    p.add_argument("--irradiance", metavar="E|R,G,B", help="directional light irradiance (default pi)")
    p.add_argument("--lights", metavar="LIGHTS_JSON",
                   help="re-render an input photo under its light estimated by the fit (a lights.json; default "
                        "SOURCE/lights.json when --image is given); writes relight_input_<K>.exr/.png")
    p.add_argument("--image", type=int, metavar="K",
                   help="with --lights: the index of the input photo to re-render (0 = the first)")
    p.add_argument("--spp", type=int, help="samples per pixel (default 16)")
    p.add_argument("--size", metavar="WxH", help="output size (default: the maps' size); one number = longer side")
    p.add_argument("--tonemap", choices=("aces", "clip"),
                   help="PNG tone mapping (default aces; clip with --lights, so the PNG compares with the photo)")
    p.add_argument("--seed", type=int, default=0, help="sampler seed (default 0)")
    p.add_argument("--constant", action="append", metavar="MAP=V",
                   help="render with roughness or metallic set to V on the mask, e.g. metallic=0 (repeatable)")
    p.add_argument("--out", help="output folder (default: the source folder, or the folder of a .glb / NAME.json)")
    p.add_argument("--overwrite", action="store_true", help="replace existing relight_* files")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from matcap.relight import env_paths, relight

    file_lights = args.lights is not None or args.image is not None
    envs = None
    if args.env:
        envs = args.env if file_lights else env_paths(args.env)  # with --lights: refused by relight() in one line
    source_path = Path(args.source)
    out = Path(args.out) if args.out else (source_path.parent if source_path.is_file() else source_path)
    source = args.source
    tonemap = args.tonemap or ("clip" if file_lights else "aces")
    if args.constant:
        from matcap.capture import parse_constants
        from matcap.relight import load_maps

        source = load_maps(args.source).with_constants(parse_constants(args.constant))
    images = relight(
        source, env=envs, rotate=args.rotate, exposure=args.exposure, point=args.point,
        intensity=args.intensity, directional=args.directional, irradiance=args.irradiance, spp=args.spp,
        size=args.size, out=out, overwrite=args.overwrite, seed=args.seed, tonemap_mode=tonemap,
        progress=not args.quiet, lights=args.lights, image=args.image,
    )
    h, w = images[0].shape[:2]
    print(f"wrote {len(images)} render(s) ({w}x{h}) to {out}/ as relight_*.exr and relight_*.png")
    return 0
