"""Inference speed, old code vs new code side by side: per-stage profile, totals, bf16, capture.

Each measurement runs in its own subprocess; the "old" code is ``git archive REV`` (default f87ac8c, the
straightforward implementation) unpacked into a temporary folder and put first on PYTHONPATH, the "new" code is this
working tree. Old and new runs alternate, so both see the same machine load; ratios are old / new.

Times are wall seconds and process CPU seconds (all threads; less sensitive than wall time to other work on a
shared machine). Per-stage times come from wrappers around the network's modules:

  encoder: backbone (ConvNeXt) | light-axis attention ("comm" blocks) | UPerNet fusion |
           rest (resize, polyphase interleave, Gaussian feature smoothing)
  decoder: pixel sampling (gather raw RGB, grid_sample features, concatenation) | glc_upsample |
           glc_aggregation (+ PMA) | regressor attention over the sample set | prediction heads
  other:   predict() outside encode/decode (pixel shuffle, scatter to the map)

Input: a Lambertian sphere (disc of radius 0.45 S, 166,740 pixels at 512^2) under K random directional lights
(``bench_networks.make_object``), deterministic real-sized weights (salt "bench"). Normals of the new code are
compared with the old code's (fp32) and bf16 with fp32 (same code).

Usage:
  python benchmarks/bench_speed.py                               # stages small + paper 512^2 K=16 fp32 and bf16
  python benchmarks/bench_speed.py --presets small --dtypes fp32 # one preset / dtype
  python benchmarks/bench_speed.py --capture                     # also the bundled example end to end
  python benchmarks/bench_speed.py --threads 1 --sets 1          # 1 thread (CPU time ~ work, robust to load);
                                                                 #   decoder timed on 1 of the 17 sample sets
  python benchmarks/bench_speed.py --large small --tiles 16      # 2048^2 K=16 scalable (new code only; --tiles N
                                                                 #   runs the first N of the 16 tiles and
                                                                 #   extrapolates, labelled as such)
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BASELINE = "f87ac8c"
DECODER_TIMERS = {"glc_upsample", "glc_aggregation", "regressor attention", "heads", "decode"}
STAGES = [
    ("encoder", "backbone"), ("encoder", "light-axis attention"), ("encoder", "UPerNet fusion"),
    ("encoder", "resize/interleave/smoothing"),
    ("decoder", "pixel sampling"), ("decoder", "glc_upsample"), ("decoder", "glc_aggregation"),
    ("decoder", "regressor attention"), ("decoder", "heads"), ("", "other"),
]


# ----------------------------------------------------------------------------------------------- child side
class _Timers:
    def __init__(self):
        self.t: dict[str, list[float]] = {}

    def wrap(self, obj, attr: str, name: str) -> None:
        fn = getattr(obj, attr)

        def timed(*a, **k):
            w, c = time.perf_counter(), time.process_time()
            try:
                return fn(*a, **k)
            finally:
                acc = self.t.setdefault(name, [0.0, 0.0])
                acc[0] += time.perf_counter() - w
                acc[1] += time.process_time() - c

        setattr(obj, attr, timed)

    def get(self, name: str) -> list[float]:
        return self.t.get(name, [0.0, 0.0])


def child_stages(preset: str, side: int, k: int, dtype: str, threads: int, out_npz: str, sets: int = 0) -> dict:
    """Run predict() once with per-stage timers; returns the record (times, RSS). ``sets`` > 0: encode, then
    decode only the first ``sets`` sample sets exactly as predict() forms them (same shuffle), and scale the
    decoder times by (number of sets) / sets; the normals cover those pixels only."""
    import resource

    import numpy as np
    import torch

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_networks import make_object
    from networks.checkpoint import reference_weights
    from networks.config import get_config
    from networks.inference import predict
    from networks.model import build_model

    torch.set_num_threads(threads)
    cfg = get_config(preset, "normal")
    model = build_model(cfg, reference_weights(cfg, "bench")).eval()
    images, mask = make_object(side, k)
    n_pixels = int(mask.sum())
    tm = _Timers()
    enc = model.image_encoder
    tm.wrap(enc.backbone, "forward", "backbone")
    for block in enc.fusion.comm:
        tm.wrap(block, "forward", "light-axis attention")
    tm.wrap(enc.fusion.fusion, "forward", "UPerNet fusion")
    tm.wrap(model.glc_upsample, "forward", "glc_upsample")
    tm.wrap(model.glc_aggregation, "forward", "glc_aggregation")
    tm.wrap(model.regressor.comm, "forward", "regressor attention")
    tm.wrap(model.regressor.prediction_normal, "forward", "heads")
    tm.wrap(model, "encode", "encode")
    tm.wrap(model, "decode", "decode")
    autocast = torch.bfloat16 if dtype == "bf16" else None
    factor = 1.0
    w0, c0 = time.perf_counter(), time.process_time()
    if not sets:
        out = predict(model, torch.from_numpy(images), torch.from_numpy(mask), autocast_dtype=autocast)
        normal = out["normal"]
    else:
        from networks.inference import split_sample_sets

        x, mb = torch.from_numpy(images), torch.from_numpy(mask)
        ids = torch.nonzero(mb.reshape(-1), as_tuple=False).squeeze(1)
        ids = ids[torch.randperm(ids.numel(), generator=torch.Generator().manual_seed(0))]
        sizes = split_sample_sets(int(ids.numel()), cfg.pixel_samples)
        factor = len(sizes) / min(sets, len(sizes))
        flat = np.zeros((side * side, 3), np.float32)
        ctx = torch.autocast("cpu", dtype=autocast) if autocast else torch.autocast("cpu", enabled=False)
        with torch.inference_mode(), ctx:
            feats = model.encode(x[None], mb[None, None].float())
            start = 0
            for size in sizes[:sets]:
                sel = ids[start:start + size]
                flat[sel.numpy()] = model.decode(x[None], mb[None, None].float(), feats, sel[None])["normal"][0].float()
                start += size
        normal = flat.reshape(side, side, 3)
        mask = mask & (np.linalg.norm(normal, axis=-1) > 0)
    total = [time.perf_counter() - w0, time.process_time() - c0]
    np.savez(out_npz, normal=normal, mask=mask)

    def minus(a, *bs):
        return [a[i] - sum(b[i] for b in bs) for i in range(2)]

    def g(name):
        v = tm.get(name)
        return [t * factor for t in v] if name in DECODER_TIMERS else v

    if factor != 1.0:  # decoder extrapolated: the total is encoder + extrapolated decoder + other
        total = [total[i] + (factor - 1.0) * tm.get("decode")[i] for i in range(2)]
    stages = {
        "backbone": g("backbone"), "light-axis attention": g("light-axis attention"),
        "UPerNet fusion": g("UPerNet fusion"),
        "resize/interleave/smoothing": minus(g("encode"), g("backbone"), g("light-axis attention"),
                                             g("UPerNet fusion")),
        "glc_upsample": g("glc_upsample"), "glc_aggregation": g("glc_aggregation"),
        "regressor attention": g("regressor attention"), "heads": g("heads"),
        "pixel sampling": minus(g("decode"), g("glc_upsample"), g("glc_aggregation"), g("regressor attention"),
                                g("heads")),
        "other": minus(total, g("encode"), g("decode")),
    }
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {"stages": stages, "encoder": g("encode"), "decoder": g("decode"), "total": total,
            "peak_rss_mb": rss, "pixels": n_pixels, "decoder_factor": factor}


def child_large(preset: str, k: int, dtype: str, threads: int, tiles: int) -> dict:
    """2048^2 scalable mode (decoder 512, 16 polyphase tiles). tiles < 16: only the first ``tiles`` tiles run
    (exactly what predict_scalable runs for them) and the total is extrapolated by pixel count."""
    import resource

    import numpy as np
    import torch

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_networks import make_object
    from networks.checkpoint import reference_weights
    from networks.config import get_config
    from networks.inference import predict, predict_scalable
    from networks.model import build_model

    torch.set_num_threads(threads)
    side, dec = 2048, 512
    cfg = get_config(preset, "normal")
    model = build_model(cfg, reference_weights(cfg, "bench")).eval()
    images, mask = make_object(side, k)
    x, m = torch.from_numpy(images), torch.from_numpy(mask)
    autocast = torch.bfloat16 if dtype == "bf16" else None
    w0, c0 = time.perf_counter(), time.process_time()
    s = side // dec
    done = 0
    if tiles >= s * s:
        predict_scalable(model, x, m, decoder_resolution=dec, autocast_dtype=autocast)
        done = int(mask.sum())
    else:
        for t in range(tiles):
            a, b = divmod(t, s)
            predict(model, x[:, :, a::s, b::s].contiguous(), m[a::s, b::s].contiguous(), autocast_dtype=autocast)
            done += int(mask[a::s, b::s].sum())
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    frac = done / int(mask.sum())
    return {"wall_s": wall, "cpu_s": cpu, "tiles": min(tiles, s * s), "fraction": frac,
            "wall_full_s": wall / frac, "cpu_full_s": cpu / frac, "peak_rss_mb": rss, "pixels": int(mask.sum())}


def child_capture(out_dir: str, threads: int) -> dict:
    """`matcap capture examples/bunny --linear --relight studio_small_03.exr` in-process, timed per phase."""
    import resource

    import torch

    torch.set_num_threads(threads)
    import matcap.capture as cap_mod
    import matcap.estimate as estimate_mod
    from matcap import cli

    phases: dict[str, float] = {}

    def wrap(mod, name, label):
        fn = getattr(mod, name)

        def timed(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                phases[label] = phases.get(label, 0.0) + time.perf_counter() - t

        setattr(mod, name, timed)

    wrap(cap_mod, "load_capture", "read photos")  # the name the capture calls (from matcap.photos)
    wrap(estimate_mod, "estimate", "networks")
    import matcap.results as results_mod
    wrap(results_mod, "write_result", "write maps")
    argv = ["capture", str(ROOT / "examples" / "bunny"), "--linear", "--out", out_dir, "--relight",
            str(ROOT / "matcap" / "data" / "envmaps" / "studio_small_03.exr"), "--overwrite"]
    w0, c0 = time.perf_counter(), time.process_time()
    rc = cli.main(argv)
    total = [time.perf_counter() - w0, time.process_time() - c0]
    meta = json.loads((Path(out_dir) / "capture.json").read_text())
    timings = meta.get("timings", {})
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {"rc": rc, "total": total, "phases": phases, "net_timings": timings, "peak_rss_mb": rss}


# ---------------------------------------------------------------------------------------------- parent side
def _run_child(tree: Path, args: list[str], threads: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--_child", json.dumps(args),
                           "--threads", str(threads)], capture_output=True, text=True, env=env, cwd=str(tree))
    if proc.returncode != 0:
        raise RuntimeError(f"child {args} failed: {proc.stderr.strip()[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _old_tree(rev: str, tmp: str) -> Path:
    dest = Path(tmp) / f"old-{rev}"
    dest.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    # the child script itself always comes from this tree (it only times; the code under test is on PYTHONPATH)
    return dest


def _angles(a_npz: str, b_npz: str) -> tuple[float, float]:
    import numpy as np

    a, b = np.load(a_npz), np.load(b_npz)
    m = a["mask"]
    x, y = a["normal"][m].astype(np.float64), b["normal"][m].astype(np.float64)
    ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(x, y), axis=-1), (x * y).sum(-1)))
    return float(ang.mean()), float(ang.max())


def _ratio(a: float, b: float) -> str:
    return f"{a / b:5.2f}x" if b > 0 else "   - "


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", default="small,paper")
    ap.add_argument("--dtypes", default="fp32,bf16")
    ap.add_argument("--side", type=int, default=512)
    ap.add_argument("--k", type=int, default=16)
    ap.add_argument("--old", default=BASELINE, help="git revision of the old code (default %(default)s)")
    ap.add_argument("--no-old", action="store_true", help="new code only")
    ap.add_argument("--capture", action="store_true", help="also time the bundled example end to end")
    ap.add_argument("--capture-only", action="store_true")
    ap.add_argument("--large", help="preset for the 2048^2 K=16 scalable row (new code only)")
    ap.add_argument("--large-dtype", default="fp32")
    ap.add_argument("--tiles", type=int, default=16, help="tiles of the 2048^2 row to run (16 = all)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sets", type=int, default=0,
                    help="decode only the first N sample sets and extrapolate the decoder times (0 = all)")
    ap.add_argument("--json", help="also write every record as JSON here")
    ap.add_argument("--_child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args._child:
        c = json.loads(args._child)
        if c[0] == "stages":
            rec = child_stages(c[1], c[2], c[3], c[4], args.threads, c[5], c[6])
        elif c[0] == "large":
            rec = child_large(c[1], c[2], c[3], args.threads, c[4])
        else:
            rec = child_capture(c[1], args.threads)
        print(json.dumps(rec))
        return 0

    import torch

    print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, torch {torch.__version__}, {args.threads} threads, "
          f"{os.cpu_count()} CPUs ({torch.backends.cpu.get_cpu_capability()}, bf16 instructions: "
          f"{'yes' if torch.ops.mkldnn._is_mkldnn_bf16_supported() else 'no, emulated'}), load average "
          f"{os.getloadavg()[0]:.1f} at start; old = {args.old}, new = working tree", flush=True)
    records: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        versions = [("new", ROOT)] if args.no_old else [("old", _old_tree(args.old, tmp)), ("new", ROOT)]
        if args.large:
            rec = _run_child(ROOT, ["large", args.large, args.k, args.large_dtype, args.tiles], args.threads)
            records["large"] = rec
            label = "measured" if rec["tiles"] >= 16 else f"EXTRAPOLATED from {rec['tiles']}/16 tiles"
            print(f"{args.large} 2048^2 K={args.k} scalable {args.large_dtype}: wall {rec['wall_s']:.0f} s, cpu "
                  f"{rec['cpu_s']:.0f} s for {rec['fraction'] * 100:.0f}% of the pixels; full image ({label}): "
                  f"wall {rec['wall_full_s']:.0f} s, cpu {rec['cpu_full_s']:.0f} s; peak RSS "
                  f"{rec['peak_rss_mb'] / 1024:.2f} GB", flush=True)
        presets = [] if (args.capture_only or args.large) else [p for p in args.presets.split(",") if p]
        for preset in presets:
            runs = {}
            for dtype in args.dtypes.split(","):
                for name, tree in versions:
                    npz = os.path.join(tmp, f"{preset}-{dtype}-{name}.npz")
                    runs[(dtype, name)] = _run_child(tree, ["stages", preset, args.side, args.k, dtype, npz,
                                                            args.sets], args.threads)
                    runs[(dtype, name)]["npz"] = npz
            records[preset] = {f"{d}-{n}": r for (d, n), r in runs.items()}
            names = [n for n, _ in versions]
            first = runs[next(iter(runs))]
            extra = (f"; decoder EXTRAPOLATED x{first['decoder_factor']:.1f} from {args.sets} sample set(s)"
                     if first["decoder_factor"] != 1.0 else "")
            print(f"\n## {preset} {args.side}^2 K={args.k} ({first['pixels']} pixels{extra}): seconds", flush=True)
            for dtype in args.dtypes.split(","):
                hdr = f"{preset + ' ' + dtype:44s}"
                for n in names:
                    hdr += f" {n + ' wall':>9s} {n + ' cpu':>9s}"
                if len(names) == 2:
                    hdr += f" {'wall old/new':>12s} {'cpu old/new':>12s}"
                print(hdr)
                rows = [(f"{part}: {stage}" if part else stage, lambda r, s=stage: r["stages"][s])
                        for part, stage in STAGES]
                rows += [("encoder total", lambda r: r["encoder"]), ("decoder total", lambda r: r["decoder"]),
                         ("TOTAL predict()", lambda r: r["total"])]
                for label, get in rows:
                    line = f"  {label:42s}"
                    vals = [get(runs[(dtype, n)]) for n in names]
                    for v in vals:
                        line += f" {v[0]:9.1f} {v[1]:9.1f}"
                    if len(names) == 2:
                        line += f" {_ratio(vals[0][0], vals[1][0]):>12s} {_ratio(vals[0][1], vals[1][1]):>12s}"
                    print(line)
                line = f"  {'peak RSS MB':42s}"
                for n in names:
                    line += f" {runs[(dtype, n)]['peak_rss_mb']:9.0f} {'':9s}"
                print(line)
            notes = []
            if len(names) == 2:
                for dtype in args.dtypes.split(","):
                    mean, mx = _angles(runs[(dtype, 'old')]["npz"], runs[(dtype, 'new')]["npz"])
                    notes.append(f"{dtype} new vs old normals: {mean:.5f} deg mean, {mx:.4f} deg max")
            if "fp32" in args.dtypes and "bf16" in args.dtypes:
                for n in names:
                    mean, mx = _angles(runs[("fp32", n)]["npz"], runs[("bf16", n)]["npz"])
                    notes.append(f"{n} code bf16 vs fp32 normals: {mean:.3f} deg mean, {mx:.2f} deg max")
            for note in notes:
                print("  " + note)
        if args.capture or args.capture_only:
            caps = {}
            for name, tree in versions:
                caps[name] = _run_child(tree, ["capture", os.path.join(tmp, f"cap-{name}")], args.threads)
            records["capture"] = caps
            names = [n for n, _ in versions]
            print("\n## capture examples/bunny --linear --relight studio_small_03.exr (50 photos 256^2; wall s)")
            labels = ["read photos", "networks", "write maps"]
            print(f"{'':30s}" + "".join(f" {n:>9s}" for n in names) + ("  old/new" if len(names) == 2 else ""))
            for lab in labels + ["relight + rest", "TOTAL (in-process)"]:
                vals = []
                for n in names:
                    r = caps[n]
                    if lab == "TOTAL (in-process)":
                        vals.append(r["total"][0])
                    elif lab == "relight + rest":
                        vals.append(r["total"][0] - sum(r["phases"].get(x, 0.0) for x in labels))
                    else:
                        vals.append(r["phases"].get(lab, 0.0))
                print(f"{lab:30s}" + "".join(f" {v:9.1f}" for v in vals)
                      + (f"  {_ratio(vals[0], vals[1])}" if len(vals) == 2 else ""))
            for n in names:
                t = caps[n]["net_timings"]
                print(f"  {n}: capture.json timings " + ", ".join(f"{k}={v:.1f}" for k, v in t.items())
                      + f"; peak RSS {caps[n]['peak_rss_mb']:.0f} MB")
    if args.json:
        Path(args.json).write_text(json.dumps(records, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
