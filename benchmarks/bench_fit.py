"""The fit's speed (matcap.refine.refine) on an idle and on a busy machine, old code against new (Markdown table).

    python benchmarks/bench_fit.py                      # known lights, 512^2, K=16, 2 threads; idle, then 2 busy
                                                        # processes; the old code (git archive of --old) and this one
    python benchmarks/bench_fit.py --load 0,2,3 --repeats 2 --estimated --old main --threads 2
    python benchmarks/bench_fit.py --steps --old main   # milliseconds: a step of the estimated lights' fit, the
                                                        # known directions' light fit, a per-pixel Jacobian

Each fit runs in its own subprocess on the photos that ``benchmarks/refine_check.py timing`` uses (a sphere rendered
by the fit's own model under 16 directional lights, the perturbed maps as the start). "Busy" starts that many
processes that spin a CPU core for the whole fit (on a 2-core machine, 2 of them make a load of about 3 with the
fit). Columns: wall seconds of the fit, CPU seconds (user + system, every thread), the fit's stage timings, peak
memory, and the mean angle of the fitted normals to the true ones (the same for every load: the fit's result does
not depend on it). Old and new alternate, so both see the same machine.
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


def _sphere(side: int, k: int = 16):
    """The benchmark's capture: a sphere's maps (``side`` px) rendered by the fit's own model under ``k`` directional
    lights of irradiance 2.5. Returns (true MaterialMaps, directions (k, 3) torch, photos (k, side, side, 3)
    float32, the perturbed maps the fit starts from)."""
    import numpy as np
    import torch

    from matcap.evaluation.toy import cone_lights
    from matcap.refine import synthetic as S
    from matcap.refine.model import shade_directional

    truth = S.sphere_maps(side)
    m = truth.mask
    n, b, r = (torch.from_numpy(a[m]) for a in (truth.normal, truth.base_color, truth.roughness))
    dirs = torch.from_numpy(cone_lights(k, 50.0, seed=1)).float()
    with torch.no_grad():
        px = shade_directional(n, b, r, torch.zeros(len(n)), dirs, torch.full((k, 3), 2.5), torch.zeros(1, 9, 3))
    photos = np.zeros((k, side, side, 3), np.float32)
    photos[:, m] = px.numpy()
    return truth, dirs, photos, S.perturb(truth)


def child(side: int, threads: int, estimated: bool) -> dict:
    """One fit in this process: seconds, CPU seconds, stage timings, peak RSS, normal error."""
    import resource

    import torch

    if threads:
        torch.set_num_threads(threads)
    from matcap.evaluation.metrics import angular_error_map
    from matcap.lightfiles import KnownLights
    from matcap.refine import RefineSettings, refine

    truth, lights, photos, start = _sphere(side)
    m = truth.mask
    known = None if estimated else KnownLights(lights.numpy().astype(float), None, "file", "bench", "order")

    def cpu() -> float:
        u = resource.getrusage(resource.RUSAGE_SELF)
        return u.ru_utime + u.ru_stime

    c0, t0 = cpu(), time.perf_counter()
    res = refine(list(photos), start, RefineSettings(seed=0), lights=known)
    wall, used = time.perf_counter() - t0, cpu() - c0
    err = angular_error_map(res.maps.normal, truth.normal, m)[m]
    return {"wall": wall, "cpu": used, "lights_s": res.report["timings"]["lights_s"],
            "maps_s": res.report["timings"]["maps_s"],
            "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "normal_deg": float(err.mean())}


def steps(threads: int, repeats: int = 5) -> dict:
    """In this process: the fastest of ``repeats`` runs, in milliseconds, of a step of the estimated lights' fit
    (50 Adam steps on 4,096 pixels of a sphere under 16 directional lights), of the whole light fit where the
    directions are known (2,048 pixels; the intensities and the ambient from a start of 0.5), and of the
    per-pixel solve's Jacobian (``shade_jacobian``) of 16,384 of its pixels."""
    import numpy as np
    import torch

    if threads:
        torch.set_num_threads(threads)
    from matcap.refine import RefineSettings
    try:  # the fit's stages, one module each (the lights' shared fits in light_fit)
        from matcap.refine import photos as P
        try:
            from matcap.refine import light_fit as L
        except ImportError:  # an --old revision whose lights stage is one module
            from matcap.refine import light_stage as L
    except ImportError:  # an --old revision whose fit is one module
        from matcap.refine import fit as L
        P = L
    from matcap.refine.model import LightParams, PixelParams, shade_jacobian

    truth, dirs, obs, start = _sphere(160)
    k, m = len(dirs), truth.mask
    s = RefineSettings(seed=0)
    arrays = P._maps_arrays(start)
    out = {}

    def best(run) -> float:
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            run()
            times.append(time.perf_counter() - t0)
        return min(times)

    def problem(count):
        idx = np.sort(np.random.default_rng(0).choice(int(m.sum()), size=count, replace=False))
        return P._Problem(torch, obs, m, arrays, np.ones(m.shape, np.float32), np.full((k, 3), np.inf, np.float32),
                          torch.device("cpu"), idx)

    def start_lights():
        return LightParams("directional", dirs.clone(), torch.full((k, 3), 0.5), torch.zeros(1, 9, 3))

    estimated, known = problem(4096), problem(2048)
    out["light_fit_4096_ms"] = best(lambda: L._fit_lights(torch, estimated, start_lights(), s, P._Bar(None, s),
                                                          "lights", 50)) / 50 * 1000

    def known_fit():
        if hasattr(L, "_fit_intensities"):
            L._fit_intensities(torch, known, start_lights(), s, P._Bar(None, s))
        else:  # revisions before the Levenberg-Marquardt fit of known directions: Adam steps
            L._fit_lights(torch, known, start_lights(), s, P._Bar(None, s), "lights", s.lights.iters,
                          directions_free=False)
    out["known_fit_2048_ms"] = best(known_fit) * 1000
    count = 16384
    p = PixelParams.from_maps(*(torch.from_numpy(a[m][:count]) for a in (start.normal, start.base_color,
                                                                          start.roughness, start.metallic)))
    nrm = p.normal()
    tangents = torch.stack([torch.cross(nrm, torch.tensor([1.0, 0.0, 0.0]).expand_as(nrm), dim=-1)] * 2)
    with torch.no_grad(), P._one_thread(torch):
        out["jacobian_16384_ms"] = best(lambda: shade_jacobian(nrm, p.base(), p.rough(), p.metal(), dirs[:, None],
                                                              torch.full((k, 1, 3), 2.5), torch.zeros(1, 9, 3),
                                                              tangents)) * 1000
    return out


