"""`matcap capture PHOTOS/`: photos under several lights -> normal (+ BRDF) maps, optional relight and export."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from matcap.commands.export import PRESET_NAMES


def _xyz(text: str) -> tuple[float, float, float]:
    try:
        x, y, z = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z (three numbers), got {text!r}") from None
    return x, y, z


def register(sub) -> None:
    p = sub.add_parser(
        "capture",
        help="recover normal / base color / roughness / metallic maps from photos under several lights",
        description="Recover SVBRDF maps from a folder of photos taken from one fixed camera under several lights.",
    )
    p.add_argument("photos", help="folder of images (PNG/JPEG/TIFF/EXR/HDR); mask.* in it is used as the mask")
    p.add_argument("--out", help="result folder (default: ./PHOTOS-matcap, named after the photos folder, in the "
                                 "current folder)")
    p.add_argument("--mask", help="mask image (> 0 is the object); default: mask.* in the folder, else none")
    p.add_argument("--weights", action="append", metavar="FILE_OR_DIR",
                   help="model weights: our .safetensors or the published .pytmodel files, or a folder of them "
                        "(repeatable; default: the bundled model)")
    p.add_argument("--max-images", type=int, help="use at most K images (chosen at random with --seed)")
    p.add_argument("--seed", type=int, default=0, help="seed for image subset and pixel sampling (default 0)")
    cg = p.add_mutually_exclusive_group()
    cg.add_argument("--linear", action="store_true", default=None,
                    help="take 8-bit images as linear (default: the fit of the photos decides; with --no-refine: "
                         "decode sRGB)")
    cg.add_argument("--srgb", dest="linear", action="store_false", help="decode 8-bit images from sRGB")
    p.add_argument("--tone-curve", type=float, default=1.0, metavar="C",
                   help="undo a camera's S-shaped tone curve of contrast C (1-4; default 1: none) before decoding "
                        "8-bit photos from sRGB (implies --srgb; recorded in capture.json)")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cpu, cuda, cuda:1 (default cpu)")
    p.add_argument("--pixel-samples", type=int, help="pixels per sample set (default: the model's)")
    p.add_argument("--bf16", action="store_true",
                   help="run the networks under bfloat16 autocast (faster on GPUs and on CPUs with AVX512-BF16 or "
                        "AMX; emulated, so slower, on other CPUs: a warning says so)")
    p.add_argument("--views", type=int, choices=(1, 2, 4, 8), default=1,
                   help="average the prediction over this many mirrored/transposed copies of the input "
                        "(test-time augmentation; costs that many times the time; default 1)")
    p.add_argument("--max-side", type=int, metavar="PX",
                   help="shrink the photos first so that their longer side is at most PX (a quick pass over large "
                        "photos; the maps come out at that size)")
    p.add_argument("--constant", action="append", metavar="MAP=V",
                   help="replace the estimated roughness or metallic map by V on the mask, e.g. metallic=0 for a "
                        "non-metal (repeatable; recorded in capture.json)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--refine", dest="refine", action="store_true", default=None,
                   help="after the networks, fit the lights and the maps to the photos (the default; docs/refine.md)")
    g.add_argument("--no-refine", dest="refine", action="store_false",
                   help="keep the networks' maps as they are (no lights.json / fit.json)")
    add_fit_options(p)
    p.add_argument("--ball", metavar="auto|MASK",
                   help="a mirror ball (chrome sphere) is in the photos: take the lights from its highlights, found "
                        "by itself ('auto') or inside a mask image of the ball; the ball is kept out of the object's "
                        "mask and calibration.png shows what was found")
    p.add_argument("--lamp-off", metavar="PHOTO",
                   help="a photo taken with the lamp off (the light of the room alone), outside the photos' folder: "
                        "subtracted from every photo, so that a room light that stays on does not lean the lamps")
    p.add_argument("--flat", action=argparse.BooleanOptionalAction, default=None,
                   help="the photos show a flat sample (a material swatch facing the camera): fit it as a plane "
                        "whose lamps are found from the falloff of their light over it, unless --lights / --ball "
                        "give them (default: decided from the networks' normals, and said in one line)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing, non-empty --out folder")
    p.add_argument("--relight", action="append", metavar="ENV",
                   help="also relight under this EXR/HDR env map (repeatable)")
    p.add_argument("--point", type=_xyz, action="append", metavar="X,Y,Z", help="also relight under a point light here")
    p.add_argument("--spp", type=int, help="samples per pixel for --relight / --point renders (default 16)")
    p.add_argument("--export", metavar="DIR", help="also export an engine-ready texture set to DIR")
    p.add_argument("--preset", default="gltf", choices=PRESET_NAMES,
                   help="texture-set preset for --export (default gltf; see `matcap export --help`)")
    p.add_argument("--quiet", action="store_true", help="no progress output (errors and notes still go to stderr)")
    p.set_defaults(func=run)


def add_fit_options(p) -> None:
    """The fit's options, spelled the same in `matcap capture` and `matcap refine`."""
    p.add_argument("--lights", metavar="FILE",
                   help="the lights you know, one per photo: a lights.json (from matcap calibrate or a previous "
                        "capture), an RTI .lp file, or a text table 'x y z [r g b]' per photo (docs/lights.md); the "
                        "fit holds their directions instead of estimating them")
    p.add_argument("--light-model", choices=("directional", "point"), default="directional",
                   help="estimated lights: distant (default; where they fail to explain the photos, lamps a few "
                        "object sizes away are tried and kept if they do) or a lamp per photo whose distance the fit "
                        "finds, always")
    p.add_argument("--glossy", action=argparse.BooleanOptionalAction, default=True,
                   help="estimated lights: where a matte surface does not explain the photos and the lamps are not "
                        "near, fit distant lamps anyway if one lamp per photo and a fixed, faint room light explain "
                        "them (a glossy object; on by default)")


