"""`matcap synth`: generate synthetic photometric-stereo training / test data (orchestration).

Sharded (scene i goes to shard i % n) and resumable: a scene folder is rendered into ``DATA/.tmp-scene_...``
and renamed into place when complete, so a finished scene (a ``scene_XXXXXX`` folder) is never rendered twice and
a crash never leaves a half-written one. ``manifest.json`` is rebuilt from the finished folders at the end of
every run (atomic write), so shards running as separate processes merge without coordination.
See docs/synth.md for the file layout.
"""
from __future__ import annotations

import json
import os
import shutil
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from matcap.errors import MatcapError, sigterm_as_interrupt
from scenes.lights import EnvironmentLight
from scenes.synth_spec import (
    GENERATOR_VERSIONS,
    NUM_IMAGES,
    SPLITS,
    AssetCatalog,
    SceneSpec,
    generate_scene,
)

MAX_ATTEMPTS = 6
ENVMAP_HEIGHT = 256  # environment maps are resampled to at most 512 x 256
ENVMAP_CLAMP = 200.0  # after normalising to unit mean radiance: caps sun peaks (fireflies at 16 spp)
MASK_CONVENTION = ("mask = every surface hit by the camera ray at the pixel centre: objects AND the background "
                   "surface when the scene has one (it has a valid normal); outside it the environment map is seen")


def parse_shard(text: str | None) -> tuple[int, int]:
    if text is None:
        return 0, 1
    try:
        i, n = (int(x) for x in str(text).split("/"))
    except ValueError:
        raise MatcapError(f"--shard must look like i/n (e.g. 0/4), got {text!r}") from None
    if n < 1 or not 0 <= i < n:
        raise MatcapError(f"--shard {text}: need 0 <= i < n")
    return i, n


# ----------------------------------------------------------------------------------------------- assets


def catalog_from_dir(assets: str | os.PathLike | None) -> AssetCatalog:
    if assets is None:
        return AssetCatalog()
    root = Path(assets)
    if not root.is_dir():
        raise MatcapError(f"--assets {assets}: no such folder")
    meshes = sorted(f"meshes/{p.name}" for p in (root / "meshes").glob("*")
                    if p.suffix.lower() in (".ply", ".obj", ".stl", ".off"))
    envs = sorted(f"envmaps/{p.name}" for p in (root / "envmaps").glob("*") if p.suffix.lower() in (".exr", ".hdr"))
    texs = sorted(f"textures/{p.name}" for p in (root / "textures").glob("*")
                  if p.is_dir() and any(p.glob("basecolor.*")))
    nmaps = [t for t in texs if any((root / t).glob("normal_gl.*"))]
    if not (meshes or envs or texs):
        raise MatcapError(f"--assets {assets}: no meshes/, envmaps/ or textures/ with usable files")
    return AssetCatalog(meshes, envs, texs, nmaps)


