"""Build (or resume) the packed training pool of data v2: seeded blocks of `matcap synth --data-version 2` scenes,
each packed into one `networks.datapack` file, plus a fixed validation pack.

    python docs/recipes/make_pool.py --out pool --assets ../shared/data                  # 6,000 scenes + val
    python docs/recipes/make_pool.py --out pool --assets ../shared/data --blocks 0:2     # only blocks 0 and 1
    python docs/recipes/make_pool.py --out pool --assets ../shared/data --jobs 14 --threads 1   # a 16-core box

Block b holds ``--block`` scenes drawn with seed ``--seed + b`` (train split, data v2) and becomes
``OUT/packs/train_BBBB.npz`` (lossy WebP basis renders at ``--quality``, ~0.08 MB a scene at 128^2); the
validation pack ``OUT/packs/val.npz`` holds ``--val`` scenes of seed 11 (data v2, never a train seed), the same on
every machine. Resumable at two levels: a block whose pack exists is skipped, and a block that was killed
mid-way resumes inside `matcap synth` (finished scenes are never rendered again). A block's rendered scene
folders are deleted once its pack is written (``--keep-renders`` keeps them). ``OUT/pool.json`` records the
settings (a different setting into the same folder is refused) and ``OUT/blocks.jsonl`` one line per finished
block (scenes, MB, seconds) for the arithmetic in docs/synth.md.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

VAL_SEED = 11
DATA_VERSION = 2


def _settings(args) -> dict:
    return {"scenes": args.scenes, "block": args.block, "seed": args.seed, "resolution": args.resolution,
            "spp": args.spp, "assets": None if args.assets is None else os.path.abspath(args.assets),
            "quality": args.quality, "val": args.val, "data_version": DATA_VERSION}


def _check_settings(out: Path, settings: dict) -> None:
    path = out / "pool.json"
    if path.exists():
        old = json.loads(path.read_text())
        diff = [k for k in settings if k not in ("scenes", "assets") and old.get(k) != settings[k]]
        if diff:
            raise SystemExit(f"make_pool: {out} was made with other settings ({', '.join(diff)}); use another --out")
    out.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(settings, indent=1))
    os.replace(tmp, path)


def _render_and_pack(name: str, seed: int, scenes: int, s: dict, out: str, threads: int, keep: bool) -> dict:
    """One block (or the validation set): render into OUT/render/NAME, pack into OUT/packs/NAME.npz."""
    if threads:
        os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    from matcap.synth import run_synth
    from networks.datapack import pack

    if threads:
        from renderers.variant import choose_variant

        choose_variant(quiet=True)
        import drjit

        drjit.set_thread_count(threads)
    out = Path(out)
    final = out / "packs" / f"{name}.npz"
    if final.exists():
        return {"name": name, "skipped": True}
    render = out / "render" / name
    t0 = time.time()
    stats = run_synth(render, scenes, resolution=s["resolution"], seed=seed, assets=s["assets"], spp=s["spp"],
                      progress=False, data_version=DATA_VERSION)
    seconds = time.time() - t0
    with tempfile.TemporaryDirectory(dir=out / "packs") as tmp:
        written = pack(render, tmp, max_mb=1e9, quality=s["quality"], prefix="" if name == "val" else f"{name}_")
        os.replace(written[0], final)
    n = len(json.loads((render / "manifest.json").read_text())["scenes"])
    render_mb = sum(f.stat().st_size for f in render.glob("scene_*/*")) / 1e6
    if not keep:
        shutil.rmtree(render)
    rec = {"name": name, "seed": seed, "scenes": n, "failed": stats["failed"], "render_s": round(seconds, 1),
           "s_per_scene": round(seconds / max(stats["rendered"], 1), 2), "pack_mb": round(final.stat().st_size / 1e6, 2),
           "mb_per_scene": round(final.stat().st_size / 1e6 / max(n, 1), 4), "render_mb_per_scene":
           round(render_mb / max(n, 1), 2), "threads": threads, "time": time.time()}
    with open(out / "blocks.jsonl", "a") as f:
        f.write(json.dumps(rec) + "\n")
    return rec


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="pool folder (created; re-run to resume)")
    ap.add_argument("--scenes", type=int, default=6000, help="train scenes in the whole pool (default 6000)")
    ap.add_argument("--block", type=int, default=220, help="scenes per block and pack (default 220: ~19 MB at 128^2)")
    ap.add_argument("--seed", type=int, default=1000, help="seed of block 0; block b uses seed + b (default 1000)")
    ap.add_argument("--resolution", type=int, default=128, help="image size (default 128, what training uses)")
    ap.add_argument("--spp", type=int, default=16, help="samples per pixel (default 16)")
    ap.add_argument("--assets", default=None, help="assets folder (meshes/, envmaps/, textures/), e.g. ../shared/data")
    ap.add_argument("--quality", type=int, default=95, help="WebP quality of packed basis renders (0 = lossless)")
    ap.add_argument("--val", type=int, default=48, help="validation scenes (seed 11; 0 = none; default 48)")
    ap.add_argument("--blocks", default=None, help="only blocks a:b of the pool (default: all)")
    ap.add_argument("--jobs", type=int, default=1, help="blocks rendered at once, one process each (default 1)")
    ap.add_argument("--threads", type=int, default=0, help="Dr.Jit threads per process (0 = all cores)")
    ap.add_argument("--keep-renders", action="store_true", help="keep the rendered scene folders after packing")
    args = ap.parse_args(argv)
    if args.scenes < 1 or args.block < 1 or args.jobs < 1:
        ap.error("--scenes, --block and --jobs must be at least 1")
    out = Path(args.out)
    s = _settings(args)
    _check_settings(out, s)
    (out / "packs").mkdir(exist_ok=True)
    nblocks = -(-args.scenes // args.block)
    lo, hi = 0, nblocks
    if args.blocks:
        a, _, b = args.blocks.partition(":")
        lo, hi = int(a or 0), min(int(b or nblocks), nblocks)
    jobs = []
    if args.val:
        jobs.append(("val", VAL_SEED, args.val))
    for b in range(lo, hi):
        jobs.append((f"train_{b:04d}", args.seed + b, min(args.block, args.scenes - b * args.block)))
    todo = [j for j in jobs if not (out / "packs" / f"{j[0]}.npz").exists()]
    print(f"make_pool: {len(jobs) - len(todo)} of {len(jobs)} packs already done; {len(todo)} to render "
          f"with {args.jobs} job(s)", flush=True)
    t0 = time.time()
    if args.jobs == 1:
        for name, seed, n in todo:
            print(json.dumps(_render_and_pack(name, seed, n, s, str(out), args.threads, args.keep_renders)), flush=True)
    else:
        with ProcessPoolExecutor(args.jobs, mp_context=get_context("spawn")) as ex:
            futures = [ex.submit(_render_and_pack, name, seed, n, s, str(out), args.threads, args.keep_renders)
                       for name, seed, n in todo]
            for fut in as_completed(futures):
                print(json.dumps(fut.result()), flush=True)
    packs = sorted((out / "packs").glob("*.npz"))
    print(f"make_pool: {len(packs)} packs, {sum(p.stat().st_size for p in packs) / 1e6:.1f} MB in {out / 'packs'} "
          f"({time.time() - t0:.0f} s this run)", flush=True)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:  # Ctrl-C / SIGTERM (matcap synth turns it into this): nothing half-written is kept
        print("make_pool: interrupted; run the same command again to resume", file=sys.stderr)
        sys.exit(130)