def fit_settings(args, light_model: str, glossy: bool):
    """RefineSettings from the shared fit options: ``--light-model`` is ``model.light``, ``--glossy`` /
    ``--no-glossy`` is ``candidates.glossy``, ``--seed`` and ``--device`` are ``seed`` and ``device``."""
    from matcap.refine import RefineSettings

    return RefineSettings(seed=args.seed, device=args.device).replace(
        {"model.light": light_model, "candidates.glossy": glossy})


#: What a candidate light model that the settings left off the estimated-lights path is for, and the flag that
#: adds it (:func:`matcap.refine.estimated_lights.candidate_models`).
CANDIDATE_TIPS = {"glossy": "a glossy object under a far lamp: try --glossy",
                  "near": "a lamp within a few object sizes: try --light-model point"}


def fit_notes(result, settings) -> list[str]:
    """The lines `matcap capture` and `matcap refine` print once the fit is done (``result``: a
    :class:`matcap.refine.RefineResult`, ``settings`` those it ran with): its light-variation warning; where the
    lamps were found near, how near; where the relief's sign was left to a prior that hardly tells (its twin ratio
    at least ``checks.twin``), so; where known lights' photos share a room's light the fit took in, how much; where
    the networks' maps were kept, why (the fit's reasons) and what to do: give the lights, or add a candidate light
    model the settings left off where only the Lambertian part of the check failed."""
    from matcap.refine.estimated_lights import candidate_models

    lines = [f"warning: {result.warning}"] if result.warning else []
    lin = result.report.get("linear") or {}
    radii = (result.report.get("near_lamps") or {}).get("light_distance_radii")
    if lin.get("check") == "near lamps" and radii is not None:
        lines.append(f"note: the lamps were near the object (median {radii:.1f} object radii away): fitted as point "
                     f"lights, their positions in lights.json")
    given = result.report.get("lights") or {}
    if given.get("room_kept"):
        lines.append(f"note: a room's light stayed on in every photo (about {given['room_share']:.0%} of the lamps' "
                     f"light): the fit models it, but the photos hold less of the lamps' shading; dim it for "
                     f"sharper maps")
    twin = lin.get("twin_ratio")
    if not result.report.get("kept_network_maps") and twin is not None and twin >= settings.checks.twin:
        lines.append(f"note: with no outline to go by, bumps and dents give the same photos under lights not given, "
                     f"and the networks hardly prefer one (twin ratio {twin:.2f}): if the relief looks inverted, give "
                     f"the lights with --lights FILE or put a mirror ball in the photos (--ball auto)")
    if result.report.get("kept_network_maps"):
        tips = []
        if lin.get("lambertian_only") and settings.model.light != "point":
            listed = candidate_models(settings)
            tips = [tip for model, tip in CANDIDATE_TIPS.items() if model not in listed]
        flat_distant = (result.report.get("flat") or {}).get("lamps") == "distant"
        if flat_distant:
            tips.append("or shoot it under a lamp 1-3 sample widths away, whose falloff places it")
        hint = f" ({'; '.join(tips)})" if tips else ""
        kept = "the networks' roughness and metallic" if flat_distant else "the networks' maps"
        lines.append(f"note: the fit kept {kept}: {lin.get('reason')}. Lights you know make the fit "
                     f"well-posed: give them with --lights FILE (a table of their directions will do), or put a mirror "
                     f"ball in the photos (--ball auto)"
                     f"{hint}")
    return lines