class AssetCache:
    """Loads assets named in specs (via matcap.imageio / trimesh) into numpy arrays, once per process."""

    def __init__(self, root: str | os.PathLike | None):
        self.root = None if root is None else Path(root)
        self._meshes: dict = {}
        self._env: dict = {}
        self._tex: dict = {}
        self.renderers: dict = {}  # (resolution, data version) -> renderers.synth.BasisRenderer (reused per scene)

    def mesh(self, name: str):
        if name not in self._meshes:
            import trimesh

            from scenes.procedural import Geometry, smooth_normals, spherical_uv
            from scenes.synth_build import normalise_mesh

            m = trimesh.load(self.root / name, force="mesh", process=False)
            v = normalise_mesh(np.asarray(m.vertices))
            f = np.asarray(m.faces, np.int32)
            uv = getattr(m.visual, "uv", None)
            uv = np.asarray(uv, np.float32) if uv is not None and len(uv) == len(v) else spherical_uv(v)
            self._meshes[name] = Geometry(v, f, smooth_normals(v, f), uv)
        return self._meshes[name]

    def envmap(self, source: str) -> np.ndarray:
        if source not in self._env:
            if source.startswith("procedural:"):
                from scenes.procedural import procedural_sky

                self._env[source] = procedural_sky(int(source.split(":", 1)[1]))
            else:
                import cv2

                from matcap.imageio import read_image

                arr = np.asarray(read_image(self.root / source).pixels, np.float32)
                arr = np.where(np.isfinite(arr) & (arr > 0), arr, 0.0).astype(np.float32)
                if arr.shape[0] > ENVMAP_HEIGHT:
                    arr = cv2.resize(arr, (2 * ENVMAP_HEIGHT, ENVMAP_HEIGHT), interpolation=cv2.INTER_AREA)
                h = arr.shape[0]
                wgt = np.sin((np.arange(h) + 0.5) / h * np.pi)[:, None, None]
                mean = float((arr * wgt).sum() / (wgt.sum() * arr.shape[1] * 3))
                self._env[source] = np.minimum(arr / max(mean, 1e-8), ENVMAP_CLAMP).astype(np.float32)
        return self._env[source]

    def texture_set(self, name: str) -> dict:
        if name not in self._tex:
            import cv2

            from matcap.imageio import read_image, to_linear_float
            from scenes.synth_build import TEXTURE_SIZE

            folder = self.root / name

            def load(stem, srgb):
                files = sorted(folder.glob(f"{stem}.*"))
                if not files:
                    return None
                arr, _ = to_linear_float(read_image(files[0]), decode_srgb_8bit=srgb)
                return cv2.resize(arr, (TEXTURE_SIZE, TEXTURE_SIZE), interpolation=cv2.INTER_AREA)

            out = {"basecolor": load("basecolor", True), "roughness": None, "normal": load("normal_gl", False)}
            packed = load("arm", False)
            packed = packed if packed is not None else load("orm", False)
            if packed is not None:
                out["roughness"] = packed[..., 1]
            rough = load("roughness", False)
            if rough is not None:
                out["roughness"] = rough[..., 0]
            if out["basecolor"] is None:
                raise MatcapError(f"{folder}: no basecolor image")
            self._tex[name] = out
        return self._tex[name]

    def for_spec(self, spec: SceneSpec):
        objs = spec.objects + ([spec.background] if spec.background else [])
        meshes = {o.mesh: self.mesh(o.mesh) for o in objs if o.shape == "mesh"}
        sets = {}
        for o in objs:
            m = o.material
            for t in (m.color_tex, m.roughness_tex, m.metallic_tex, m.normal_tex):
                if t is not None and t.pattern == "pbr":
                    sets[t.pbr_set] = self.texture_set(t.pbr_set)
        envs = {b.source: self.envmap(b.source) for b in spec.lights() if isinstance(b, EnvironmentLight)}
        return meshes, sets, envs


# ----------------------------------------------------------------------------------------------- one scene


@dataclass
class SceneResult:
    spec: SceneSpec
    render: object  # renderers.synth.SynthRender
    images: np.ndarray  # (10, H, W, 3) exposed, clipped
    lights: list[dict]
    problems: list[str] = field(default_factory=list)
    basis_vectors: np.ndarray | None = None  # (B, 3) vector irradiance of each basis light at the origin


def combine(basis: np.ndarray, weights) -> np.ndarray:
    """A non-negative combination of basis renders (light transport is linear in the light)."""
    w = np.asarray(weights, np.float32)
    if (w < 0).any():
        raise ValueError("basis weights must be non-negative")
    return np.tensordot(w, basis, axes=1).astype(np.float32)


def _mitsuba_variant() -> str:
    from renderers.variant import choose_variant

    return choose_variant()


def render_spec(spec: SceneSpec, cache: AssetCache, spp: int, persistent: bool = True) -> SceneResult:
    """Render one scene. ``persistent``: through the cache's :class:`renderers.synth.BasisRenderer`, whose Mitsuba
    scenes are reused for every scene of the process (``False``: fresh Mitsuba scenes for every scene)."""
    from renderers.synth import BasisRenderer, render_scene
    from scenes.synth_build import auto_exposure, build_render_objects, check_scene

    meshes, sets, envs = cache.for_spec(spec)
    objects = build_render_objects(spec, meshes, sets)
    renderer = None
    if persistent and not _mitsuba_variant().startswith("scalar"):
        key = (spec.resolution, spec.data_version)
        renderer = cache.renderers.get(key)
        if renderer is None:  # v2: up to 6 objects + an occluder + a background, normal maps
            v2 = spec.data_version >= 2
            renderer = cache.renderers[key] = BasisRenderer(spec.resolution, slots=8 if v2 else 5, normal_maps=v2)
    r = render_scene(objects, spec.lights(), envs, spec.resolution, spp=spp, seed=spec.render_seed,
                     renderer=renderer, persistent=persistent)
    raw = np.stack([combine(r.basis, im.weights) for im in spec.images])
    exposures = [auto_exposure(x, r.mask) for x in raw]
    images = np.stack([np.clip(x * e, 0, 1) for x, e in zip(raw, exposures)]).astype(np.float32)
    vectors = basis_light_vectors(spec, envs)
    lights = []
    for k, (im, e) in enumerate(zip(spec.images, exposures)):
        entry = {"image": f"{k:03d}.png", "config": im.config, "weights": im.weights, "exposure": float(e)}
        if spec.data_version >= 2:  # per-image light ground truth (a light-alignment loss reads it)
            entry["light_vector"] = [float(x) for x in float(e) * np.asarray(im.weights, np.float64) @ vectors]
        lights.append(entry)
    problems = check_scene(images, r.normal, r.mask, r.object_mask, raw, [im.config for im in spec.images],
                           r.stats, r.stats.get("mask_agreement", 1.0))
    return SceneResult(spec, r, images, lights, problems, vectors)


