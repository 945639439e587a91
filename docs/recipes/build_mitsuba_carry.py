"""Build the Mitsuba + Dr.Jit that a lent GPU machine carries: only the variants the training recipe renders with.

    python docs/recipes/build_mitsuba_carry.py                      # cp312 (the lent machine's Python) -> carry/mitsuba/
    python docs/recipes/build_mitsuba_carry.py --python 3.11 --verify --out /tmp/mi311   # a build for this Python, tested

The lent machine has PyTorch but no Mitsuba, reaches no registry, and takes at most 64 MiB per call (the working tree
included). The wheels pip downloads (mitsuba 3.9.1, drjit 1.5.0) hold every variant (mono, spectral, polarized, ...),
type stubs, C++ headers and ~100 plugins; this keeps

* the variants ``cuda_ad_rgb`` (first choice on the GPU), ``llvm_ad_rgb`` and ``scalar_rgb`` (the fall-backs);
* the plugins the scene generator loads (:data:`PLUGINS`: those seen loaded while rendering data v1 and v2 scenes of
  both splits, plus the scene-file defaults around them), and the shared libraries every variant links;

drops the rest and the debug symbols (``strip --strip-unneeded``), and packs what is left into one
``mitsuba-<ver>-drjit-<ver>-<tag>.tar.xz`` in ``--out`` (an ignored folder: ``/carry/`` is in .gitignore). Beside
it, ``carry/wheels`` gets the wheels of the product's dependencies that the machine's image lacks (OpenEXR,
trimesh, colour-science: 11.6 MB), which docs/recipes/gpu_train.py installs there. On the machine,
``tar -xJf carry/mitsuba/*.tar.xz -C /tmp/matcap_site`` and ``PYTHONPATH=/tmp/matcap_site`` make
``import mitsuba`` work (docs/recipes/gpu_train.py does this itself). ``--verify`` unpacks the archive into a temporary
folder and, in a child process that sees only that copy, imports it, renders a test scene in ``scalar_rgb`` and
``llvm_ad_rgb`` (the latter only where libLLVM >= 17 is installed) and renders two data v2 scenes with ``matcap
synth``'s generator; it needs a build for the running Python (``--python`` equal to this interpreter's version).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
MITSUBA, DRJIT = "3.9.1", "1.5.0"
VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")
#: Plugins kept. Seen loaded (/proc/self/maps) while `matcap synth` rendered data v1 and v2 scenes of both splits:
#: aov area bitmap box d65 diffuse directional envmap hdrfilm independent merge normalmap orthographic path point
#: principled rectangle regular spot srgb stratified twosided uniform; the rest are types the repository's code
#: names (constant, direct, sphere) or Mitsuba's defaults for a scene dict (gaussian filter, perspective camera,
#: mesh files, the plain BSDFs): cheap insurance against a scene kind the sample above did not draw.
PLUGINS = ("aov", "area", "bitmap", "box", "d65", "diffuse", "directional", "envmap", "hdrfilm", "independent",
           "merge", "normalmap", "orthographic", "path", "point", "principled", "rectangle", "regular", "spot", "srgb",
           "stratified", "twosided", "uniform",
           "constant", "direct", "sphere", "disk", "gaussian", "perspective", "obj", "ply", "serialized", "conductor",
           "roughconductor", "dielectric", "plastic", "roughplastic", "blendbsdf", "mask", "irregular", "moment",
           "multijitter", "ldsampler")
#: Folders and files nobody imports at run time.
DROP = ("mitsuba/include", "mitsuba/cmake", "mitsuba/pkgconfig", "mitsuba/mitsuba_stubs", "drjit/include",
        "drjit/cmake", "share", "mitsuba/data/sunsky", "mitsuba/data/srgb.coeff")


def log(msg: str) -> None:
    print(f"build_mitsuba_carry: {msg}", flush=True)


def download(dest: Path, python: str) -> list[Path]:
    """The two wheels for CPython ``python`` on manylinux x86-64 (cached in ``dest``)."""
    tag = "cp" + python.replace(".", "")
    have = sorted(dest.glob(f"*-{tag}-*.whl"))
    names = {p.name.split("-")[0] for p in have}
    if {"mitsuba", "drjit"} <= names:
        return have
    pip_download(dest, python, f"mitsuba=={MITSUBA}", f"drjit=={DRJIT}")
    return sorted(dest.glob(f"*-{tag}-*.whl"))


def pip_download(dest: Path, python: str, *requirements: str) -> None:
    """``pip download --no-deps`` of binary wheels of ``requirements`` for CPython ``python`` on manylinux x86-64."""
    dest.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--python-version", python,
           "--implementation", "cp", "--platform", "manylinux_2_28_x86_64", "--platform", "manylinux_2_27_x86_64",
           "--platform", "manylinux_2_17_x86_64", "--platform", "manylinux2014_x86_64", "-d", str(dest),
           *requirements]
    log("downloading " + " ".join(cmd[3:]))
    subprocess.run(cmd, check=True)


#: The product's dependencies that the lent machine's image lacks (it has numpy, scipy, opencv, pillow, safetensors,
#: tqdm and torch): carried as wheels in ``carry/wheels`` and installed there by docs/recipes/gpu_train.py.
DEPENDENCIES = ("OpenEXR", "trimesh", "colour-science")


def download_dependencies(dest: Path, python: str) -> list[Path]:
    """The wheels of :data:`DEPENDENCIES` for CPython ``python`` on manylinux x86-64, into ``dest``."""
    for old in dest.glob("*.whl"):
        old.unlink()
    pip_download(dest, python, *DEPENDENCIES)
    return sorted(dest.glob("*.whl"))


def strip_tree(root: Path, variants=VARIANTS, plugins=PLUGINS, strip_symbols: bool = True) -> dict:
    """Remove what the recipe does not use from an unpacked mitsuba + drjit; returns counts for the report."""
    removed = {"variant_modules": [], "plugins": 0, "stubs": 0}
    for f in (root / "mitsuba").iterdir():
        m = re.match(r"((?:cuda|llvm|scalar)_[a-z_]+)\.cpython", f.name)
        if m and m.group(1) not in variants:
            removed["variant_modules"].append(m.group(1))
            f.unlink()
    missing = [v for v in variants if not list((root / "mitsuba").glob(f"{v}.cpython*"))]
    if missing:
        raise SystemExit(f"build_mitsuba_carry: the wheel has no module for {missing}")
    keep = {f"{p}.so" for p in plugins}
    for f in (root / "mitsuba" / "plugins").iterdir():
        if f.name not in keep:
            f.unlink()
            removed["plugins"] += 1
    for f in list(root.rglob("*.pyi")):
        f.unlink()
        removed["stubs"] += 1
    for rel in DROP:
        p = root / rel
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    if not (root / "drjit" / "cuda").is_dir() and "cuda_ad_rgb" in variants:
        raise SystemExit("build_mitsuba_carry: drjit.cuda is missing from the wheel")
    for d in root.glob("*.dist-info"):  # keep METADATA (pip show) and the licence; RECORD would list removed files
        for f in d.iterdir():
            if f.name not in ("METADATA", "WHEEL") and not f.name.lower().startswith("licen"):
                if f.is_dir():
                    shutil.rmtree(f)
                else:
                    f.unlink()
    if strip_symbols and shutil.which("strip"):
        for so in root.rglob("*.so*"):
            subprocess.run(["strip", "--strip-unneeded", str(so)], check=True)
    removed["variant_modules"].sort()
    return removed


def tree_bytes(root: Path) -> int:
    return sum(f.stat().st_size for f in root.rglob("*") if f.is_file())


def build(wheels: list[Path], out: Path, tag: str, strip_symbols: bool = True) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    archive = out / f"mitsuba-{MITSUBA}-drjit-{DRJIT}-{tag}.tar.xz"
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        wheel_bytes = 0
        for w in wheels:
            wheel_bytes += w.stat().st_size
            with zipfile.ZipFile(w) as z:
                z.extractall(root)
        for f in root.rglob("*.so*"):  # zip drops the execute bits
            f.chmod(0o755)
        full = tree_bytes(root)
        removed = strip_tree(root, strip_symbols=strip_symbols)
        kept = tree_bytes(root)
        log(f"wheels {wheel_bytes / 1e6:.1f} MB ({full / 1e6:.1f} MB unpacked); kept {kept / 1e6:.1f} MB unpacked: "
            f"variants {', '.join(VARIANTS)}; dropped {len(removed['variant_modules'])} variant modules, "
            f"{removed['plugins']} plugins, {removed['stubs']} stub files, headers and debug symbols")
        t0 = time.time()
        tmp_archive = archive.with_suffix(".part")
        with tarfile.open(tmp_archive, "w:xz", preset=9) as tar:
            for top in sorted(root.iterdir()):
                tar.add(top, arcname=top.name)
        os.replace(tmp_archive, archive)
        info = {"archive": archive.name, "mitsuba": MITSUBA, "drjit": DRJIT, "python": tag, "variants": list(VARIANTS),
                "plugins": sorted(p.name[:-3] for p in (root / "mitsuba" / "plugins").iterdir()),
                "wheel_mb": round(wheel_bytes / 1e6, 2), "unpacked_mb": round(kept / 1e6, 2),
                "archive_mb": round(archive.stat().st_size / 1e6, 2),
                "archive_mib": round(archive.stat().st_size / 2**20, 2)}
        (out / f"{archive.name}.json").write_text(json.dumps(info, indent=1) + "\n")
        log(f"packed in {time.time() - t0:.0f} s: {archive} {info['archive_mb']} MB ({info['archive_mib']} MiB)")
    return archive


VERIFY = r"""
import json, os, sys, tempfile
import mitsuba as mi
assert os.path.realpath(mi.__file__).startswith(os.path.realpath(sys.argv[1])), mi.__file__
print("variants", sorted(mi.variants()))
scene = {"type": "scene", "integrator": {"type": "path"},
         "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 8, "height": 8}},
         "shape": {"type": "rectangle", "bsdf": {"type": "principled"}}, "light": {"type": "constant"}}