def print_fit_notes(result, settings) -> None:
    """:func:`fit_notes` on stderr."""
    import sys

    for line in fit_notes(result, settings):
        print(line, file=sys.stderr)


def run(args) -> int:
    from matcap.capture import capture, parse_constants
    from matcap.errors import MatcapError
    from networks.inference import check_device

    photos = Path(args.photos)
    out = Path(args.out) if args.out else Path(f"{photos.resolve().name}-matcap")  # in the current folder
    if args.max_images is not None and args.max_images < 2:
        raise MatcapError(f"--max-images must be at least 2, got {args.max_images}")
    if args.pixel_samples is not None and args.pixel_samples < 1:
        raise MatcapError(f"--pixel-samples must be at least 1, got {args.pixel_samples}")
    if args.seed < 0:
        raise MatcapError(f"--seed must be 0 or more, got {args.seed}")
    constants = parse_constants(args.constant)
    check_device(args.device)
    from matcap.capture import REFINE_BY_DEFAULT

    do_refine = REFINE_BY_DEFAULT if args.refine is None else args.refine
    if args.lights is not None or args.ball is not None:
        if not do_refine:
            raise MatcapError(f"{'--lights' if args.lights is not None else '--ball'} gives the fit its lights; it "
                              f"has no use with --no-refine")
        if args.lights is not None and args.ball is not None:
            raise MatcapError("--lights and --ball both give the lights; choose one")
    if args.flat and not do_refine:
        raise MatcapError("--flat fits a plane's lamps and maps to the photos; it has no use with --no-refine")
    settings = fit_settings(args, args.light_model, args.glossy) if do_refine else None
    spp = {"spp": args.spp} if args.spp is not None else {}
    relight = [{"env": env, **spp} for env in args.relight or []] + [{"point": p, **spp} for p in args.point or []]
    if args.spp is not None and not relight:
        from matcap.relight import check_spp

        check_spp(args.spp)
    export = {"out": args.export, "preset": args.preset} if args.export else None
    maps, out = capture(
        photos, out, mask=args.mask, linear=args.linear,
        contrast=args.tone_curve, overwrite=args.overwrite,
        weights=args.weights, max_images=args.max_images, seed=args.seed, device=args.device,
        pixel_samples=args.pixel_samples, bf16=args.bf16, views=args.views, progress=not args.quiet,
        constants=constants, max_side=args.max_side, relight=relight, export=export, refine=do_refine,
        refine_settings=settings, lights=args.lights, ball=args.ball, flat=args.flat, lamp_off=args.lamp_off,
        on_fit=print_fit_notes,
    )
    flat = maps.meta.get("flat") or {}
    lamps = (maps.meta.get("refine") or {}).get("flat_lamps")
    if flat.get("chosen_by") == "detection" and flat.get("flat"):
        print(f"note: taken as a flat sample ({flat['why']})"
              + ("; fitted as a plane under lamps found from their falloff" if lamps == "near" else "")
              + "; --no-flat takes it as an object", file=sys.stderr)
    t = maps.meta["timings"]
    print(f"wrote {out}/ ({maps.shape[1]}x{maps.shape[0]}, {len(maps.meta['images_used'])} images, "
          f"{'normal + BRDF' if maps.has_brdf else 'normal'} maps, {t['total_s']:.1f} s"
          + (f" + colour decision {t['colour_decision_s']:.1f} s" if "colour_decision_s" in t else "")
          + (f" + refinement {t['refine_s']:.1f} s, re-render {maps.meta['refine']['psnr_db_mean']:.1f} dB"
             if "refine" in maps.meta else "") + ")")
    if relight:
        print(f"relit renders in {out}/")
    if export:
        print(f"texture set in {args.export}/")
    return 0
