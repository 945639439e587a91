"""`matcap calibrate PHOTOS --out rig.json`: light directions from a mirror ball photographed under each light."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser(
        "calibrate",
        help="light directions (and relative intensities) from photos of a mirror ball, as a lights.json",
        description="Find the mirror ball in a folder of photos (one light each, camera fixed), locate each photo's "
                    "highlight and write the light directions as a lights.json (for capture --lights), with "
                    "calibration.png beside it: the ball's circle and each highlight, numbered in photo order. "
                    "Camera model: orthographic (view along -z) unless --focal-px is given.",
    )
    p.add_argument("photos", help="folder of photos of the ball (PNG/JPEG/TIFF/EXR/HDR), in natural name order")
    p.add_argument("--out", required=True, metavar="RIG_JSON",
                   help="the light file to write (e.g. rig.json), outside the photos folder")
    p.add_argument("--ball-mask", metavar="FILE",
                   help="image that is bright (> half) on the ball's disc, where the ball is not found by itself")
    p.add_argument("--focal-px", type=float, metavar="F",
                   help="perspective camera of this focal length in pixels (principal point at the image centre); "
                        "default: orthographic")
    cg = p.add_mutually_exclusive_group()
    cg.add_argument("--linear", action="store_true", default=False, help="take 8-bit images as linear")
    cg.add_argument("--srgb", dest="linear", action="store_false", help="decode 8-bit images from sRGB (default)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing light file and calibration.png")
    p.add_argument("--quiet", action="store_true", help="print nothing on success")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    import numpy as np

    from matcap.calibrate import DIAGNOSTIC, calibrate_folder

    cal = calibrate_folder(args.photos, args.out, ball_mask=args.ball_mask, focal_px=args.focal_px,
                           linear=args.linear, overwrite=args.overwrite)
    if args.quiet:
        return 0
    cx, cy, r = cal.circle
    spread = np.array([q["spread_deg"] for q in cal.quality])
    inten = "relative intensities" if cal.intensities is not None else "intensities unknown (clipped highlights)"
    found = "found" if cal.circle_source == "auto" else "from the mask"
    print(f"ball {found} at ({cx:.1f}, {cy:.1f}) px, radius {r:.1f} px; {len(cal.names)} lights, {inten}; "
          f"camera {cal.camera}; highlight spread {np.median(spread):.1f} deg median")
    print(f"wrote {args.out} and {Path(args.out).parent / DIAGNOSTIC}")
    return 0