def basis_light_vectors(spec: SceneSpec, envs: dict[str, np.ndarray]) -> np.ndarray:
    """(B, 3) float32: :func:`scenes.lights.light_vector` of each basis light (env maps as rendered)."""
    from scenes.lights import light_vector

    return np.stack([light_vector(b, envs.get(b.source) if isinstance(b, EnvironmentLight) else None)
                     for b in spec.lights()]).astype(np.float32)


def write_scene(result: SceneResult, folder: Path) -> None:
    """Write one scene folder (into ``folder``, which should be a temporary name)."""
    from matcap import formats  # the scene layout: basecolor.png here is linear ground truth

    folder.mkdir(parents=True, exist_ok=True)
    r, spec = result.render, result.spec
    spec_d = spec.to_dict()
    spec_d["ground_truth_stats"] = r.stats
    formats.write_json(folder / "spec.json", spec_d)
    lights = {"basis": spec.basis, "basis_kind": spec.basis_kind, "images": result.lights}
    if spec.data_version >= 2:
        lights["basis_light_vector"] = result.basis_vectors.tolist()
        lights["light_vector"] = ("vector irradiance at the scene origin (camera space, toward the light; length = "
                                  "irradiance, mean over RGB), of the image as stored: exposure * sum_b w_b * "
                                  "basis_light_vector[b]")
    formats.write_json(folder / "lights.json", lights)
    extra = {}
    if spec.data_version >= 2:
        extra = {"data_version": np.array(spec.data_version), "basis_light_vec": result.basis_vectors,
                 "light_vec": np.array([x["light_vector"] for x in result.lights], np.float32)}
    for k, img in enumerate(result.images):
        formats.write_scene_image(folder, k, img)
    formats.write_scene_maps(folder, normal=r.normal, mask=r.mask, base_color=r.base_color,
                             roughness=r.roughness, metallic=r.metallic)
    np.savez(folder / "data.npz", basis=r.basis.astype(np.float16), basis_kind=np.array(spec.basis_kind),
             normal=r.normal.astype(np.float16), mask=r.mask, object_mask=r.object_mask,
             base_color=r.base_color.astype(np.float16), roughness=r.roughness.astype(np.float16),
             metallic=r.metallic.astype(np.float16), images=result.images.astype(np.float16),
             weights=np.array([im.weights for im in spec.images], np.float32),
             exposure=np.array([x["exposure"] for x in result.lights], np.float32), **extra)


# ----------------------------------------------------------------------------------------------- dataset


def _params(split, resolution, seed, scenes, spp, assets_used, data_version=1):
    return {"split": split, "resolution": int(resolution), "seed": int(seed), "num_scenes": int(scenes),
            "spp": int(spp), "generator_version": GENERATOR_VERSIONS[data_version], "assets": assets_used}


def _check_params(out: Path, params: dict) -> None:
    from matcap.imageio import write_text_atomic

    path = out / "synth_params.json"
    if path.exists():
        try:
            old = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise MatcapError(f"{path}: not valid JSON ({exc}); is {out} a `matcap synth` dataset?") from None
        if not isinstance(old, dict):
            raise MatcapError(f"{path}: expected a JSON object, got a {type(old).__name__}")
        diff = [k for k in params if k != "num_scenes" and old.get(k) != params[k]]
        if diff:
            raise MatcapError(f"{out} holds a dataset made with other settings ({', '.join(diff)}); use another --out")
    else:
        write_text_atomic(path, json.dumps(params, indent=1))


