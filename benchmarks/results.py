"""Re-measure every published number and rewrite the results table.

    python benchmarks/results.py                       # everything: docs/results.md
    python benchmarks/results.py --quick --out FILE    # a small subset in a few minutes, written to FILE
    python benchmarks/results.py --only uw_normals,bunny_speed   # some rows (the others keep their last numbers
                                                                 # only if they are cached in --work)

Each row runs the project's own commands (`matcap ...`, `python benchmarks/...`, `python -m networks.validate`) as
subprocesses of this checkout (PYTHONPATH is set to the repository root), reads their output (JSON where the
command writes it, else its Markdown table) and records the command, its wall time, its peak memory (the child's
``ru_maxrss`` from ``os.wait4``), the date and the machine. Outputs are cached in the work folder (``--work``,
default ``$TMPDIR/matcap-results``): a re-run skips every command that already finished with the same command
line, so an interrupted run resumes where it stopped (``--fresh`` re-measures everything).

The rows are written between ``<!-- results:start -->`` and ``<!-- results:end -->`` of ``--out`` (default
docs/results.md; a new file is created with the markers), and, where ``--readme FILE`` is given, a table of the
summary rows (at most 8) between ``<!-- results-summary:start -->`` and ``<!-- results-summary:end -->`` of FILE.
The project's README.md has its own summary, each number with the command that gives it: it is not rewritten.

Rows that need ``../shared/data`` (the UW and ToyPS captures, the held-out assets of the synthetic test split,
textures and environment maps of the rendered domes) say so, and are skipped with that reason when it is missing.
The synthetic test split is rendered into the work folder (``matcap synth --split test``) unless ``--data-test``
names an existing one.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import hashlib
import json
import os
import platform
import re
import shlex
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
START, END = "<!-- results:start -->", "<!-- results:end -->"
SUM_START, SUM_END = "<!-- results-summary:start -->", "<!-- results-summary:end -->"
UW = "uw_buddha,uw_cat,uw_gray,uw_horse,uw_owl,uw_rock"  # the UW captures without the mirror sphere
UW_ALL = "uw_buddha,uw_cat,uw_chrome,uw_gray,uw_horse,uw_owl,uw_rock"
SYNTH_TEST = ["--scenes", "48", "--resolution", "128", "--seed", "7"]  # the published test split
SYNTH_QUICK = ["--scenes", "4", "--resolution", "128", "--seed", "7"]  # the networks take multiples of 128


# ----------------------------------------------------------------------------------------------- running commands
@dataclass
class Run:
    """One finished command: its output and what it cost."""
    argv: list[str]
    shown: str
    rc: int
    stdout: str
    stderr: str
    wall_s: float
    cpu_s: float
    peak_rss_mb: float
    date: str
    machine: str
    files: dict = field(default_factory=dict)  # JSON files the command wrote, read back


def machine() -> str:
    """CPU model and core count of this machine, e.g. 'AMD EPYC 9R14, 2 cores'."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} cores"


class Runner:
    """Runs commands of this checkout in subprocesses, caching each finished one in ``work``."""

    def __init__(self, work: Path, shown_paths: dict[str, str], fresh: bool = False):
        self.work = work
        self.shown_paths = shown_paths  # real path -> how a command shows it
        self.fresh = fresh
        self.cache_only = False  # rows outside --only: their cached outputs, or nothing
        (work / "runs").mkdir(parents=True, exist_ok=True)

    def show(self, argv: list[str]) -> str:
        """The command as a user types it: `matcap ...` for `python -m matcap`, paths as the user knows them."""
        words = list(argv)
        if words[:3] == [sys.executable, "-m", "matcap"]:
            words = ["matcap"] + words[3:]
        elif words[0] == sys.executable:
            words = ["python"] + words[1:]
        text = " ".join(shlex.quote(w) for w in words)
        for real, shown in sorted(self.shown_paths.items(), key=lambda kv: -len(kv[0])):
            text = text.replace(real, shown)
        return text

    def run(self, argv: list[str], json_files: tuple[str, ...] = (), label: str = "") -> Run:
        argv = [str(a) for a in argv]
        key = hashlib.sha1("\0".join(argv).encode()).hexdigest()[:16]
        cache = self.work / "runs" / f"{key}.json"
        shown = self.show(argv)
        if cache.exists() and (not self.fresh or self.cache_only):
            data = json.loads(cache.read_text())
            if data["rc"] == 0:
                print(f"  cached ({data['date']}): {shown}", flush=True)
                return Run(**data)
        if self.cache_only:
            raise NotCached("not measured in this run")
        print(f"  running: {shown}", flush=True)
        env = dict(os.environ)
        env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        env.setdefault("TQDM_DISABLE", "1")
        out_path, err_path = self.work / "runs" / f"{key}.out", self.work / "runs" / f"{key}.err"
        load = os.getloadavg()[0]
        t0 = time.perf_counter()
        with open(out_path, "w") as out, open(err_path, "w") as err:
            proc = subprocess.Popen(argv, cwd=REPO, env=env, stdout=out, stderr=err)
            try:
                _, status, usage = os.wait4(proc.pid, 0)
            except BaseException:
                proc.kill()
                proc.wait()
                raise
            proc.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t0
        files = {}
        for f in json_files:
            try:
                files[f] = json.loads(Path(f).read_text())
            except (OSError, ValueError):
                pass
        run = Run(argv=argv, shown=shown, rc=proc.returncode, stdout=out_path.read_text(),
                  stderr=err_path.read_text()[-4000:], wall_s=wall, cpu_s=usage.ru_utime + usage.ru_stime,
                  peak_rss_mb=usage.ru_maxrss / 1024, date=_dt.date.today().isoformat(),
                  machine=f"{machine()}, load {load:.1f}", files=files)
        cache.write_text(json.dumps(run.__dict__))
        state = "done" if run.rc == 0 else f"FAILED (exit {run.rc}; see {err_path})"
        print(f"  {state} in {wall:.0f} s, peak {run.peak_rss_mb:.0f} MB", flush=True)
        return run


