"""The training split's assets, reduced to what the scene generator reads, as one small archive for a lent GPU call.

    python docs/recipes/make_gpu_assets.py --assets ../shared/data --out carry_gpu/assets    # -> train_assets.tar.xz
    python docs/recipes/make_gpu_assets.py --assets ../shared/data --out carry_gpu/assets \
        --carry carry --val-data data/val128                                              # the whole carried folder

A lent machine takes at most 64 MiB a call, and the full asset folder (61 MB) does not fit beside Mitsuba and the
weights. The generator (`matcap.synth.AssetCache`) resamples every environment map to at most 512 x 256 and every
texture to 256 x 256 anyway, so the archive holds, for the assets the train split may draw (the held-out ones of
`scenes.synth_spec` are left out, with the unusable meshes):

* meshes as they are (PLY);
* environment maps as the generator loads them (at most 512 x 256, unit mean radiance over the sphere, sun peaks
  capped), resampled (area average) to ``--env-height`` rows and twice as many columns, as half-float EXR;
* each texture set's maps as the generator loads them (linear, 256 x 256: base colour decoded from sRGB,
  roughness taken from a packed ARM / ORM map where there is one), written as PNG, which the generator reads as
  linear (base colour with 16 bits, normal map and roughness with the 8 bits they had): the lent machine needs no
  colour-science;
* the licence and source files of the three folders.

With ``--carry DIR --val-data DATA`` the rest of a call's carried folder is made beside the archive (in the
parent of ``--out``): ``mitsuba/`` and the OpenEXR and trimesh wheels of ``wheels/`` copied from ``DIR``
(docs/recipes/build_mitsuba_carry.py), and ``val/`` holding ``DATA`` as one `networks.datapack` pack (WebP
quality 95). On the lent machine, ``gpu_train.py --carry carry_gpu --assets carry_gpu/assets/train_assets.tar.xz
--val-pack carry_gpu/val/pack_000.npz`` unpacks both.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]


def build(assets: Path, out_dir: Path, env_height: int) -> Path:
    """The archive ``out_dir/train_assets.tar.xz``: the train split's assets as `matcap.synth.AssetCache` loads
    them (what the generator renders with), written back out small."""
    sys.path.insert(0, str(REPO))
    import cv2

    from matcap.imageio import write_exr, write_png
    from matcap.synth import AssetCache, catalog_from_dir

    cat = catalog_from_dir(assets).for_split("train")
    cache = AssetCache(assets)
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for kind in ("meshes", "envmaps", "textures"):
            (root / kind).mkdir()
            for f in (assets / kind).iterdir():
                if f.is_file() and (f.name.startswith("LICENSE") or f.name == "SOURCES.md"):
                    shutil.copy(f, root / kind / f.name)
        for name in cat.meshes:
            shutil.copy(assets / name, root / name)
        for name in cat.envmaps:
            env = cache.envmap(name)  # at most 512 x 256, unit mean radiance, sun peaks capped
            if env.shape[0] > env_height:
                env = cv2.resize(env, (2 * env_height, env_height), interpolation=cv2.INTER_AREA)
            write_exr(root / "envmaps" / (Path(name).stem + ".exr"), env, half=True)
        for name in cat.textures:
            dst = root / name
            dst.mkdir()
            tex = cache.texture_set(name)  # linear, TEXTURE_SIZE square
            # base colour: 16-bit linear (8 bits would band its darks); the others were 8-bit linear codes
            for stem, key, bits in (("basecolor", "basecolor", 16), ("normal_gl", "normal", 8),
                                    ("roughness", "roughness", 8)):
                if tex[key] is not None:
                    write_png(dst / f"{stem}.png", np.clip(tex[key], 0.0, 1.0), bits=bits)
            for f in (assets / name).iterdir():
                if f.name.startswith("LICENSE") or f.suffix == ".md":
                    shutil.copy(f, dst / f.name)
        archive = out_dir / "train_assets.tar.xz"
        tmp_archive = archive.with_suffix(".tmp")
        with tarfile.open(tmp_archive, "w:xz", preset=9) as tar:
            for kind in ("meshes", "envmaps", "textures"):
                tar.add(root / kind, arcname=kind)
        tmp_archive.replace(archive)
    print(f"{archive}: {len(cat.meshes)} meshes, {len(cat.envmaps)} environment maps ({2 * env_height} x "
          f"{env_height}), {len(cat.textures)} texture sets; {archive.stat().st_size / 1e6:.1f} MB")
    return archive


def carry_rest(carry: Path, val_data: Path, out_root: Path) -> None:
    """Beside the archive: Mitsuba and the wheels the lent machine lacks (not colour-science: the archive needs
    none), and the validation set as one pack."""
    sys.path.insert(0, str(REPO))
    from networks.datapack import pack

    (out_root / "mitsuba").mkdir(parents=True, exist_ok=True)
    (out_root / "wheels").mkdir(parents=True, exist_ok=True)
    for f in sorted((carry / "mitsuba").glob("*")):
        shutil.copy(f, out_root / "mitsuba" / f.name)
    wheels = [w for w in sorted((carry / "wheels").glob("*.whl")) if not w.name.lower().startswith("colour")]
    for w in wheels:
        shutil.copy(w, out_root / "wheels" / w.name)
    shutil.rmtree(out_root / "val", ignore_errors=True)
    packs = pack(val_data, out_root / "val", max_mb=60.0, quality=95)
    if len(packs) != 1:
        raise SystemExit(f"{val_data}: {len(packs)} packs; one validation pack is wanted")
    size = sum(f.stat().st_size for f in out_root.rglob("*") if f.is_file())
    print(f"{out_root}: mitsuba, {len(wheels)} wheels, {packs[0].name}; {size / 1e6:.1f} MB in all")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--assets", default=str(REPO.parent / "shared" / "data"), help="the full assets folder")
    ap.add_argument("--out", default=str(REPO / "carry_gpu" / "assets"), help="folder for train_assets.tar.xz")
    ap.add_argument("--env-height", type=int, default=128, help="rows of the resampled environment maps")
    ap.add_argument("--carry", default=None, help="a carried folder with mitsuba/ and wheels/ to copy from")
    ap.add_argument("--val-data", default=None, help="a `matcap synth` validation set to carry as one pack")
    a = ap.parse_args(argv)
    if (a.carry is None) != (a.val_data is None):
        ap.error("--carry and --val-data go together")
    build(Path(a.assets), Path(a.out), a.env_height)
    if a.carry:
        carry_rest(Path(a.carry), Path(a.val_data), Path(a.out).parent)
    return 0


if __name__ == "__main__":
    sys.exit(main())