def rebuild_manifest(out: Path) -> dict:
    """Rebuild manifest.json from the finished scene folders (safe to call from any shard at any time)."""
    from matcap.imageio import write_text_atomic

    params = json.loads((out / "synth_params.json").read_text())
    names = sorted(p.parent.name for p in out.glob("scene_*/spec.json"))
    groups = {}
    for n in names:
        g = json.loads((out / n / "spec.json").read_text()).get("lighting_group")
        if g:
            groups[n] = g
    manifest = {
        "split": params["split"], "resolution": params["resolution"], "seed": params["seed"], "scenes": names,
        "generator_version": params["generator_version"], "num_scenes_requested": params["num_scenes"],
        "complete": len(names) >= params["num_scenes"], "images_per_scene": NUM_IMAGES, "spp": params["spp"],
        "assets": params["assets"],
        "images": "NNN.png: linear RGB, 16-bit, auto-exposed (exposure in lights.json); clipped to [0, 1]",
        "mask": MASK_CONVENTION,
        "normal": "normal.exr float32 (H,W,3), camera space x right / y up / z toward camera, z >= 0, 0 outside mask",
        "brdf": "basecolor.png, roughness.png, metallic.png: 16-bit LINEAR (not sRGB), 0 outside mask",
    }
    if groups:
        manifest["lighting_groups"] = groups
    write_text_atomic(out / "manifest.json", json.dumps(manifest, indent=1))
    return manifest


def _log_failure(out: Path, spec: SceneSpec, problems: list[str]) -> None:
    line = json.dumps({"scene": spec.name, "attempt": spec.attempt, "problems": problems, "time": time.time()})
    with open(out / "failures.log", "a") as f:
        f.write(line + "\n")


class ShardLock:
    """``OUT/.lock-shard-I-of-N`` holding ``PID HOST`` while a process renders that shard: a second process on the
    same shard would render the same scenes twice. A lock left by a process of this host that no longer exists is
    taken over; one from another host must be deleted by hand if it is stale."""

    def __init__(self, out: Path, i: int, n: int):
        self.path = out / f".lock-shard-{i}-of-{n}"
        self.shard = f"{i}/{n}"
        self.text = f"{os.getpid()} {socket.gethostname()}"

    def __enter__(self) -> "ShardLock":
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                pid, _, host = self.path.read_text().strip().partition(" ")
                if host == socket.gethostname() and pid.isdigit() and not _alive(int(pid)):
                    self.path.unlink(missing_ok=True)  # stale: its process is gone
                    continue
                raise MatcapError(f"shard {self.shard} of {self.path.parent} is being "
                                  f"rendered by process {pid} on {host or '?'}; wait for it, or delete "
                                  f"{self.path} if that process is gone") from None
            with os.fdopen(fd, "w") as f:
                f.write(self.text + "\n")
            return self
        raise MatcapError(f"cannot take {self.path}")

    def __exit__(self, *exc) -> None:
        try:
            if self.path.read_text().strip() == self.text:
                self.path.unlink()
        except OSError:
            pass


