"""One call of the self-contained GPU training recipe: the lent machine renders its own data v2 and trains both
networks on it while the set grows. docs/training.md ("Training on a lent GPU") has the plan and the budget.

    python3 docs/recipes/gpu_train.py --call 1 --seconds 560            # call 1 (carry: carry/mitsuba)
    python3 docs/recipes/gpu_train.py --call 2 --seconds 560            # later calls (carry: carry/mitsuba, carry/resume)
    python3 docs/recipes/gpu_train.py --call 5 --seconds 560 --last     # the last call stops everything
    python3 docs/recipes/gpu_train.py --call 1 --seconds 40 --dry-run --work W --out O   # tiny, on a CPU (the tests)

Each call, in order (one line per stage):

1. Mitsuba: imported as installed, else unpacked from ``carry/mitsuba/*.tar.xz`` (docs/recipes/build_mitsuba_carry.py).
2. Variant: the first of cuda_ad_rgb, scalar_rgb, llvm_ad_rgb that renders a test scene (each probed in a child).
3. Validation set: ``--val-scenes`` scenes (data v2, or ``--data-version 1``) of seed 11, test split, rendered
   before anything else by all render processes (shards of one `matcap synth` set): the same scenes on every
   machine and every call; or a carried pack of them (``--val-pack``).
4. Training data: ``--render-procs`` background processes render data v2 scenes of seed ``--seed-base + M`` into
   one folder (shard i of n each), where M is the call that started this machine: scene k of that seed is the same
   whoever renders it (`matcap synth --data-version 2 --seed S --resolution R --spp P --split train`), and a fresh
   machine draws scenes no earlier machine drew.
5. Training: the normal and the BRDF runs start once ``--min-scenes`` scenes exist and re-list the folder every
   ``--rescan-s`` seconds (`networks.train --rescan-every-s`). Each run continues from the best state there is: its
   own checkpoint on this machine (a warm machine: bit-for-bit), else the weights the previous call returned
   (``carry/resume/{n,b}_last.safetensors``: `--resume-from`, fresh optimiser), else the bundled weights.
6. Until ``--seconds`` minus a margin: one status line every ``--poll-s`` (scenes, steps, losses, validation).
7. Return: both runs stop (SIGTERM: they finish the step and write checkpoint.pt), and ``OUT`` gets each run's last
   weights as float16 (``n_last`` / ``b_last``: what the next call carries as ``carry/resume``), its best weights
   when they improved on this machine (``n_best`` / ``b_best``), and ``logs.tar.gz`` (training logs, validation
   curves, render progress, this call's log). Then, unless ``--last`` or ``--dry-run``, the runs restart with
   ``--resume`` and the renderers go on, detached, so a machine that stays warm keeps working until the next call.

``--dry-run``: the same steps at tiny sizes on this CPU (32 px scenes, 1 spp, the tiny preset, a few steps), and
everything stops at the end of the call; tests/test_gpu_recipe.py runs two calls with a machine return between them.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
VAL_SEED = 11
#: Probed in this order. On a CPU, scalar_rgb renders these 128 px, 16 spp scenes faster than llvm_ad_rgb with one
#: thread per process (4.1 vs 6.6 CPU-seconds a scene, docs/training.md), and needs no libLLVM.
VARIANTS = ("cuda_ad_rgb", "scalar_rgb", "llvm_ad_rgb")
RUNS = ("n", "b")  # normal, BRDF

_PROBE = r"""
import sys, time
import mitsuba as mi
mi.set_variant(sys.argv[1])
scene = mi.load_dict({"type": "scene", "integrator": {"type": "path"},
    "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 16, "height": 16}},
    "shape": {"type": "rectangle", "bsdf": {"type": "principled"}}, "light": {"type": "constant"}})
