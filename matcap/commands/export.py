"""`matcap export RESULT/ --out TEXTURES/`: a capture result -> engine-ready texture set + glb (docs/export.md)."""
from __future__ import annotations

PRESET_NAMES = ("gltf", "unreal", "unity-hdrp", "blender")  # = matcap.export.PRESETS (kept here: lazy imports)
HEIGHT_METHODS = ("frankot-chellappa", "poisson-masked", "periodic")  # = matcap.height.METHODS


def register(sub) -> None:
    p = sub.add_parser(
        "export",
        help="write engine-ready SVBRDF textures (PNG/EXR, packed ORM / mask maps) and a glTF .glb from a result",
        description="Export a capture result folder as a texture set for Blender, Unreal, Unity, three.js and "
                    "Substance: NAME_basecolor.png (sRGB), NAME_normal.png (OpenGL, 16-bit), NAME_roughness.png, "
                    "NAME_metallic.png, NAME_orm.png, NAME_height.exr, NAME_mask.png, NAME.json and NAME.glb. "
                    "See docs/export.md for every file and convention.",
    )
    p.add_argument("result", help="capture result folder (normal.exr, mask.png, basecolor.png, ... capture.json); an "
                                  "earlier export, a texture set or a .glb load too (docs/formats.md)")
    p.add_argument("--out", required=True, help="folder for the texture set (created if missing)")
    p.add_argument("--name", help="file name prefix (default: the result folder's name)")
    p.add_argument("--preset", default="gltf", choices=PRESET_NAMES,
                   help="engine preset: which packed maps to add and the default normal convention (default gltf)")
    p.add_argument("--normal", choices=("gl", "dx"),
                   help="normal convention: dx also writes NAME_normal_dx.png (default: the preset's; gltf, "
                        "unity-hdrp, blender: gl; unreal: dx). NAME_normal.png is always OpenGL")
    p.add_argument("--no-height", action="store_true", help="do not write NAME_height.exr")
    p.add_argument("--height-method", default="frankot-chellappa", choices=HEIGHT_METHODS,
                   help="normal integration for the height map (poisson-masked respects the mask edge and depth "
                        "discontinuities; periodic is for tileable maps; default frankot-chellappa)")
    p.add_argument("--no-ao", action="store_true",
                   help="do not bake ambient occlusion from the height map (occlusion channels stay 1)")
    p.add_argument("--ao-radius", type=float, metavar="PX",
                   help="horizon search radius of the ambient occlusion in pixels (default 2%% of the larger side)")
    p.add_argument("--mesh", action="store_true", help="also write NAME_mesh.ply, the surface from the height map")
    p.add_argument("--fit-frame", action="store_true",
                   help="tangent space relative to the mean surface normal (sample photographed at an angle) "
                        "instead of the camera")
    p.add_argument("--no-glb", action="store_true", help="do not write NAME.glb")
    p.add_argument("--constant", action="append", metavar="MAP=V",
                   help="export roughness or metallic as the constant V on the mask, e.g. metallic=0 for a "
                        "non-metal (repeatable; the result folder is not changed)")
    p.add_argument("--tileable", action="store_true",
                   help="export the seamless tiled set (matcap tile runs first unless the input is already tiled); "
                        "the glb is a 3 x 3 repeat of the tile with REPEAT samplers")
    p.add_argument("--tile-size", type=int, metavar="N",
                   help="with --tileable: side of the tile, a power of two (default: chosen by matcap tile)")
    p.add_argument("--overwrite", action="store_true", help="replace files of an earlier export with the same name")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from matcap.errors import MatcapError
    from matcap.export import export

    if not Path(args.result).exists():
        raise MatcapError(f"{args.result}: no such result folder")
    if args.mesh and args.no_height:
        raise MatcapError("--mesh needs the height map; drop --no-height")
    source = args.result
    if args.constant:
        from matcap.capture import parse_constants
        from matcap.formats import load_maps

        source = load_maps(args.result).with_constants(parse_constants(args.constant))
    from matcap.formats import default_name

    paths = export(
        source, args.out, name=args.name or default_name(args.result), preset=args.preset,
        normal=args.normal, height=not args.no_height, mesh=args.mesh, overwrite=args.overwrite, glb=not args.no_glb,
        height_method=args.height_method,
        frame="fit" if args.fit_frame else "camera", occlusion=not args.no_ao, ao_radius=args.ao_radius,
        tileable=args.tileable, tile_size=args.tile_size,
    )
    for key, path in paths.items():
        print(f"{key:>10}  {path}")
    return 0
