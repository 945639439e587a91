"""Scripted galleries: environment grid, light orbit (GIF + MP4/WebP + contact sheet) and a static ``index.html``.

    from matcap import gallery
    gallery("result/", envs="envmaps/", orbit=36, out="gallery/")

Layout of ``out`` (static files only; ``index.html`` opens from disk with no server):

    index.html            maps side by side, the renders, the orbit animation, settings
    maps/{normal,basecolor,roughness,metallic}.png
    renders/<env>.exr     linear radiance (black background)   renders/<env>.png   tone mapped, transparent background
    envs.png              labelled contact sheet, one tile per environment map
    orbit.gif             the light orbit (N frames), plus orbit.mp4 (ffmpeg, H.264) or orbit.webp when no encoder
    orbit_sheet.png       still contact sheet of the orbit (up to 12 frames, labelled with the light's azimuth)
    gallery.json          settings and timings

The folder is built in a temporary sibling and renamed into place when complete.
"""
from __future__ import annotations

import html
import sys
import types
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np

from matcap.errors import MatcapError
from matcap.imageio import write_json_atomic, write_text_atomic
from matcap.relight import (
    TONEMAPS,
    build_lights,
    downsample_maps,
    env_paths,
    fit_size,
    load_maps,
    tonemap,
    write_render,
)

BACKDROP = (0.19, 0.19, 0.19)  # sRGB grey behind masked-out pixels in sheets and animations
ORBIT_SHEET_MAX = 12