def _remove_stale_tmp(out: Path) -> list[str]:
    """Delete the ``.tmp-scene_*-PID`` folders of processes that no longer run (a run killed with ``kill -9``
    while writing a scene); those of running processes (other shards) are left alone. Returns the names."""
    removed = []
    for entry in out.glob(".tmp-scene_*-*"):
        pid = entry.name.rsplit("-", 1)[1]
        if pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)):
            shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry.name)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def run_synth(out, scenes: int, resolution: int = 256, seed: int = 0, shard: str | None = None,
              assets=None, split: str = "train", spp: int = 16, progress: bool = True, data_version: int = 1) -> dict:
    """Generate (this shard's part of) a dataset. Returns {"rendered", "skipped", "failed", "seconds"}.

    ``data_version`` 1 draws the scenes it always drew for a seed; 2 is data v2 (scenes.synth_spec.generate_scene_v2).
    """
    if data_version not in GENERATOR_VERSIONS:
        raise MatcapError(f"--data-version must be one of {', '.join(map(str, sorted(GENERATOR_VERSIONS)))}, "
                          f"got {data_version}")
    if split not in SPLITS:
        raise MatcapError(f"--split must be train or test, got {split!r}")
    if scenes < 1:
        raise MatcapError("--scenes must be at least 1")
    if not 8 <= resolution <= 4096:
        raise MatcapError(f"--resolution {resolution}: must be between 8 and 4096")
    if spp < 1:
        raise MatcapError("--spp must be at least 1")
    i, n = parse_shard(shard)
    catalog = catalog_from_dir(assets)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise MatcapError(f"--out {out}: exists and is not a folder")
    if out.is_dir() and not (out / "synth_params.json").exists():  # resume a dataset, but never mix into other data
        foreign = sorted(p.name for p in out.iterdir() if not p.name.startswith(".") and not p.name.startswith("scene_")
                         and p.name not in ("synth_params.json", "manifest.json", "failures.log"))
        if foreign:
            raise MatcapError(f"--out {out} holds files that are not part of a `matcap synth` dataset "
                              f"({', '.join(foreign[:3])}{', ...' if len(foreign) > 3 else ''}); use another folder")
    out.mkdir(parents=True, exist_ok=True)
    assets_used = None if assets is None else {"meshes": len(catalog.meshes), "envmaps": len(catalog.envmaps),
                                               "textures": len(catalog.textures)}
    _check_params(out, _params(split, resolution, seed, scenes, spp, assets_used, data_version))
    with sigterm_as_interrupt(), ShardLock(out, i, n):  # one process per shard
        _remove_stale_tmp(out)
        cache = AssetCache(assets)
        todo = [k for k in range(i, scenes, n) if not (out / f"scene_{k:06d}" / "spec.json").exists()]
        skipped = len(range(i, scenes, n)) - len(todo)
        stats = {"rendered": 0, "skipped": skipped, "failed": 0, "redrawn": 0}
        t0 = time.time()
        bar = None
        if progress:
            from networks.progress import progress as progress_bar

            bar = progress_bar(total=len(todo), desc=f"synth {split} shard {i}/{n}", unit="scene")
        try:
            for k in todo:
                final = out / f"scene_{k:06d}"
                done = False
                for attempt in range(MAX_ATTEMPTS):
                    spec = generate_scene(seed, split, k, resolution, catalog, attempt, data_version)
                    result = render_spec(spec, cache, spp)
                    if result.problems:
                        _log_failure(out, spec, result.problems)
                        stats["redrawn"] += 1
                        continue
                    tmp = out / f".tmp-{final.name}-{os.getpid()}"
                    if tmp.exists():
                        shutil.rmtree(tmp)
                    try:
                        write_scene(result, tmp)
                    except BaseException:  # Ctrl-C or a full disk while writing: no half-written folder left
                        shutil.rmtree(tmp, ignore_errors=True)
                        raise
                    try:
                        os.rename(tmp, final)
                    except OSError:  # another process finished it first
                        shutil.rmtree(tmp, ignore_errors=True)
                    done = True
                    break
                stats["rendered" if done else "failed"] += 1
                if bar is not None:
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
            rebuild_manifest(out)
        stats["seconds"] = time.time() - t0
    return stats


def contact_sheet(data_dir, out_png, scenes: list[str] | None = None, images: int = 3) -> np.ndarray:
    """A grid image of scenes (rows): a few of the 10 images (sRGB for display), normal, mask, base colour,
    roughness, metallic. Written as an 8-bit sRGB PNG; returns the array."""
    from matcap.imageio import linear_to_srgb, read_exr, read_image, write_png

    data_dir = Path(data_dir)
    scenes = scenes or json.loads((data_dir / "manifest.json").read_text())["scenes"][:4]
    rows = []
    for name in scenes:
        f = data_dir / name
        tiles = [linear_to_srgb(read_image(f / f"{k:03d}.png").pixels / 65535.0) for k in range(images)]
        n = read_exr(f / "normal.exr")
        m = read_image(f / "mask.png").pixels / 255.0
        tiles.append(np.where(m > 0, (n + 1) / 2, 0))
        tiles.append(m)
        tiles.append(linear_to_srgb(read_image(f / "basecolor.png").pixels / 65535.0))
        tiles.append(read_image(f / "roughness.png").pixels / 65535.0)
        tiles.append(read_image(f / "metallic.png").pixels / 65535.0)
        pad = [np.pad(t, ((2, 2), (2, 2), (0, 0)), constant_values=1.0) for t in tiles]
        rows.append(np.concatenate(pad, axis=1))
    grid = np.concatenate(rows, axis=0).astype(np.float32)
    write_png(out_png, grid, bits=8)
    return grid