import subprocess
for v in sys.argv[2].split(","):
    mi.set_variant(v)
    img = mi.render(mi.load_dict(scene), spp=4)
    import numpy as np
    print(v, "mean", round(float(np.array(img).mean()), 4))
sys.path.insert(0, sys.argv[3])
os.environ["MATCAP_MITSUBA_VARIANT"] = sys.argv[2].split(",")[-1]
from matcap.synth import run_synth
out = tempfile.mkdtemp()
stats = run_synth(out, 2, resolution=32, seed=1000, spp=2, progress=False, data_version=2,
                  assets=sys.argv[4] if len(sys.argv) > 4 else None)
print("synth", json.dumps({k: stats[k] for k in ("rendered", "failed")}))
assert stats["rendered"] == 2 and stats["failed"] == 0
"""


def verify(archive: Path, assets: str | None) -> None:
    """Unpack into a temporary folder and render there, in a child process that sees only that copy."""
    from renderers.variant import llvm_works  # probes the *installed* mitsuba; LLVM is a system library either way

    variants = ["scalar_rgb"] + (["llvm_ad_rgb"] if llvm_works() else [])
    with tempfile.TemporaryDirectory() as tmp:
        with tarfile.open(archive) as tar:
            if hasattr(tarfile, "data_filter"):  # Python >= 3.11.4 / 3.12
                tar.extractall(tmp, filter="tar")
            else:
                tar.extractall(tmp)
        env = {**os.environ, "PYTHONPATH": tmp}
        args = [sys.executable, "-c", VERIFY, tmp, ",".join(variants), str(REPO)] + ([assets] if assets else [])
        t0 = time.time()
        r = subprocess.run(args, env=env, capture_output=True, text=True)
        print(r.stdout, end="")
        if r.returncode:
            print(r.stderr[-3000:], file=sys.stderr)
            raise SystemExit("build_mitsuba_carry: the stripped build failed its check")
        log(f"verified ({', '.join(variants)}; 2 data v2 scenes) in {time.time() - t0:.0f} s")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(REPO / "carry" / "mitsuba"), help="folder for the archive (default carry/mitsuba)")
    ap.add_argument("--python", default="3.12", help="CPython version of the machine (default 3.12, the lent one's)")
    ap.add_argument("--wheels", default="/tmp/matcap_mitsuba_wheels", help="wheel cache (default %(default)s)")
    ap.add_argument("--deps-out", default=None,
                    help="folder for the dependency wheels (default: wheels/ beside --out, i.e. carry/wheels)")
    ap.add_argument("--no-strip-symbols", action="store_true", help="keep the debug symbols")
    ap.add_argument("--verify", action="store_true", help="render with the packed copy here (needs --python = this one)")
    ap.add_argument("--assets", default=None, help="assets folder for --verify's synth scenes (e.g. ../shared/data)")
    args = ap.parse_args(argv)
    tag = "cp" + args.python.replace(".", "")
    out = Path(args.out)
    wheels = download(Path(args.wheels), args.python)
    archive = build(wheels, out, tag, strip_symbols=not args.no_strip_symbols)
    for old in out.glob("mitsuba-*.tar.xz"):
        if old != archive and tag in old.name:
            old.unlink()
    if args.verify:
        here = f"{sys.version_info.major}.{sys.version_info.minor}"
        if here != args.python:
            raise SystemExit(f"build_mitsuba_carry: --verify needs a build for this Python ({here}), not {args.python}")
        sys.path.insert(0, str(REPO))
        verify(archive, args.assets)
    print(f"{archive} {archive.stat().st_size / 1e6:.1f} MB")
    deps_out = Path(args.deps_out) if args.deps_out else out.parent / "wheels"
    deps = download_dependencies(deps_out, args.python)
    print(f"{deps_out}: {', '.join(d.name for d in deps)} {sum(d.stat().st_size for d in deps) / 1e6:.1f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