def _composite(srgb: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """sRGB [0,1] image over the backdrop by ``coverage`` -> uint8 RGB."""
    a = coverage[..., None]
    out = srgb[..., :3] * a + np.asarray(BACKDROP, np.float32) * (1.0 - a)
    return np.round(np.clip(out, 0, 1) * 255).astype(np.uint8)


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow without FreeType sizes
        return ImageFont.load_default()


def contact_sheet(tiles: list[np.ndarray], labels: list[str], cols: int | None = None, pad: int = 6) -> np.ndarray:
    """Tiles (uint8 RGB, same size) in a grid, each with its label underneath -> uint8 RGB image."""
    from PIL import Image, ImageDraw

    if not tiles:
        raise ValueError("no tiles")
    th, tw = tiles[0].shape[:2]
    cols = cols or int(np.ceil(np.sqrt(len(tiles))))
    rows = int(np.ceil(len(tiles) / cols))
    font_size = max(10, min(18, tw // 14))
    label_h = font_size + 8
    sheet = Image.new("RGB", (cols * (tw + pad) + pad, rows * (th + label_h + pad) + pad), (24, 24, 24))
    draw = ImageDraw.Draw(sheet)
    font = _font(font_size)
    for i, (tile, label) in enumerate(zip(tiles, labels)):
        r, c = divmod(i, cols)
        x, y = pad + c * (tw + pad), pad + r * (th + label_h + pad)
        sheet.paste(Image.fromarray(tile), (x, y))
        text = label
        while len(text) > 3 and draw.textlength(text, font=font) > tw:
            text = text[:-2]
        if text != label:
            text = text[:-1] + "…"
        draw.text((x + 2, y + th + 3), text, fill=(230, 230, 230), font=font)
    return np.asarray(sheet)


def _save_rgb(path: Path, rgb: np.ndarray) -> None:
    from matcap.imageio import write_png

    write_png(path, rgb.astype(np.float32) / 255.0, bits=8)


def write_animation(frames: list[np.ndarray], folder: Path, stem: str, fps: float) -> dict[str, str]:
    """``<stem>.gif`` (Pillow) and ``<stem>.mp4`` (ffmpeg H.264) or, without a working ffmpeg, ``<stem>.webp``."""
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    duration = int(round(1000.0 / fps))
    files = {}
    gif = folder / f"{stem}.gif"
    images[0].save(gif, save_all=True, append_images=images[1:], duration=duration, loop=0, optimize=False)
    files["gif"] = gif.name
    ffmpeg = shutil.which("ffmpeg")
    if ffmpeg:
        h, w = frames[0].shape[:2]
        mp4 = folder / f"{stem}.mp4"
        cmd = [ffmpeg, "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w}x{h}",
               "-r", f"{fps:g}", "-i", "-", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-c:v", "libx264",
               "-pix_fmt", "yuv420p", "-movflags", "+faststart", str(mp4)]
        try:
            proc = subprocess.run(cmd, input=b"".join(np.ascontiguousarray(f).tobytes() for f in frames),
                                  capture_output=True, timeout=300)
            if proc.returncode == 0 and mp4.is_file() and mp4.stat().st_size > 0:
                files["mp4"] = mp4.name
        except (OSError, subprocess.TimeoutExpired):
            pass
    if "mp4" not in files:
        webp = folder / f"{stem}.webp"
        images[0].save(webp, save_all=True, append_images=images[1:], duration=duration, loop=0, quality=90)
        files["webp"] = webp.name
    return files


def orbit_lights(n: int, kind: str = "directional", elevation: float = 40.0, distance: float = 3.0,
                 gain: float = 1.0) -> list:
    """``n`` lights circling the view axis at ``elevation`` degrees above the surface plane, starting at +x
    (right) and turning counter-clockwise as seen by the camera. Directional: irradiance pi; point: at
    ``distance``, intensity pi * distance^2 (the same irradiance at the centre)."""
    from scenes.lights import DirectionalLight, PointLight

    el = np.radians(elevation)
    lights = []
    for k in range(n):
        az = 2.0 * np.pi * k / n
        d = (float(np.cos(el) * np.cos(az)), float(np.cos(el) * np.sin(az)), float(np.sin(el)))
        if kind == "directional":
            lights.append(DirectionalLight(direction=d, irradiance=(np.pi * gain,) * 3))
        elif kind == "point":
            lights.append(PointLight(position=tuple(distance * v for v in d),
                                     intensity=(np.pi * distance**2 * gain,) * 3))
        else:
            raise MatcapError(f"orbit light must be 'directional' or 'point', got {kind!r}")
    return lights


def _map_images(maps, folder: Path) -> dict[str, str]:
    """Display PNGs of the four maps (the ``gallery`` layout of :mod:`matcap.formats`: normal as (n+1)/2, base
    colour sRGB, roughness / metallic grey; missing maps shown with their defaults, black off-mask)."""
    from matcap import formats

    src = formats.sources(maps, defaults={"base_color": (0.8, 0.8, 0.8), "roughness": 0.5, "metallic": 0.0},
                          masked=True)
    out = {}
    for spec in formats.files_of("gallery", ("normal", "basecolor", "roughness", "metallic")):
        formats.write_file(folder, spec, src)
        out[spec.key] = spec.file
    return out


def _page(info: dict) -> str:
    e = html.escape
    defaults = info["defaulted_maps"]
    maps_html = "\n".join(
        f'<figure><img src="{e(path)}" alt="{e(name)} map"><figcaption>{e(name)}'
        f'{" (default)" if name in defaults else ""}</figcaption></figure>'
        for name, path in info["maps"].items()
    )
    renders_html = "\n".join(
        f'<figure><a href="{e(r["exr"])}"><img src="{e(r["png"])}" alt="render under {e(r["name"])}"></a>'
        f'<figcaption>{e(r["name"])}</figcaption></figure>'
        for r in info["renders"]
    )
    anim = info["orbit"]["files"]
    video = ""
    if "mp4" in anim:
        video = (f'<figure><video src="{e(anim["mp4"])}" autoplay loop muted playsinline controls></video>'
                 f'<figcaption>orbit (MP4)</figcaption></figure>')
    elif "webp" in anim:
        video = (f'<figure><img src="{e(anim["webp"])}" alt="orbit animation (WebP)">'
                 f'<figcaption>orbit (WebP)</figcaption></figure>')
    s = info["settings"]
    settings = "".join(f"<tr><th>{e(str(k))}</th><td>{e(str(v))}</td></tr>" for k, v in s.items())
    return f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>matcap gallery: {e(info["source"])}</title>
<style>
body {{ background: #181818; color: #ddd; font-family: system-ui, sans-serif; margin: 1.5em; }}
h1 {{ font-size: 1.3em; }} h2 {{ font-size: 1.1em; margin-top: 1.6em; }}
.row {{ display: flex; flex-wrap: wrap; gap: 12px; }}
figure {{ margin: 0; }} figcaption {{ font-size: 0.85em; color: #aaa; padding-top: 4px; }}
.row img, .row video {{ width: 256px; height: auto; background: #303030; display: block; }}
img.sheet {{ max-width: 100%; height: auto; }}
table {{ border-collapse: collapse; font-size: 0.85em; }} th, td {{ text-align: left; padding: 2px 10px 2px 0; }}
</style>
</head>
<body>
<h1>matcap gallery — {e(info["source"])}</h1>
<h2>Maps</h2>
<div class="row">
{maps_html}
</div>
<h2>Relit under environment maps</h2>
<div class="row">
{renders_html}
</div>
<p><img class="sheet" src="{e(info["env_sheet"])}" alt="environment contact sheet"></p>
<h2>Light orbit ({info["orbit"]["frames"]} frames, {e(info["orbit"]["light"])} light)</h2>
<div class="row">
<figure><img src="{e(anim["gif"])}" alt="orbit animation (GIF)"><figcaption>orbit (GIF)</figcaption></figure>
{video}
</div>
<p><img class="sheet" src="{e(info["orbit"]["sheet"])}" alt="orbit contact sheet"></p>
<h2>Settings</h2>
<table>{settings}</table>
<p>Tone mapping: {e(info["tonemap_text"])} Renders: Mitsuba 3, Principled BSDF on a flat plane, orthographic camera
(framed like the input photos). Masked-out pixels are transparent in the PNGs and black in the EXRs.</p>
</body>
</html>
"""


TONEMAP_TEXT = {
    "aces": "ACES filmic fit (Narkowicz 2015) of linear radiance, clipped, sRGB-encoded.",
    "clip": "linear radiance clipped to [0, 1], sRGB-encoded.",
}


def gallery(
    result_dir_or_maps,
    envs=None,
    orbit: int = 36,
    out="gallery",
    *,
    size=512,
    spp: int | None = None,
    orbit_spp: int = 4,
    orbit_light: str = "directional",
    elevation: float = 40.0,
    rotate: float = 0.0,
    exposure: float = 0.0,
    fps: float = 12.0,
    tonemap_mode: str = "aces",
    overwrite: bool = False,
    seed: int = 0,
    progress: bool = True,
) -> dict:
    """Build a gallery folder (see the module docstring); returns the summary written to ``gallery.json``.

    envs: an .exr/.hdr file, a folder of them, or a list (None: the bundled studio map). orbit: number of
    frames (0: no orbit). size: longer side in pixels (maps are area-downsampled to it) or ``"WxH"``.
    spp: samples per pixel for the environment renders (default ``renderers.relight.DEFAULT_SPP``);
    orbit_spp: for the orbit frames (point/directional light: noise-free, spp only anti-aliases).
    """
    from matcap.results import check_not_replacing_inputs, output_dir
    from networks.progress import progress as progress_bar
    from renderers.relight import DEFAULT_SPP, mask_coverage, render

    t0 = time.perf_counter()
    spp = DEFAULT_SPP if spp is None else int(spp)
    if spp < 1 or orbit_spp < 1:
        raise MatcapError("spp must be >= 1")
    if orbit < 0 or orbit > 720:
        raise MatcapError(f"orbit must be between 0 and 720 frames, got {orbit}")
    if not (0.0 < fps <= 60.0):
        raise MatcapError(f"fps must be in (0, 60], got {fps}")
    if tonemap_mode not in TONEMAPS:
        raise MatcapError(f"tone mapping must be one of {', '.join(TONEMAPS)}, got {tonemap_mode!r}")
    if not (0.0 < elevation < 90.0):
        raise MatcapError(f"elevation must be between 0 and 90 degrees, got {elevation}")
    source = result_dir_or_maps
    maps = load_maps(source)
    defaulted = [n for n, v in (("basecolor", maps.base_color), ("roughness", maps.roughness),
                                ("metallic", maps.metallic)) if v is None]
    width, height = fit_size(maps, size)
    if max(width, height) < max(maps.shape):
        maps = downsample_maps(maps, max(width, height))
        width, height = fit_size(maps, (width, height))
    files = env_paths(envs)
    jobs = build_lights(files, rotate=rotate, exposure=exposure)  # reads every map first: fail early
    names = [n for n, _, _ in jobs]
    if len(set(names)) != len(names):
        raise MatcapError("two environment maps have the same file name; rename one")
    check_not_replacing_inputs(out, source, *files)  # --overwrite replaces `out`: never the maps it renders
    coverage = mask_coverage(maps.mask, width, height)
    src_text = str(source) if not hasattr(source, "normal") else str(maps.meta.get("source", "MaterialMaps"))
    timings: dict[str, float] = {}

    with output_dir(out, overwrite) as tmp:
        info: dict = {"source": src_text, "maps": _map_images(maps, tmp), "defaulted_maps": defaulted}
        (tmp / "renders").mkdir()
        renders, tiles = [], []
        t = time.perf_counter()
        for name, lights, pixels in progress_bar(jobs, desc="environment renders", unit="render", enabled=progress):
            img = render(maps, lights, pixels, spp=spp, size=(width, height), seed=seed)
            write_render(tmp / "renders" / name, img, coverage, tonemap_mode)
            tiles.append(_composite(tonemap(img / np.maximum(coverage[..., None], 1e-3), tonemap_mode), coverage))
            renders.append({"name": name, "png": f"renders/{name}.png", "exr": f"renders/{name}.exr"})
        timings["environment_renders_s"] = time.perf_counter() - t
        _save_rgb(tmp / "envs.png", contact_sheet(tiles, names))
        info.update(renders=renders, env_sheet="envs.png")

        t = time.perf_counter()
        orbit_info = {"frames": orbit, "light": orbit_light, "elevation_deg": elevation, "files": {}, "sheet": ""}
        if orbit > 0:
            frames = []
            lights = orbit_lights(orbit, orbit_light, elevation, gain=2.0 ** exposure)
            for light in progress_bar(lights, desc="orbit frames", unit="frame", enabled=progress):
                img = render(maps, [light], None, spp=orbit_spp, size=(width, height), seed=seed)
                frames.append(_composite(tonemap(img / np.maximum(coverage[..., None], 1e-3), tonemap_mode),
                                         coverage))
            orbit_info["files"] = write_animation(frames, tmp, "orbit", fps)
            picks = np.unique(np.linspace(0, orbit - 1, min(orbit, ORBIT_SHEET_MAX)).round().astype(int))
            sheet = contact_sheet([frames[i] for i in picks],
                                  [f"azimuth {360.0 * i / orbit:.0f}°" for i in picks],
                                  cols=min(len(picks), 6))
            _save_rgb(tmp / "orbit_sheet.png", sheet)
            orbit_info["sheet"] = "orbit_sheet.png"
        timings["orbit_s"] = time.perf_counter() - t
        info["orbit"] = orbit_info
        info["settings"] = {
            "size": f"{width}x{height}", "spp (environment renders)": spp, "spp (orbit)": orbit_spp,
            "environment maps": ", ".join(str(p) for p in files), "rotate (deg)": rotate, "exposure (EV)": exposure,
            "orbit light": f"{orbit_light}, elevation {elevation:g}°", "fps": fps, "tone mapping": tonemap_mode,
        }
        info["tonemap_text"] = TONEMAP_TEXT[tonemap_mode]
        if orbit == 0:
            page_info = dict(info, orbit={**orbit_info, "files": {"gif": ""}, "sheet": ""})
            page = _page(page_info).replace('<figure><img src="" alt="orbit animation (GIF)"><figcaption>orbit '
                                            '(GIF)</figcaption></figure>', "").replace(
                '<p><img class="sheet" src="" alt="orbit contact sheet"></p>', "")
        else:
            page = _page(info)
        write_text_atomic(tmp / "index.html", page)
        timings["total_s"] = time.perf_counter() - t0
        info["timings"] = {k: round(v, 3) for k, v in timings.items()}
        write_json_atomic(tmp / "gallery.json", info)
    info["out"] = str(Path(out))
    return info


# ``from matcap import gallery`` gives this module; make it callable (same as matcap.relight).
class _CallableModule(types.ModuleType):
    def __call__(self, *args, **kwargs):
        return gallery(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
