"""`matcap tile RESULT --out TILED/`: every map of a result made seamless together (docs/export.md)."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser(
        "tile",
        help="make a flat sample's maps a seamless, tileable square texture set (with a periodic height map and a "
             "3 x 3 preview render)",
        description="Crop the largest square of surface, resample it to a power-of-two size and make every map "
                    "(normal, base colour, roughness, metallic) seamless with one shared cut and a gradient-domain "
                    "blend; the height map is integrated periodically from the tiled normals. Writes a result "
                    "folder (read by relight, export, gallery) with preview_3x3.png. See docs/export.md.",
    )
    p.add_argument("result", help="capture result folder (or any map source: an export, a texture set, a .glb)")
    p.add_argument("--out", required=True, help="folder for the tiled result (must not exist, or pass --overwrite)")
    p.add_argument("--size", type=int, metavar="N",
                   help="side of the tile in pixels, a power of two no larger than the largest square of surface: "
                        "all of the square, resampled (default: the largest power of two that fits with its "
                        "overlap of N/8 at the maps' own resolution, cropped; at most 4096)")
    p.add_argument("--spp", type=int, default=16, help="samples per pixel of the preview render (default 16)")
    p.add_argument("--no-preview", action="store_true", help="do not render preview_3x3.png")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from matcap.errors import MatcapError
    from matcap.tile import check_size, tile

    if not Path(args.result).exists():
        raise MatcapError(f"{args.result}: no such result folder")
    check_size(args.size)
    info = tile(args.result, args.out, size=args.size, overwrite=args.overwrite,
                preview_image=not args.no_preview, spp=args.spp, progress=not args.quiet)
    crop = info["crop"]
    print(f"tiled {info['size']} x {info['size']} from the {crop['side']} x {crop['side']} square at row "
          f"{crop['row']}, column {crop['col']} -> {args.out}")
    for name, e in info["seam_energy"].items():
        print(f"  {name:>10}  border / interior gradient energy {e['ratio']:.2f}  "
              f"(cut {info['cut_energy'][name]['ratio']:.2f})")
    return 0