class RowFailed(Exception):
    pass


class NotCached(RowFailed):
    """A row outside ``--only`` whose commands have not run yet in this work folder."""


def ok(run: Run) -> Run:
    if run.rc != 0:
        last = (run.stderr.strip().splitlines() or ["no output"])[-1]
        raise RowFailed(f"`{run.shown}` failed (exit {run.rc}): {last[:200]}")
    return run


ANSI = re.compile(r"\x1b\[[0-9;]*m")
#: a log line of Mitsuba (written to standard output, possibly between a table's rows): not part of the output
LOG_LINE = re.compile(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\s+(TRACE|DEBUG|INFO|WARN|ERROR)\b")


def tables(text: str) -> list[list[list[str]]]:
    """Markdown tables in ``text``: a list of tables, each a list of rows (header first), each a list of cells.
    Colour codes are dropped and log lines skipped, so a renderer's warnings between rows do not split a table."""
    out, cur = [], None
    for line in text.splitlines():
        line = ANSI.sub("", line).strip()
        if LOG_LINE.match(line):
            continue
        if line.startswith("|") and line.endswith("|"):
            cells = [c.strip() for c in line[1:-1].split("|")]
            if all(re.fullmatch(r":?-+:?", c) for c in cells):
                continue
            if cur is None:
                cur = []
                out.append(cur)
            cur.append(cells)
        else:
            cur = None
    return out


def num(cell: str) -> float:
    m = re.search(r"-?\d+(?:\.\d+)?", cell.replace(",", ""))
    if not m:
        raise RowFailed(f"no number in {cell!r}")
    return float(m.group())


def row_by(table: list[list[str]], first: str) -> list[str]:
    """The row of ``table`` whose first cell starts with ``first``."""
    for r in table[1:]:
        if r[0].strip("* ").startswith(first):
            return r
    raise RowFailed(f"no row {first!r} in the table")


def deg(v: float) -> str:
    return f"{v:.2f}°"


# ----------------------------------------------------------------------------------------------- the rows
@dataclass
class Row:
    key: str
    section: str
    what: str
    measure: Callable  # (ctx) -> (value, comparison, [Run, ...])
    shared: bool = False  # needs ../shared/data
    quick: bool = False  # part of --quick
    summary: str = ""  # the row's label in the summary table of --readme ("" = not in it)
    quick_what: str = ""  # what the row measures under --quick, where that differs


@dataclass
class Ctx:
    runner: Runner
    quick: bool
    work: Path
    data_test: Path | None
    has_shared: bool

    @property
    def py(self) -> list[str]:
        return [sys.executable]

    @property
    def matcap(self) -> list[str]:
        return [sys.executable, "-m", "matcap"]

    def run(self, argv, json_files=()):
        return ok(self.runner.run(argv, tuple(str(f) for f in json_files)))

    def test_split(self) -> Path:
        """The synthetic test split: --data-test, else rendered into the work folder (needs the shared assets)."""
        if self.data_test is not None:
            return self.data_test
        path = self.work / ("DATA_TEST_quick" if self.quick else "DATA_TEST")
        spec = SYNTH_QUICK if self.quick else SYNTH_TEST
        if not (path / "manifest.json").exists() or (self.runner.fresh and not self.runner.cache_only):
            self.run(self.matcap + ["synth", "--out", path, *spec, "--assets", SHARED, "--split", "test", "--quiet"])
        self.data_test = path
        return path

    def scenes(self, split: Path, n: int | None) -> list[str]:
        names = sorted(p.name for p in split.iterdir() if p.name.startswith("scene_"))
        return names if n is None else names[:n]


def _eval(ctx: Ctx, name: str, dataset, args: list[str]) -> Run:
    out = ctx.work / f"eval-{name}.json"
    return ctx.run(ctx.matcap + ["eval", dataset, *args, "--json", out, "--overwrite", "--quiet"], [out])


def _group(run: Run, group: str = "all") -> dict:
    report = next(iter(run.files.values()), None)
    if report is None:
        raise RowFailed(f"`{run.shown}` wrote no JSON")
    groups = report["groups"]
    if group not in groups:
        group = next(iter(groups))  # one group only: no "all" row
    return groups[group]


def synthetic_normals(ctx: Ctx):
    split = ctx.test_split()
    sel = ["--objects", ",".join(ctx.scenes(split, 4))] if ctx.quick else []
    net = _eval(ctx, "syn-net" + ("-q" if ctx.quick else ""), split, ["--method", "sdm-unips", *sel])
    flat = _eval(ctx, "syn-flat" + ("-q" if ctx.quick else ""), split, ["--method", "flat", *sel])
    ls = _eval(ctx, "syn-lsr" + ("-q" if ctx.quick else ""), split, ["--method", "least-squares-robust", *sel])
    report = ls.files and next(iter(ls.files.values()))
    ok_rows = [r for r in report["objects"] if r.get("status") == "ok"]
    names = {r["object"] for r in ok_rows}
    net_rows = [r for r in next(iter(net.files.values()))["objects"] if r["object"] in names]
    n = len(_scenes_in(net))
    value = f"**{deg(_group(net)['mae'])}** ({n} scenes)"
    comp = f"every normal facing the camera: {deg(_group(flat)['mae'])}"
    if ok_rows:
        comp += (f"; least squares given the lights (robust), the {len(ok_rows)} directional-light scenes: "
                 f"{deg(sum(r['mae'] for r in ok_rows) / len(ok_rows))} (network on them: "
                 f"{deg(sum(r['mae'] for r in net_rows) / len(net_rows))})")
    return value, comp, [net, flat, ls]


def _scenes_in(run: Run) -> list[dict]:
    return [r for r in next(iter(run.files.values()))["objects"] if r.get("status") == "ok"]


def brdf_rmse(ctx: Ctx):
    split = ctx.test_split()
    out = ctx.work / ("validate-brdf-q.json" if ctx.quick else "validate-brdf.json")
    run = ctx.run([*ctx.py, "-m", "networks.validate", "networks/weights/brdf_small.safetensors", split,
                   *(["--scenes", "2"] if ctx.quick else []), "--json", out], [out])
    r = run.files[str(out)]
    keys = ("base_color", "roughness", "metallic")
    value = " / ".join(f"{r['rmse_' + k]:.3f}" for k in keys) + f" ({r['scenes']} scenes)"
    comp = "best constant per map: " + " / ".join(f"{r['rmse_const_' + k]:.3f}" for k in keys)
    return value, comp, [run]


def sphere_normals(ctx: Ctx):
    run = ctx.run([*ctx.py, "benchmarks/sphere_check.py", "--capture", SHARED / "captures" / "toyps_sphere",
                   "--views", "1"])
    t = tables(run.stdout)[0]
    lin = num(row_by(t, "linear input")[1])
    return (f"**{deg(lin)}** (`--linear`)", f"every normal facing the camera: {deg(num(row_by(t, 'flat')[1]))}; "
            f"the same photos decoded as sRGB: {deg(num(row_by(t, 'sRGB')[1]))}", [run])


def uw_normals(ctx: Ctx):
    caps = SHARED / "captures"
    objs = "uw_cat" if ctx.quick else UW_ALL
    size = ["--max-side", "128"] if ctx.quick else []
    q = "-q" if ctx.quick else ""
    lin = _eval(ctx, "uw-lin" + q, caps, ["--objects", objs, "--method", "sdm-unips", "--reference",
                                          "least-squares", "--linear", *size])
    runs = [lin]
    comp = []
    if not ctx.quick:
        srgb = _eval(ctx, "uw-srgb", caps, ["--objects", objs, "--method", "sdm-unips", "--reference",
                                             "least-squares"])
        runs.append(srgb)
        comp.append(f"photos decoded as sRGB: {deg(_group(srgb)['mae'])}")
    flat = _eval(ctx, "uw-flat" + q, caps, ["--objects", objs, "--method", "flat", "--reference", "least-squares"])
    runs.append(flat)
    comp.insert(0, f"every normal facing the camera: {deg(_group(flat)['mae'])}")
    n = len(_scenes_in(lin))
    return f"**{deg(_group(lin)['mae'])}** ({n} capture{'s' * (n > 1)})", "; ".join(comp), runs


def uw_baselines(ctx: Ctx):
    objs = "uw_cat" if ctx.quick else UW
    run = _eval(ctx, "uw-ls" + ("-q" if ctx.quick else ""), SHARED / "captures",
                ["--objects", objs, "--method", "least-squares-robust", "--reference", "least-squares"])
    g = _group(run)
    return (deg(g["mae"]), f"median {deg(g['median'])}; {g['under10']:.0%} of pixels under 10°; "
            f"{g['seconds']:.2f} s per capture", [run])


def bunny_speed(ctx: Ctx):
    out = ctx.work / ("bunny-quick" if ctx.quick else "bunny")
    small = ["--max-side", "128", "--max-images", "16"] if ctx.quick else []
    run = ctx.run(ctx.matcap + ["capture", "examples/bunny", "--linear", *small, "--out", out, "--overwrite",
                                "--quiet"], [out / "capture.json"])
    cap = run.files.get(str(out / "capture.json"))
    if cap is None:
        raise RowFailed("no capture.json")
    t = cap["timings"]
    w, h = cap["image_size_wh"]
    value = f"**{run.wall_s:.1f} s**, peak {run.peak_rss_mb / 1024:.2f} GB ({len(cap['images_used'])} photos, {w}×{h})"
    comp = (f"normal network {t['normal_s']:.1f} s, BRDF network {t['brdf_s']:.1f} s, the fit "
            f"{t.get('refine_s', 0.0):.1f} s; {run.cpu_s:.0f} CPU s")
    return value, comp, [run]


def relight_speed(ctx: Ctx):
    if ctx.quick:
        maps = ctx.work / "bunny-quick"
        if not (maps / "capture.json").exists():
            bunny_speed(ctx)
        args = ["--texture-set", maps, "--size", "256", "--spp", "16", "--repeat", "1", "--ref-spp", "64"]
    else:
        args = ["--spp", "16", "--repeat", "2"]
    run = ctx.run([*ctx.py, "benchmarks/bench_relight.py", *args])
    t = tables(run.stdout)[0]
    r = row_by(t, "16")
    side = 256 if ctx.quick else 1024
    return (f"**{num(r[1]):.2f} s** per {side}² frame", f"noise against 512 spp: {num(r[2]):.3f} relative RMSE, "
            f"{num(r[3]):.2f} 8-bit levels; peak {run.peak_rss_mb / 1024:.2f} GB", [run])


def network_speed(ctx: Ctx):
    out = ctx.work / ("bench-speed-q.json" if ctx.quick else "bench-speed.json")
    size = ["--side", "256", "--k", "4"] if ctx.quick else []
    run = ctx.run([*ctx.py, "benchmarks/bench_speed.py", "--presets", "small", "--dtypes", "fp32", *size,
                   "--no-old", "--threads", "2", "--json", out], [out])
    r = run.files[str(out)]["small"]["fp32-new"]
    wall, cpu = r["total"]
    return (f"**{wall:.1f} s**, peak {r['peak_rss_mb'] / 1024:.2f} GB",
            f"encoder {r['encoder'][0]:.1f} s, decoder {r['decoder'][0]:.1f} s; {cpu:.0f} CPU s", [run])


def large_speed(ctx: Ctx):
    out = ctx.work / "bench-large.json"
    run = ctx.run([*ctx.py, "benchmarks/bench_speed.py", "--large", "small", "--tiles", "1", "--no-old",
                   "--threads", "2", "--json", out], [out])
    r = run.files[str(out)]["large"]
    return (f"peak **{r['peak_rss_mb'] / 1024:.2f} GB**",
            f"one tile of 16: {r['wall_s']:.0f} s; the whole image extrapolated from it: {r['wall_full_s']:.0f} s",
            [run])


def synth_speed(ctx: Ctx):
    out = ctx.work / ("synth-speed-q" if ctx.quick else "synth-speed")
    n, side = (2, 64) if ctx.quick else (8, 256)
    run = ctx.run(ctx.matcap + ["synth", "--out", out, "--scenes", n, "--resolution", side, "--seed", "123",
                                "--split", "train", "--quiet"])
    return (f"**{3600 * n / run.wall_s:.0f} scenes/h** ({n} scenes at {side}², 10 images each)",
            f"{run.cpu_s / n:.1f} CPU s per scene, first scene's start-up included", [run])


def fit_timing(ctx: Ctx):
    side = "128" if ctx.quick else "512"
    plain = ctx.run([*ctx.py, "benchmarks/refine_check.py", "timing", "--side", side, "--threads", "2"])
    runs = [plain]
    r = tables(plain.stdout)[0][1]
    value = f"**{num(r[1]):.1f} s**, peak {num(r[2]) / 1024:.2f} GB"
    comp = ""
    if not ctx.quick:
        glossy = ctx.run([*ctx.py, "benchmarks/refine_check.py", "timing", "--side", side, "--threads", "2",
                          "--glossy"])
        g = tables(glossy.stdout)[0][1]
        runs.append(glossy)
        comp = f"a glossy capture (every look of the fit runs): {num(g[1]):.1f} s, {num(g[2]) / 1024:.2f} GB"
    return value, comp, runs


def _mean_row(run: Run) -> list[str]:
    t = tables(run.stdout)[0]
    return row_by(t, "mean")


def refine_uw(ctx: Ctx, side: int):
    objs = ["--objects", "cat"] if ctx.quick else []
    run = ctx.run([*ctx.py, "benchmarks/refine_check.py", "uw", "--max-side", side, *objs, "--threads", "1"])
    t = tables(run.stdout)[0]
    m = row_by(t, "mean") if len(t) > 2 else t[1]
    lights = [num(r[3]) for r in t[1:] if not r[0].startswith("**")]
    spread = f"{min(lights):.1f}°" if len(lights) == 1 else f"{min(lights):.1f}-{max(lights):.1f}° per capture"
    comp = (f"lights found vs the calibrated ones: median {spread}; "
            f"re-render {num(m[5]):.1f} dB, a held-out photo {num(m[6]):.1f} dB; the fit {num(m[7]):.0f} s per capture")
    return f"{deg(num(m[1]))} → **{deg(num(m[2]))}**", comp, [run]


def refine_uw_known(ctx: Ctx, source: str):
    """UW at 160 px with lights given: each capture's ``lights.txt`` ("txt"), or the rig that ``matcap calibrate``
    finds from the chrome ball of ``uw_chrome`` ("ball")."""
    runs = []
    lights = "txt"
    if source == "ball":
        rig = ctx.work / "uw_rig.json"
        runs.append(ctx.run(ctx.matcap + ["calibrate", SHARED / "captures" / "uw_chrome", "--out", rig,
                                          "--overwrite", "--quiet"]))
        lights = str(rig)
    objs = ["--objects", "cat"] if ctx.quick else []
    run = ctx.run([*ctx.py, "benchmarks/refine_check.py", "uw", "--max-side", 128 if ctx.quick else 160, *objs,
                   "--threads", "1", "--lights", lights])
    runs.append(run)
    t = tables(run.stdout)[0]
    m = row_by(t, "mean") if len(t) > 2 else t[1]
    comp = f"re-render {num(m[5]):.1f} dB; the fit {num(m[7]):.0f} s per capture"
    if source == "ball":
        comp = f"the ball's light directions vs lights.txt: median {num(m[3]):.2f}°, max {num(m[4]):.2f}°; " + comp
    return f"{deg(num(m[1]))} → **{deg(num(m[2]))}**", comp, runs


def refine_synthetic_known(ctx: Ctx):
    split = ctx.test_split()
    n = 6 if ctx.quick else len(ctx.scenes(split, None))
    run = ctx.run([*ctx.py, "benchmarks/refine_check.py", "synthetic", "--data", split, "--scenes", n,
                   "--threads", "1", "--given-lights", "--given-only"])
    t = tables(run.stdout)[0]
    m = row_by(t, "mean, lights given")
    parts = re.search(r"normals of the (\d+) scenes with a backdrop, scene means: objects ([\d.]+) -> ([\d.]+) deg, "
                      r"backdrop ([\d.]+) -> ([\d.]+) deg", run.stdout)
    apart = "" if parts is None else (
        f"; the {parts[1]} scenes with a backdrop: objects {deg(float(parts[2]))} → {deg(float(parts[3]))}, "
        f"backdrop {deg(float(parts[4]))} → {deg(float(parts[5]))}")
    return (f"{deg(num(m[2]))} → **{deg(num(m[3]))}** ({m[-1].strip()})",
            f"roughness RMSE {num(m[6]):.3f} → {num(m[7]):.3f}, metallic {num(m[8]):.3f} → {num(m[9]):.3f}{apart}",
            [run])


def refine_sphere(ctx: Ctx):
    run = ctx.run([*ctx.py, "benchmarks/refine_check.py", "sphere", "--capture", SHARED / "captures" /
                   "toyps_sphere", "--threads", "1"])
    t = tables(run.stdout)[0]
    a, b = row_by(t, "network + refine"), row_by(t, "network")
    kept = "maps kept" if a[5].endswith("kept") else "maps fitted"
    return f"{deg(num(b[1]))} → {deg(num(a[1]))} ({kept})", f"re-render {num(a[3]):.1f} dB", [run]


def refine_synthetic(ctx: Ctx):
    split = ctx.test_split()
    n = 2 if ctx.quick else len(ctx.scenes(split, None))
    run = ctx.run([*ctx.py, "benchmarks/refine_check.py", "synthetic", "--data", split, "--scenes", n,
                   "--threads", "1"])
    t = tables(run.stdout)[0]
    m = row_by(t, "mean")
    body = [r for r in t[1:] if not r[0].startswith("**")]
    fitted = [r for r in body if r[-1].endswith("fitted")]
    detail = ", ".join(f"{num(r[2]):.1f}° → {num(r[3]):.1f}°" for r in fitted[:4])
    return (f"{deg(num(m[2]))} → **{deg(num(m[3]))}** ({len(body)} scenes)",
            f"fits {len(fitted)} scene{'s' * (len(fitted) != 1)}" + (f" ({detail})" if detail else "")
            + f", keeps {len(body) - len(fitted)}", [run])


def _dome_cells(run: Run, with_light: bool = True) -> list[str]:
    out = []
    for r in tables(run.stdout)[0][1:]:
        kept = r[4] == "kept"
        cell = f"{r[0]}: {deg(num(r[1]))} → " + (f"{deg(num(r[2]))} (kept)" if kept else f"**{deg(num(r[2]))}**")
        if with_light and not kept and r[3] != "-":
            cell += f", lights {num(r[3]):.1f}° off"
        out.append(cell)
    return out


def refine_dome(ctx: Ctx):
    run = ctx.run([*ctx.py, "benchmarks/refine_check.py", "dome", "--threads", "1", "--roughness",
                   "0.25,0.4,0.6,0.9"])
    return "; ".join(_dome_cells(run, False)), "; ".join(_dome_cells(run)), [run]


def refine_dome_near(ctx: Ctx):
    runs, cells = [], []
    for d in ("3", "6", "10"):
        run = ctx.run([*ctx.py, "benchmarks/refine_check.py", "dome", "--side", "128", "--dome-light", "point",
                       "--lamp-distance", d, "--roughness", "0.4,0.9", "--threads", "1"])
        runs.append(run)
        cells.append(f"lamps at {d}: " + ", ".join(_dome_cells(run, False)))
    return "; ".join(cells), "roughness: network → fit, normals vs the truth", runs


def refine_dome_room(ctx: Ctx):
    base = [*ctx.py, "benchmarks/refine_check.py", "dome", "--side", "128", "--dome-light", "dir+env",
            "--roughness", "0.4,0.9", "--threads", "1"]
    fixed = ctx.run(base + ["--env-fixed"])
    turning = ctx.run(base)
    lamp_off = ctx.run(base + ["--env-fixed", "--lamp-off"])
    return ("; ".join(_dome_cells(fixed, False)),
            "the map turning between photos instead: " + "; ".join(_dome_cells(turning, False))
            + "; the fixed map with a lamp-off photo subtracted (`--lamp-off`): "
            + "; ".join(_dome_cells(lamp_off, False)),
            [fixed, turning, lamp_off])


def refine_detail(ctx: Ctx):
    run = ctx.run([*ctx.py, "benchmarks/refine_check.py", "detail", "--threads", "2", "--crops",
                   ctx.work / "detail_crops.png"])
    rows = tables(run.stdout)[0][1:]
    value = "; ".join(f"{r[0]}: {deg(num(r[1]))} → **{deg(num(r[2]))}**" for r in rows)
    comp = "correlation of the fine detail with the truth's: " + "; ".join(f"{r[0]}: {r[4]}" for r in rows)
    return value, comp, [run]


def refine_samples(ctx: Ctx):
    run = ctx.run([*ctx.py, "benchmarks/refine_check.py", "samples", "--threads", "1"])
    rows = tables(run.stdout)[0][1:]
    shown = [r for r in rows if not r[0].startswith("bumpy plane 192^2, heights")]  # the wood and the planes' mean
    value = "; ".join(f"{r[0]}: {deg(num(r[2]))} → {deg(num(r[3]))}" for r in shown)
    chose = shown[-1][6].removeprefix("truth ")
    comp = ("every normal facing the camera: " + "; ".join(f"{r[0]} {deg(num(r[1]))}" for r in shown)
            + f"; the fit chose the bumpy planes' true reading, not their twin's: {chose}")
    return value, comp, [run]


ACC, SPEED, FIT = "Accuracy of the networks", "Speed and memory", "The fit of the photos (network → fit)"
ROWS = [
    Row("synthetic_normals", ACC, "normal error, synthetic test split (128²), lights unknown: mean angle",
        synthetic_normals, shared=True, quick=True, summary="normal error, synthetic test split",
        quick_what="normal error, first 4 scenes of the synthetic test split"),
    Row("brdf_rmse", ACC, "BRDF RMSE base color / roughness / metallic, synthetic test split", brdf_rmse,
        shared=True, quick=True, summary="BRDF RMSE base color / roughness / metallic, synthetic"),
    Row("sphere_normals", ACC, "normal error, ToyPS sphere (truth from its silhouette), 50 photos",
        sphere_normals, shared=True, quick=True, summary="normal error, ToyPS sphere"),
    Row("uw_normals", ACC, "normals vs calibrated least squares, real UW captures (mean angle)", uw_normals,
        shared=True, quick=True, summary="normals vs calibrated least squares, real UW captures",
        quick_what="normals vs calibrated least squares, UW cat at 128 px"),
    Row("uw_baselines", ACC, "robust vs plain least squares, both given the lights, UW captures without chrome",
        uw_baselines, shared=True, quick=True, quick_what="robust vs plain least squares, UW cat"),
    Row("bunny_speed", SPEED, "`examples/bunny` end to end: both networks and the fit", bunny_speed, quick=True,
        summary="`examples/bunny` end to end"),
    Row("network_speed", SPEED, "normal network `small`, 512², 16 photos, fp32, 2 threads", network_speed,
        quick=True, quick_what="normal network `small`, 256², 4 photos, fp32, 2 threads"),
    Row("large_memory", SPEED, "normal network `small`, 2048², 16 photos (16 tiles of 512²), 2 threads",
        large_speed),
    Row("fit_timing", SPEED, "the fit at 512², 16 photos, 2 threads", fit_timing,
        summary="the fit at 512², 16 photos"),
    Row("relight_speed", SPEED, "relight one frame under an environment map, 16 spp", relight_speed, quick=True,
        summary="relight one 1024² frame, 16 spp"),
    Row("synth_speed", SPEED, "synthetic training scenes (`matcap synth`, procedural assets)", synth_speed,
        quick=True),
    Row("refine_uw160", FIT, "real UW captures without chrome, 160 px: normals vs calibrated least squares",
        lambda c: refine_uw(c, 128 if c.quick else 160), shared=True, quick=True,
        quick_what="real UW cat, 128 px: normals vs calibrated least squares",
        summary="real UW captures, network → fit, vs calibrated least squares"),
    Row("refine_uw512", FIT, "the same at full size (512 × 340)", lambda c: refine_uw(c, 512), shared=True),
    Row("refine_uw_txt", FIT, "the UW captures at 160 px with their lights.txt given (--lights)",
        lambda c: refine_uw_known(c, "txt"), shared=True),
    Row("refine_uw_ball", FIT, "the UW captures at 160 px with the lights of `matcap calibrate uw_chrome`",
        lambda c: refine_uw_known(c, "ball"), shared=True),
    Row("refine_synthetic_known", FIT, "synthetic test split, directional scenes given their true lights",
        refine_synthetic_known, shared=True),
    Row("refine_sphere", FIT, "ToyPS sphere, 16 photos: normals vs the truth", refine_sphere, shared=True),
    Row("refine_synthetic", FIT, "synthetic test split: normals vs the truth", refine_synthetic, shared=True,
        quick=True),
    Row("refine_dome", FIT, "a rendered textured dome, 256², 16 distant lamps; by roughness", refine_dome,
        shared=True),
    Row("refine_dome_near", FIT, "the dome at 128², a lamp 3 / 6 / 10 half-widths away; roughness 0.4, 0.9",
        refine_dome_near, shared=True),
    Row("refine_dome_room", FIT, "the dome at 128², 16 lamps plus a fixed room light (environment map at 0.3)",
        refine_dome_room, shared=True),
    Row("refine_detail", FIT, "fine detail: the dome carrying a CC0 normal map's relief, 256²", refine_detail,
        shared=True),
    Row("refine_samples", FIT, "material samples filling the frame (flat wood, 6 bumpy planes), 12 lamps",
        refine_samples, shared=True),
]


# ----------------------------------------------------------------------------------------------- writing
def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def previous_rows(path: Path) -> dict[str, str]:
    """The measured lines already between the markers of ``path``, by their first cell (the row's label). A line
    written when the page named one machine for all its rows (its header: "Generated by ... on MACHINE.") and its
    *measured* cell only the cores gets that machine in the cell, so that it keeps it beside rows measured
    elsewhere."""
    try:
        text = path.read_text()
    except OSError:
        return {}
    if START not in text or END not in text:
        return {}
    block = text.split(START, 1)[1].split(END, 1)[0]
    header = re.search(r"^Generated by `[^`]*` on (.+), \d+ cores\.$", block, re.M)
    rows = {}
    for line in block.splitlines():
        cells = line.split(" | ")
        if line.startswith("| ") and len(cells) > 2 and not cells[1].startswith("not measured"):
            if header and len(cells) > 3:
                cells[3] = re.sub(r"^((?:20\d\d-\d\d-\d\d, )+)(\d+ cores)",
                                  lambda m: f"{m[1]}{header[1]}, {m[2]}", cells[3])
                line = " | ".join(cells)
            rows[cells[0][2:]] = line
    return rows


def render_table(results: list[tuple[Row, dict]], quick: bool, mach: str, given: bool = False) -> str:
    lines = [f"Generated by `python benchmarks/results.py{' --quick' if quick else ''}`; each row's *measured* "
             f"column gives its date and machine (this run: {mach})."]
    lines += ["This is the quick subset: smaller inputs, as each row says."] if quick else []
    lines += [
             "`WORK` is its work folder (`--work`). `DATA_TEST` is the synthetic test split"
             + (" given with `--data-test`; the published one is:" if given else ":"),
             f"`matcap synth --out DATA_TEST {' '.join(SYNTH_QUICK if quick and not given else SYNTH_TEST)} "
             "--assets ../shared/data --split test`.",
             "Rows marked *shared* need `../shared/data`. Times are wall seconds, with the machine's load average",
             "when the command started (other jobs running on it slow every time down)."]
    section = None
    for row, res in results:
        if row.section != section:
            section = row.section
            lines += ["", f"### {section}", "", "| what | value | for comparison | measured | command |",
                      "|---|---|---|---|---|"]
        what = ((quick and row.quick_what) or row.what) + (" *(shared)*" if row.shared else "")
        if "line" in res:  # measured by an earlier run whose outputs are not in the cache: kept as it was
            lines.append(res["line"])
            continue
        if "error" in res:
            lines.append(f"| {_cell(what)} | {_cell(res['error'])} | | | |")
            continue
        cmds = "<br>".join(f"`{_cell(c)}`" for c in res["commands"])
        lines.append(f"| {_cell(what)} | {_cell(res['value'])} | {_cell(res['comparison'])} | "
                     f"{res['measured']} | {cmds} |")
    return "\n".join(lines).strip() + "\n"


def render_summary(results: list[tuple[Row, dict]], link: str) -> str:
    lines = ["| what | value | for comparison |", "|---|---|---|"]
    for row, res in results:
        if row.summary and "error" not in res:
            first = res["comparison"].split("; ")[0]  # the full comparison is in the results page
            value = res["value"] if "line" in res else _cell(res["value"])  # a kept line is escaped already
            lines.append(f"| {_cell(row.summary)} | {value} | {first if 'line' in res else _cell(first)} |")
    lines += ["", f"Each number with its command, date and machine, and more rows: [{Path(link).name}]({link})."]
    return "\n".join(lines) + "\n"


def replace_between(path: Path, start: str, end: str, body: str, new_file: str = "") -> None:
    text = path.read_text() if path.exists() else new_file + f"{start}\n{end}\n"
    if start not in text or end not in text:
        raise SystemExit(f"results: {path} has no {start} ... {end} markers")
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(f"{head}{start}\n{body}{end}{tail}")
    os.replace(tmp, path)


NEW_DOC = """# Results

Every number on this page is measured by `python benchmarks/results.py` on the checkout it lives in. Each row
runs the commands in its last column (the project's own: `matcap eval`, `matcap capture`, `matcap synth`,
`python -m networks.validate` and the scripts in `benchmarks/`), reads the numbers from their output, and records
the date, the machine and its load. Nothing between the markers is typed by hand.

```
python benchmarks/results.py                        # every row (hours on 2 cores): this page
python benchmarks/results.py --only bunny_speed     # some rows; the others come from the cache or stay as they are
python benchmarks/results.py --quick --out FILE     # a small subset in a few minutes, written to FILE (CI runs it)
python benchmarks/results.py --list                 # the rows: which are quick, which need ../shared/data
```

Finished commands are cached in the work folder (`--work`, default `matcap-results` in the system's temporary
folder), so an interrupted run resumes where it stopped; `--fresh` measures again. Rows marked *shared* need
`../shared/data` (the UW and ToyPS captures, the held-out assets of the synthetic test split, textures and
environment maps) and say so when it is missing. `--data-test DIR` uses an existing synthetic test split instead
of rendering one.

Reading the numbers: angles are mean angular errors in degrees over the object's pixels; "network → fit" is the
bundled networks' normals before and after the fit of the photos (`matcap capture` runs both by default). Times are
wall seconds on the machine named in the row, with its load average when the command started: where other jobs
share the machine, every time is longer than on an idle one. Peak memory is the command's largest resident set.

"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--quick", action="store_true", help="a small subset of every quick row (a few minutes)")
    ap.add_argument("--out", type=Path, help="the Markdown file to write (default docs/results.md)")
    ap.add_argument("--readme", type=Path,
                    help="a file whose summary markers to rewrite with a table of the summary rows")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "matcap-results",
                    help="work folder: outputs and the cache of finished commands (default %(default)s)")
    ap.add_argument("--data-test", type=Path, help="an existing synthetic test split (default: rendered in --work)")
    ap.add_argument("--only", help="comma-separated row keys (default: all rows, or the quick ones)")
    ap.add_argument("--fresh", action="store_true", help="re-measure commands cached in the work folder")
    ap.add_argument("--list", action="store_true", help="list the rows and exit")
    args = ap.parse_args(argv)
    if args.list:
        for row in ROWS:
            print(f"{row.key:20s} {'quick ' if row.quick else '      '}{'shared ' if row.shared else '       '}"
                  f"{row.what}")
        return 0
    rows = [r for r in ROWS if r.quick or not args.quick]
    keys = {r.key for r in rows}
    if args.only:
        keys = set(args.only.split(","))
        unknown = keys - {r.key for r in ROWS}
        if unknown:
            ap.error(f"unknown rows: {', '.join(sorted(unknown))} (see --list)")
    out = args.out or REPO / "docs" / "results.md"
    readme = args.readme
    work = args.work.resolve() / ("quick" if args.quick else "full")
    work.mkdir(parents=True, exist_ok=True)
    has_shared = SHARED.is_dir()
    data_test = args.data_test.resolve() if args.data_test else None
    if data_test is not None and not (data_test / "manifest.json").exists():
        ap.error(f"--data-test {data_test}: no manifest.json there")
    shown = {str(SHARED): "../shared/data", str(REPO) + "/": "", str(work): "WORK"}
    if data_test is not None:
        shown[str(data_test)] = "DATA_TEST"
    for name in ("DATA_TEST", "DATA_TEST_quick"):
        shown[str(work / name)] = "DATA_TEST"
    ctx = Ctx(Runner(work, shown, args.fresh), args.quick, work, data_test, has_shared)
    mach = machine()
    print(f"results: {len(rows)} rows, work folder {work}, {mach}; ../shared/data "
          f"{'found' if has_shared else 'missing: its rows are skipped'}", flush=True)
    t_all = time.perf_counter()
    results, failed = [], 0
    for i, row in enumerate(rows, 1):
        print(f"[{i}/{len(rows)}] {row.key}: {row.what}" + ("" if row.key in keys else " (cached only)"),
              flush=True)
        ctx.runner.cache_only = row.key not in keys
        if row.shared and not has_shared:
            res = {"error": "not measured: needs ../shared/data (not found)"}
            print("  skipped: needs ../shared/data", flush=True)
        else:
            try:
                value, comp, runs = row.measure(ctx)
                dates = sorted({r.date for r in runs})
                machines = sorted({r.machine.split(", load")[0] for r in runs})  # "MODEL, N cores"
                load = max(float(r.machine.rsplit("load ", 1)[-1]) for r in runs)
                res = {"value": value, "comparison": comp, "commands": [r.shown for r in runs],
                       "measured": f"{', '.join(dates)}, {'; '.join(machines)}, load {load:.1f}"}
                print(f"  -> {value}" + (f" | {comp}" if comp else ""), flush=True)
            except NotCached:
                res = {"error": f"not measured yet (`python benchmarks/results.py{' --quick' * args.quick} "
                                f"--only {row.key}`)", "cached_only": True}
                print("  not measured in this run", flush=True)
            except RowFailed as exc:
                failed += 1
                res = {"error": f"not measured: {exc}"}
                print(f"  FAILED: {exc}", flush=True)
        results.append((row, res))
    previous = previous_rows(out)
    for row, res in results:
        label = _cell(((args.quick and row.quick_what) or row.what) + (" *(shared)*" if row.shared else ""))
        if res.get("cached_only") and label in previous:
            cells = previous[label].split(" | ")
            res.update(line=previous[label], value=cells[1], comparison=cells[2])
            res.pop("error")
    body = render_table(results, args.quick, mach, args.data_test is not None)
    replace_between(out, START, END, body, NEW_DOC)
    print(f"wrote {out}", flush=True)
    if readme is not None:
        link = os.path.relpath(out, readme.parent) if out.resolve().is_relative_to(REPO) else str(out)
        replace_between(readme, SUM_START, SUM_END, render_summary(results, link))
        print(f"wrote the summary rows of {readme}", flush=True)
    done = sum("commands" in res for _, res in results)
    kept = sum("line" in res for _, res in results)
    print(f"results: {done} rows measured or cached, {kept} kept from {out.name}, {failed} failed, "
          f"{len(results) - done - kept - failed} not measured, in {time.perf_counter() - t_all:.0f} s")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