def _run(tree: Path, job: list, load: int, passive: bool) -> dict:
    """``job`` (the child's arguments: [side, threads, estimated] for a fit, ["steps", threads]) in a subprocess
    on the code of ``tree``, beside ``load`` busy processes."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    env.pop("OMP_WAIT_POLICY", None)
    if passive:  # as the matcap command sets it (matcap.cli)
        env["OMP_WAIT_POLICY"] = "PASSIVE"
    spin = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(load)]
    try:
        proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--_child",
                               json.dumps(job)], cwd=tree, capture_output=True, text=True,
                              env=env)
    finally:
        for p in spin:
            p.kill()
            p.wait()
    if proc.returncode:
        raise SystemExit(proc.stderr[-3000:])
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _old_tree(rev: str, tmp: str) -> Path:
    dest = Path(tmp) / "old"
    dest.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    shared = ROOT.parent / "shared"
    if shared.exists() and not (dest.parent / "shared").exists():
        (dest.parent / "shared").symlink_to(shared)
    return dest


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--side", type=int, default=512)
    ap.add_argument("--threads", type=int, default=2, help="torch threads (0: torch's default)")
    ap.add_argument("--load", default="0,2", help="busy processes to run beside the fit, one value per row")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--estimated", action="store_true", help="lights estimated (default: the true lights given)")
    ap.add_argument("--wait", default="default",
                    help="OpenMP threads' waiting: default (libgomp spins a while, then sleeps), passive (they "
                         "sleep: what the matcap command sets), or both (a row each)")
    ap.add_argument("--old", default=None, help="git revision of the old code (default: none, the new code only)")
    ap.add_argument("--steps", action="store_true",
                    help="time single steps (the light fit's, the per-pixel solve's Jacobian) instead of whole fits")
    ap.add_argument("--_child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args._child is not None:
        what = json.loads(args._child)
        print(json.dumps(steps(what[1]) if what[0] == "steps" else child(*what)))
        return 0
    loads = [int(v) for v in args.load.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        trees = ([("old " + args.old, _old_tree(args.old, tmp))] if args.old else []) + [("new", ROOT)]
        if args.steps:
            print(f"Milliseconds per step (the fastest of 5 runs), {args.threads or 'default'} threads, "
                  f"idle, OpenMP wait passive")
            print("| code | estimated lights, a step, 4,096 pixels | known directions, the whole light fit, 2,048 "
                  "pixels | Jacobian, 16,384 pixels, one thread |")
            print("|---|---:|---:|---:|")
            for _ in range(args.repeats):
                for name, tree in trees:
                    r = _run(tree, ["steps", args.threads], 0, True)
                    print(f"| {name} | {r['light_fit_4096_ms']:.2f} | {r['known_fit_2048_ms']:.0f} | "
                          f"{r['jacobian_16384_ms']:.1f} |", flush=True)
            return 0
        what = "lights estimated" if args.estimated else "known lights"
        print(f"Fit at {args.side}^2, K=16, {what}, {args.threads or 'default'} threads")
        print("| code | OpenMP wait | busy processes | wall s | CPU s | lights s | maps s | peak RSS MB | "
              "normals deg |")
        print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
        waits = ["default", "passive"] if args.wait == "both" else [args.wait]
        for load in loads:
            for _ in range(args.repeats):
                for wait in waits:
                    for name, tree in trees:
                        r = _run(tree, [args.side, args.threads, args.estimated], load, wait == "passive")
                        print(f"| {name} | {wait} | {load} | {r['wall']:.1f} | {r['cpu']:.1f} | {r['lights_s']:.1f} | "
                              f"{r['maps_s']:.1f} | {r['rss_mb']:.0f} | {r['normal_deg']:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
