"""`matcap refine RESULT PHOTOS`: fit lights and maps of an existing result to its photos (again)."""
from __future__ import annotations

from matcap.commands.capture import add_fit_options


def register(sub) -> None:
    p = sub.add_parser(
        "refine",
        help="fit the lights and the maps of a capture result to its photos (photo-consistent refinement)",
        description="Re-run the photo-consistent refinement on a result folder written by `matcap capture`: start "
                    "from its maps, fit per-photo lights and per-pixel normal / base colour / roughness / metallic "
                    "to the photos, and replace the folder (atomically; needs --overwrite) or write --out.",
    )
    p.add_argument("result", help="result folder of `matcap capture`")
    p.add_argument("photos", help="the photo folder the result came from")
    p.add_argument("--out", help="write the refined result here instead of replacing RESULT")
    p.add_argument("--mask", help="mask image (default: the result's mask.png)")
    cg = p.add_mutually_exclusive_group()
    cg.add_argument("--linear", action="store_true", help="take 8-bit photos as linear (default: as the result did)")
    cg.add_argument("--srgb", action="store_true", help="decode 8-bit photos from sRGB (default: as the result did)")
    p.add_argument("--tone-curve", type=float, metavar="C",
                   help="undo a camera tone curve of contrast C (1-4; 1: none) before decoding 8-bit sRGB photos "
                        "(default: as the result did)")
    p.add_argument("--lamp-off", metavar="PHOTO",
                   help="a photo taken with the lamp off, subtracted from every photo (default: as the result did)")
    p.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    add_fit_options(p)
    p.add_argument("--overwrite", action="store_true", help="replace RESULT (or a non-empty --out)")
    p.add_argument("--quiet", action="store_true", help="no progress output (errors and notes still go to stderr)")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from matcap.capture import refine_maps
    from matcap.commands.capture import fit_settings, print_fit_notes
    from matcap.errors import MatcapError
    from matcap.photos import downscale_arrays, load_capture, read_lights_for
    from matcap.results import check_not_replacing_inputs, check_output_dir, read_result, write_result
    from networks.inference import check_device

    if args.seed < 0:
        raise MatcapError(f"--seed must be 0 or more, got {args.seed}")
    check_device(args.device)
    result = Path(args.result)
    if not result.is_dir():
        raise MatcapError(f"{result}: not a result folder (make one with matcap capture)")
    out = Path(args.out) if args.out else result
    if out.resolve() == result.resolve() and not args.overwrite:
        raise MatcapError(f"{result} would be replaced by the refined result; pass --overwrite (or --out DIR)")
    check_output_dir(out, args.overwrite)
    check_not_replacing_inputs(out, args.photos, args.mask)
    maps = read_result(result)
    meta = maps.meta
    if args.linear or args.srgb:
        linear = bool(args.linear)
    else:
        linear = (meta.get("decoding") or {}).get("8bit") == "linear" and args.tone_curve is None
    if args.tone_curve is not None:
        contrast = args.tone_curve
    else:
        contrast = 1.0 if (args.linear or args.srgb) else meta.get("tone_curve_contrast", 1.0)
    if linear and contrast != 1.0:
        raise MatcapError("--tone-curve undoes a camera's curve over sRGB; it contradicts --linear")
    lamp_off = args.lamp_off or meta.get("lamp_off_file")
    cap = load_capture(args.photos, mask=args.mask, linear=linear, contrast=contrast, lamp_off=lamp_off)
    names = meta.get("inputs") or cap.files
    missing = [n for n in names if n not in cap.files]
    if missing:
        raise MatcapError(f"{args.photos}: the result used {missing[0]}, which is not in this folder")
    images = [cap.images[cap.files.index(n)] for n in names]
    if images[0].shape[:2] != maps.shape:
        images, _ = downscale_arrays(images, None, max(maps.shape))
        if images[0].shape[:2] != maps.shape:
            raise MatcapError(f"{args.photos}: photos are {images[0].shape[1]}x{images[0].shape[0]} but the maps "
                              f"{maps.shape[1]}x{maps.shape[0]}")
    known = None
    if args.lights is not None:
        known = read_lights_for(args.lights, args.photos, [cap.files.index(n) for n in names])
    settings = fit_settings(args, args.light_model, args.glossy)
    refined, writer = refine_maps(maps, images, list(names), cap.colour, settings, meta.get("constant_maps") or {},
                                  progress=not args.quiet, lights=known, on_fit=print_fit_notes)
    refined.meta["tool"] = "matcap refine"
    refined.meta["colour_handling"] = cap.colour  # as decoded here (--linear / --srgb / --tone-curve may differ)
    refined.meta["lamp_off_file"] = cap.lamp_off_file
    refined.meta.pop("tone_curve_contrast", None)
    if contrast != 1.0 and "8-bit" in cap.colour:
        refined.meta["tone_curve_contrast"] = contrast
    write_result(refined, out, overwrite=True, extra_files=writer)
    r = refined.meta["refine"]
    print(f"wrote {out}/ (refined: re-render {r['psnr_db_mean']:.1f} dB, normals moved "
          f"{r['normal_change_deg_mean']:.1f} deg on average, {r['seconds']:.1f} s)")
    return 0