t0 = time.time()
import numpy as np
v = float(np.array(mi.render(scene, spp=4)).mean())
assert 0 < v < 10, v
print(round(time.time() - t0, 2))
"""


class Call:
    def __init__(self, args):
        self.a = args
        self.t0 = time.time()
        self.work = Path(args.work)
        self.out = Path(args.out)
        self.work.mkdir(parents=True, exist_ok=True)
        self.out.mkdir(parents=True, exist_ok=True)
        self.log_path = self.work / f"call_{args.call}.log"
        self.state_path = self.work / "state.json"
        self.state = json.loads(self.state_path.read_text()) if self.state_path.exists() else {}
        self.env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.log_offset: dict[str, int] = {}  # size of each run's log.jsonl when this call started it
        self.env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in [self.env.get("PYTHONPATH")] if p])

    # ------------------------------------------------------------------ bookkeeping
    def say(self, msg: str) -> None:
        line = f"[{time.time() - self.t0:6.1f}s] {msg}"
        print(line, flush=True)
        with open(self.log_path, "a") as f:
            f.write(line + "\n")

    def save_state(self) -> None:
        tmp = self.state_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.state, indent=1))
        os.replace(tmp, self.state_path)

    def left(self) -> float:
        return self.a.seconds - (time.time() - self.t0)

    # ------------------------------------------------------------------ 1-2: Mitsuba and its variant
    def setup_wheels(self) -> None:
        """Install the carried wheels (``carry/wheels/*.whl``: the product's dependencies the machine's image lacks,
        e.g. OpenEXR, trimesh, colour-science) into the work folder, once per machine."""
        from importlib import metadata

        def norm(name: str) -> str:
            return name.lower().replace("-", "_")

        have = {norm(d.metadata["Name"] or "") for d in metadata.distributions()}
        wheels = [w for w in sorted(Path(self.a.carry).glob("wheels/*.whl")) if norm(w.name.split("-")[0]) not in have]
        if not wheels:
            return
        site = self.work / "wheels"
        if not (site / ".installed").exists():
            subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile",
                            "--upgrade", "--target", str(site)] + [str(w) for w in wheels], check=True)
            (site / ".installed").write_text("\n".join(w.name for w in wheels))
        self.env["PYTHONPATH"] = os.pathsep.join([self.env["PYTHONPATH"], str(site)])
        self.say(f"wheels: {', '.join(w.name.split('-')[0] for w in wheels)} installed into {site}")

    def setup_mitsuba(self) -> None:
        if not self.a.carried_mitsuba:
            try:
                subprocess.run([sys.executable, "-c", "import mitsuba"], env=self.env, check=True, capture_output=True)
                self.say("mitsuba: installed here")
                return
            except subprocess.CalledProcessError:
                pass
        tag = f"cp{sys.version_info.major}{sys.version_info.minor}"
        archives = sorted(Path(self.a.carry).glob(f"mitsuba/mitsuba-*-{tag}.tar.xz"))
        if not archives:
            raise SystemExit(f"gpu_train: no Mitsuba here and none carried for this Python "
                             f"({self.a.carry}/mitsuba/*-{tag}.tar.xz: docs/recipes/build_mitsuba_carry.py)")
        site = self.work / "site"
        if not (site / ".unpacked").exists():
            site.mkdir(exist_ok=True)
            with tarfile.open(archives[-1]) as tar:
                if hasattr(tarfile, "data_filter"):
                    tar.extractall(site, filter="tar")
                else:
                    tar.extractall(site)
            (site / ".unpacked").write_text(archives[-1].name)
        self.env["PYTHONPATH"] = os.pathsep.join([str(site), self.env["PYTHONPATH"]])
        where = subprocess.run([sys.executable, "-c", "import mitsuba; print(mitsuba.__file__)"], env=self.env,
                               check=True, capture_output=True, text=True).stdout.strip()
        self.say(f"mitsuba: {archives[-1].name} unpacked into {site} ({where})")

    def choose_variant(self) -> str:
        if self.state.get("variant"):
            return self.state["variant"]
        order = [self.a.variant] if self.a.variant != "auto" else list(VARIANTS)
        probes = {}
        for v in order:
            try:
                r = subprocess.run([sys.executable, "-c", _PROBE, v], env=self.env, capture_output=True, text=True,
                                   timeout=300)
                ok = r.returncode == 0
                probes[v] = r.stdout.strip() if ok else (r.stderr.strip().splitlines() or ["failed"])[-1][:200]
            except subprocess.TimeoutExpired:
                ok, probes[v] = False, "timed out"
            self.say(f"variant probe {v}: {'ok, ' + probes[v] + ' s' if ok else 'no: ' + probes[v]}")
            if ok:
                self.state.update(variant=v, probes=probes)
                self.save_state()
                return v
        raise SystemExit("gpu_train: no Mitsuba variant renders here")

    # ------------------------------------------------------------------ 3-4: rendering
    def render_procs(self, variant: str) -> tuple[int, int]:
        """(processes, Dr.Jit threads each)."""
        cores = os.cpu_count() or 2
        if self.a.render_procs:
            n = self.a.render_procs
        elif variant.startswith("cuda"):
            n = 4
        else:  # leave cores to the trainers' data workers
            n = max(1, cores - self.a.train_cores)
        threads = 1 if variant.startswith("cuda") else max(1, (cores - self.a.train_cores) // n)
        return n, threads

    def render_cmd(self, out: Path, seed: int, scenes: int, split: str, shard: str, threads: int, variant: str):
        return [sys.executable, __file__, "--render-worker", "--render-out", str(out), "--render-seed", str(seed),
                "--render-scenes", str(scenes), "--render-split", split, "--render-shard", shard,
                "--render-threads", str(threads), "--variant", variant, "--resolution", str(self.a.resolution),
                "--spp", str(self.a.spp), "--data-version", str(self.a.data_version)] + (
                    ["--assets", self.a.assets] if self.a.assets else [])

    def setup_carried_data(self) -> None:
        """A carried asset archive (``--assets X.tar.xz``, docs/recipes/make_gpu_assets.py) unpacked into the work
        folder, and a carried validation set (``--val-pack``, a `networks.datapack` pack) unpacked as the
        validation set, once per machine."""
        a = self.a
        if a.assets and a.assets.endswith((".tar.xz", ".tar")):
            dest = self.work / "assets"
            if not (dest / ".unpacked").exists():
                dest.mkdir(parents=True, exist_ok=True)
                with tarfile.open(a.assets) as tar:
                    tar.extractall(dest, filter="data")
                (dest / ".unpacked").write_text(a.assets)
            self.say(f"assets: {a.assets} unpacked into {dest}")
            a.assets = str(dest)
        if a.val_pack:
            from networks.datapack import unpack

            val = self.work / "val"
            if not (val / "manifest.json").exists():
                unpack([a.val_pack], val)
                names = sorted(p.parent.name for p in val.glob("*/data.npz"))
                (val / "manifest.json").write_text(json.dumps({"scenes": names, "source": a.val_pack}))
            count = len(list(val.glob("*/data.npz")))
            a.val_scenes = min(a.val_scenes, count)
            self.say(f"validation set: {count} scenes from {a.val_pack}, {a.val_scenes} used")

    def render_validation(self, variant: str) -> None:
        val = self.work / "val"
        if (val / "manifest.json").exists() and len(list(val.glob("scene_*/data.npz"))) >= self.a.val_scenes:
            self.say(f"validation set: {self.a.val_scenes} scenes already here")
            return
        n, threads = self.render_procs(variant)
        n = min(n, self.a.val_scenes)
        t = time.time()
        procs = [subprocess.Popen(self.render_cmd(val, VAL_SEED, self.a.val_scenes, "test", f"{i}/{n}", threads,
                                                  variant), env=self.env, stdout=subprocess.DEVNULL,
                                  stderr=open(self.work / f"render_val_{i}.err", "a")) for i in range(n)]
        codes = [p.wait() for p in procs]
        got = len(list(val.glob("scene_*/data.npz")))
        if any(codes) or got < self.a.val_scenes:
            raise SystemExit(f"gpu_train: validation rendering failed ({got} of {self.a.val_scenes} scenes; "
                             f"see {self.work}/render_val_*.err)")
        self.say(f"validation set: {got} scenes (seed {VAL_SEED}, test split) in {time.time() - t:.0f} s "
                 f"with {n} processes")

    def _alive(self, pid: int | None) -> bool:
        if not pid:
            return False
        try:
            os.kill(pid, 0)
        except OSError:
            return False
        try:  # a zombie (our own exited child) is not alive
            return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
        except OSError:
            return True

    def start_renderers(self, variant: str) -> None:
        if "machine_call" not in self.state:
            self.state["machine_call"] = self.a.call
            self.state["train_seed"] = self.a.seed_base + self.a.call
            self.save_state()
        seed = self.state["train_seed"]
        n, threads = self.render_procs(variant)
        pids = self.state.get("render_pids", [])
        if pids and all(self._alive(p) for p in pids):
            self.say(f"training data: {len(pids)} render processes still running (seed {seed})")
            return
        self.stop_pids(pids)
        pids = []
        for i in range(n):
            p = subprocess.Popen(self.render_cmd(self.work / "train", seed, self.a.max_scenes, "train", f"{i}/{n}",
                                                 threads, variant), env=self.env, stdout=subprocess.DEVNULL,
                                 stderr=open(self.work / f"render_{i}.err", "a"), start_new_session=True)
            pids.append(p.pid)
        self.state["render_pids"] = pids
        self.save_state()
        self.say(f"training data: {n} render processes ({variant}, {threads} thread(s) each), seed {seed}, "
                 f"{self.a.resolution} px, {self.a.spp} spp, into {self.work / 'train'}")

    def scenes(self) -> int:
        return len(list((self.work / "train").glob("scene_*/data.npz")))

    # ------------------------------------------------------------------ 5: training
    def train_args(self, r: str) -> list[str]:
        a = self.a
        run = self.work / f"run_{r}"
        args = [sys.executable, "-m", "networks.train", "--data", str(self.work / "train"), "--val-data",
                str(self.work / "val"), "--out", str(run), "--target", "normal" if r == "n" else "brdf",
                "--preset", a.preset, "--canonical-resolution", str(a.resolution), "--resolution", str(a.resolution),
                "--dropout", "0", "--min-images", "3", "--max-images", str(a.max_images), "--batch", str(a.batch),
                "--pixel-samples", str(a.pixel_samples), "--steps", str(a.steps), "--lr", str(a.lr),
                "--warmup-steps", str(a.warmup), "--decay-every", str(a.decay_every), "--decay-factor", "0.7",
                "--val-scenes", str(a.val_scenes), "--val-every-s", str(a.val_every_s), "--checkpoint-every-s",
                str(a.checkpoint_every_s), "--rescan-every-s", str(a.rescan_s), "--workers", str(a.workers),
                "--device", a.device, "--log-every", str(a.log_every), "--quiet"]
        if a.threads:
            args += ["--threads", str(a.threads)]
        if a.bf16:
            args.append("--bf16")
        if r == "b":
            args += ["--brdf-weights", "1,2,2", "--brdf-loss-before-relu"]
        return args

    def start_trainers(self) -> None:
        pids = self.state.setdefault("train_pids", {})
        for r in RUNS:
            if self._alive(pids.get(r)):
                self.say(f"run {r}: still training (pid {pids[r]})")
                continue
            run = self.work / f"run_{r}"
            carried = Path(self.a.carry) / "resume" / f"{r}_last.safetensors"
            init = self.a.init_normal if r == "n" else self.a.init_brdf
            if (run / "checkpoint.pt").exists():
                how = ["--resume"]
            elif carried.exists():
                how = ["--resume-from", str(carried)]
            elif init and init != "none":
                how = ["--init", init]
            else:
                how = []
            log = run / "log.jsonl"
            self.log_offset[r] = log.stat().st_size if log.exists() else 0
            p = subprocess.Popen(self.train_args(r) + how, env=self.env, stdout=open(self.work / f"run_{r}.out", "a"),
                                 stderr=subprocess.STDOUT, start_new_session=True, cwd=REPO)
            pids[r] = p.pid
            self.say(f"run {r}: started {' '.join(how) or 'from random weights'} (pid {p.pid})")
        self.save_state()

    def stop_pids(self, pids) -> None:
        """SIGTERM the processes this recipe started (by pid) and wait for them."""
        pids = [p for p in pids if self._alive(p)]
        for p in pids:
            try:
                os.kill(p, signal.SIGTERM)
            except OSError:
                pass
        deadline = time.time() + 120
        for p in pids:
            while self._alive(p) and time.time() < deadline:
                try:  # reap our own child, if it is one
                    os.waitpid(p, os.WNOHANG)
                except ChildProcessError:
                    pass
                time.sleep(0.2)

    def trained(self, r: str) -> bool:
        """Whether run ``r`` has logged a training step since this call started it."""
        log = self.work / f"run_{r}" / "log.jsonl"
        if r not in self.log_offset:
            return True  # not started by this call
        if not log.exists():
            return False
        with open(log) as f:
            f.seek(self.log_offset[r])
            return '"event": "train"' in f.read()

    def run_status(self, r: str) -> str:
        log = self.work / f"run_{r}" / "log.jsonl"
        if not log.exists():
            return f"{r}: starting"
        step, loss, val = 0, float("nan"), ""
        for line in log.read_text().splitlines():
            rec = json.loads(line)
            step = max(step, int(rec.get("step", 0)))
            if rec.get("event") == "train":
                loss = rec["loss"]
            elif rec.get("event") == "val":
                val = (f" val {rec['mae']:.2f} deg" if r == "n" else f" val rmse {rec.get('rmse_mean', float('nan')):.3f}")
        return f"{r}: step {step} loss {loss:.4f}{val}"

    # ------------------------------------------------------------------ 7: what comes back
    def export(self) -> None:
        import torch
        from safetensors import safe_open
        from safetensors.torch import load_file, save_file

        exported = self.state.setdefault("exported_best", {})
        for r in RUNS:
            run = self.work / f"run_{r}"
            names = ["last"]
            best = run / "best.safetensors"
            if best.exists() and exported.get(r) != best.stat().st_mtime_ns:
                names.append("best")
            for w in names:
                src = run / f"{w}.safetensors"
                if not src.exists():
                    continue
                with safe_open(str(src), "pt") as f:
                    meta = f.metadata()
                state = {k: v.to(torch.float16) if v.is_floating_point() else v for k, v in load_file(str(src)).items()}
                save_file(state, str(self.out / f"{r}_{w}.safetensors"), metadata=meta)
                if w == "best":
                    exported[r] = src.stat().st_mtime_ns
        self.save_state()
        with tarfile.open(self.out / "logs.tar.gz", "w:gz") as tar:
            for f in sorted(self.work.glob("run_*/*")):
                if f.suffix in (".jsonl", ".log", ".txt"):
                    tar.add(f, arcname=f"{f.parent.name}/{f.name}")
            for f in sorted(list(self.work.glob("*.log")) + list(self.work.glob("*.out")) +
                            list(self.work.glob("*.err")) + [self.work / "render.jsonl", self.state_path]):
                if f.exists():
                    tar.add(f, arcname=f.name)
        sizes = ", ".join(f"{p.name} {p.stat().st_size / 2**20:.1f} MiB" for p in sorted(self.out.iterdir()))
        self.say(f"returned: {sizes}")

    # ------------------------------------------------------------------ the call
    def run(self) -> int:
        a = self.a
        self.say(f"gpu_train call {a.call}: {a.seconds} s, work {self.work}, out {self.out}, device {a.device}, "
                 f"{os.cpu_count()} cores")
        self.setup_wheels()
        self.setup_mitsuba()
        self.setup_carried_data()
        variant = self.choose_variant()
        self.render_validation(variant)
        self.start_renderers(variant)
        t_wait = time.time()
        while self.scenes() < a.min_scenes and self.left() > a.margin:
            time.sleep(1)
        self.say(f"training data: {self.scenes()} scenes after {time.time() - t_wait:.0f} s")
        if self.scenes() < a.min_scenes:
            self.say("gpu_train: too few scenes to train on before the deadline")
        else:
            self.start_trainers()
        last_poll = 0.0
        with open(self.work / "render.jsonl", "a") as progress:
            while self.left() > a.margin:
                time.sleep(min(1.0, max(self.left() - a.margin, 0)))
                if time.time() - last_poll >= a.poll_s:
                    last_poll = time.time()
                    n = self.scenes()
                    progress.write(json.dumps({"call": a.call, "t": round(time.time(), 1), "scenes": n}) + "\n")
                    progress.flush()
                    alive = [r for r in RUNS if self._alive(self.state.get("train_pids", {}).get(r))]
                    self.say(f"scenes {n}; " + "; ".join(self.run_status(r) for r in RUNS)
                             + ("" if len(alive) == len(RUNS) else f" (running: {alive})"))
        grace = time.time() + a.grace
        while not all(self.trained(r) for r in RUNS) and time.time() < grace:
            time.sleep(0.5)  # (--grace, the dry run's) a run still starting gets to its first step before it stops
        self.stop_pids(self.state.get("train_pids", {}).values())
        self.say("runs stopped: " + "; ".join(self.run_status(r) for r in RUNS))
        stop_all = a.last or a.dry_run
        if stop_all:
            self.stop_pids(self.state.get("render_pids", []))
        self.export()
        if not stop_all:
            self.start_trainers()  # --resume from the checkpoints just written; they run on between calls
        self.say(f"call {a.call} done: {self.scenes()} training scenes on this machine")
        return 0


def render_worker(a) -> int:
    """One shard of a `matcap synth` data v2 set, in this process (the variant and thread count set first)."""
    os.nice(10)  # the trainers' data workers come first
    os.environ["MATCAP_MITSUBA_VARIANT"] = a.variant
    from renderers.variant import choose_variant

    choose_variant(quiet=True)
    if not a.variant.startswith("cuda"):
        import drjit

        drjit.set_thread_count(a.render_threads)
    from matcap.synth import run_synth

    try:
        run_synth(a.render_out, a.render_scenes, resolution=a.resolution, seed=a.render_seed, shard=a.render_shard,
                  assets=a.assets, split=a.render_split, spp=a.spp, progress=False, data_version=a.data_version)
    except KeyboardInterrupt:  # SIGTERM: the scene in progress is dropped, finished ones stay
        return 130
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--call", type=int, default=1, help="call number (1, 2, ...)")
    ap.add_argument("--seconds", type=float, default=560, help="wall time of this call (default 560)")
    ap.add_argument("--last", action="store_true", help="the last call: stop the runs and the renderers")
    ap.add_argument("--dry-run", action="store_true", help="tiny sizes on a CPU (the tests)")
    ap.add_argument("--work", default="/tmp/matcap_gpu", help="this machine's working folder (default %(default)s)")
    ap.add_argument("--out", default=os.environ.get("OUT", "/tmp/matcap_gpu_out"), help="what comes back ($OUT)")
    ap.add_argument("--carry", default=str(REPO / "carry"), help="carried folder (mitsuba/, resume/)")
    ap.add_argument("--variant", default="auto", choices=("auto",) + VARIANTS)
    ap.add_argument("--carried-mitsuba", action="store_true", help="use the carried Mitsuba even where one is "
                    "installed (to check the carried build)")
    ap.add_argument("--assets", default=None, help="assets folder (meshes/, envmaps/, textures/) or an archive of "
                    "one (docs/recipes/make_gpu_assets.py); default procedural")
    ap.add_argument("--val-pack", default=None, help="a carried validation set (`python -m networks.datapack pack`) "
                    "used instead of rendering one")
    ap.add_argument("--seed-base", type=int, default=2000, help="a machine first used in call M renders seed BASE+M")
    ap.add_argument("--max-scenes", type=int, default=100000, help="scenes per machine at most")
    ap.add_argument("--render-procs", type=int, default=0, help="render processes (0: 4 on CUDA, else the cores "
                    "left after --train-cores)")
    ap.add_argument("--train-cores", type=int, default=4, help="cores kept for the trainers on a CPU variant")
    ap.add_argument("--val-scenes", type=int, default=32)
    ap.add_argument("--min-scenes", type=int, default=16, help="training starts once this many scenes exist")
    ap.add_argument("--rescan-s", type=float, default=60.0)
    ap.add_argument("--poll-s", type=float, default=30.0)
    ap.add_argument("--margin", type=float, default=45.0, help="seconds kept for stopping and the export")
    ap.add_argument("--grace", type=float, default=0.0, help="seconds past the deadline a run that has not trained "
                    "a step yet may take (default 0; the dry run 120)")
    ap.add_argument("--init-normal", default=str(REPO / "networks/weights/normal_small.safetensors"))
    ap.add_argument("--init-brdf", default=str(REPO / "networks/weights/brdf_small.safetensors"))
    # training settings (the GPU recipe's; --dry-run replaces them)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--data-version", type=int, default=2, choices=(1, 2),
                    help="scene generator version of the rendered sets (`matcap synth --data-version`)")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--pixel-samples", type=int, default=2048)
    ap.add_argument("--max-images", type=int, default=6)
    ap.add_argument("--lr", type=float, default=2.5e-4)
    ap.add_argument("--warmup", type=int, default=100)
    ap.add_argument("--decay-every", type=int, default=2500)
    ap.add_argument("--steps", type=int, default=200000)
    ap.add_argument("--val-every-s", type=float, default=60.0)
    ap.add_argument("--checkpoint-every-s", type=float, default=60.0)
    ap.add_argument("--workers", type=int, default=5, help="data workers per run")
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--log-every", type=int, default=10)
    ap.add_argument("--device", default=None, help="cuda where torch sees a GPU, else cpu")
    ap.add_argument("--no-bf16", dest="bf16", action="store_false")
    # the render worker (internal)
    ap.add_argument("--render-worker", action="store_true", help=argparse.SUPPRESS)
    for name, kind in (("out", str), ("seed", int), ("scenes", int), ("split", str), ("shard", str), ("threads", int)):
        ap.add_argument(f"--render-{name}", type=kind, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    if a.render_worker:
        return render_worker(a)
    if a.dry_run:
        a.preset, a.resolution, a.spp, a.batch, a.pixel_samples, a.max_images = "tiny", 32, 1, 1, 64, 3
        a.val_scenes, a.min_scenes, a.warmup, a.workers, a.threads, a.log_every = min(a.val_scenes, 1), 1, 2, 0, 1, 1
        a.render_procs = a.render_procs or 1
        a.rescan_s, a.poll_s, a.margin, a.grace = 1.0, min(a.poll_s, 2.0), min(a.margin, 1.0), a.grace or 120.0
        a.val_every_s, a.checkpoint_every_s, a.bf16 = 3.0, 1e9, False  # the checkpoint: when stopped
        a.device = a.device or "cpu"
    if a.device is None:
        import torch

        a.device = "cuda" if torch.cuda.is_available() else "cpu"
    if a.device == "cpu":
        a.bf16 = a.bf16 and not a.dry_run
    return Call(a).run()


if __name__ == "__main__":
    sys.exit(main())
