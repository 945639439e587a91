"""Interrupted work loses nothing and resumes. Each case runs a real `matcap` command in a child process
that stops at a chosen point (a function patched to announce itself and wait), sends it a signal (SIGINT, SIGTERM
or SIGKILL), then checks what is left on disk and that the same command run again succeeds and leaves no strays.

| stage the run is stopped in | signals | after the stop | the same command again |
|---|---|---|---|
| capture: networks running | INT, TERM, KILL | no result folder, nothing beside it | completes |
| capture: writing the result folder | INT, TERM, KILL | no result folder; KILL leaves one hidden temporary folder | completes, temporary folder gone |
| capture: --relight renders | TERM | no result folder, nothing beside it | completes |
| capture: --export texture set | INT, KILL | no result, no texture file; KILL leaves the hidden temporary result folder and a hidden staging folder | completes, both gone |
| capture --overwrite: between its two renames | KILL | the previous result is put back by the next run | completes |
| export: writing the texture set | TERM, KILL | no texture file | completes |
| synth: rendering scenes | KILL | finished scenes kept | renders only the missing scenes |
"""
from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import sphere_photos

pytestmark = pytest.mark.slow  # each case starts one or two `matcap` processes (torch import included)

CHILD = r"""
import signal, sys, time
# Ctrl-C as on a terminal: a test run started in the background (`cmd &`, some CI runners) hands its children
# SIGINT ignored, and Python keeps an ignored SIGINT ignored
signal.signal(signal.SIGINT, signal.default_int_handler)
patch = sys.argv[1]
argv = sys.argv[2:]

def stop_here():
    print("STOPPED", flush=True)
    time.sleep(600)

exec(patch)
from matcap.cli import main
sys.exit(main(argv))
"""

# each: code run in the child before the command, defining where it stops
STOP_IN_NETWORKS = """
import matcap.estimate as m
_orig = m.estimate
def estimate(*a, **k):
    stop_here()
    return _orig(*a, **k)
m.estimate = estimate
"""
STOP_WRITING_RESULT = """
import matcap.formats as f
_orig = f.write_json
def write_json(path, obj):
    if str(path).endswith("capture.json"):
        stop_here()
    return _orig(path, obj)
f.write_json = write_json
"""
STOP_IN_RELIGHT = """
import matcap.relight as r
_orig = r.render_plan
def render_plan(*a, **k):
    stop_here()
    return _orig(*a, **k)
r.render_plan = render_plan
"""
STOP_IN_EXPORT = """
import matcap.export as e
_orig = e.build_glb
def build_glb(*a, **k):
    stop_here()
    return _orig(*a, **k)
e.build_glb = build_glb
"""
STOP_BETWEEN_RENAMES = """
import os, scenes.atomic as a
_orig = os.replace
def replace(src, dst):
    if ".tmp-" in os.path.basename(str(src)) and not os.path.basename(str(dst)).startswith("."):
        stop_here()  # the previous folder is already moved aside; the new one is not in place yet
    return _orig(src, dst)
a.os = type("os_proxy", (), {"__getattr__": staticmethod(lambda n: getattr(os, n)), "replace": staticmethod(replace)})()
"""
NO_STOP = ""


def run_stopped(patch: str, argv: list[str], sig: int, cwd: Path) -> subprocess.CompletedProcess:
    """Run ``matcap ARGV`` in a child with ``patch`` applied; once it reports STOPPED, send ``sig``."""
    env = {**os.environ, "MATCAP_PROGRESS": "off"}
    p = subprocess.Popen([sys.executable, "-c", CHILD, patch, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, cwd=cwd, env=env)
    deadline = time.time() + 600
    line = ""
    while time.time() < deadline and p.poll() is None:
        ready, _, _ = select.select([p.stdout], [], [], 1.0)
        if ready:
            line = p.stdout.readline()
            if line.strip() == "STOPPED":
                break
    assert line.strip() == "STOPPED", (p.poll(), p.communicate(timeout=60))
    p.send_signal(sig)
    out, err = p.communicate(timeout=300)
    return subprocess.CompletedProcess(p.args, p.returncode, out, err)


def run_cli(argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "matcap", *argv], capture_output=True, text=True, timeout=600,
                          cwd=cwd, env={**os.environ, "MATCAP_PROGRESS": "off"})


def check_stopped(r: subprocess.CompletedProcess, sig: int) -> None:
    if sig == signal.SIGKILL:
        assert r.returncode == -signal.SIGKILL
    else:  # Ctrl-C and kill unwind: one line, exit 130, no traceback
        assert r.returncode == 130, r.stderr
        assert "Traceback" not in r.stderr and r.stderr.strip().splitlines()[-1] == "matcap: interrupted", r.stderr


def hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".")) if folder.is_dir() else []


@pytest.fixture()
def setup(tmp_path, tiny_weights):
    photos = sphere_photos(tmp_path / "photos", h=24, w=32, n=3)
    work = tmp_path / "work"
    work.mkdir()
    argv = ["capture", str(photos), "--out", "result", "--weights", str(tiny_weights), "--quiet"]
    return work, argv


SIGNALS = {"INT": signal.SIGINT, "TERM": signal.SIGTERM, "KILL": signal.SIGKILL}


STOPS = {"networks": STOP_IN_NETWORKS, "writing": STOP_WRITING_RESULT, "relight": STOP_IN_RELIGHT}


@pytest.mark.parametrize("stage,sig", [
    ("networks", "INT"), ("networks", "TERM"), ("networks", "KILL"),
    ("writing", "INT"), ("writing", "TERM"), ("writing", "KILL"),
    ("relight", "TERM"),
])
def test_capture_stopped_leaves_nothing_and_reruns(setup, stage, sig):
    work, argv = setup
    patch = STOPS[stage]
    if stage == "relight":
        argv = [*argv, "--point", "0,0,3", "--spp", "1"]
    r = run_stopped(patch, argv, SIGNALS[sig], work)
    check_stopped(r, SIGNALS[sig])
    assert not (work / "result").exists()
    left = hidden(work)
    if sig == "KILL" and stage == "writing":
        assert len(left) == 1 and left[0].startswith(".result.tmp-"), left  # what only a kill -9 leaves
    else:
        assert left == [], left
    again = run_cli(argv, work)
    assert again.returncode == 0, again.stderr
    assert hidden(work) == [] and sorted(p.name for p in work.iterdir()) == ["result"]
    info = json.loads((work / "result" / "capture.json").read_text())
    assert sorted(info["files"]) == sorted(p.name for p in (work / "result").iterdir())
    if stage == "relight":
        assert {"relight_point_0_0_3.exr", "relight_point_0_0_3.png"} <= set(info["files"])


@pytest.mark.parametrize("sig", ["INT", "KILL"])
def test_capture_stopped_while_exporting(setup, sig):
    work, argv = setup
    argv = [*argv, "--export", "tex"]
    r = run_stopped(STOP_IN_EXPORT, argv, SIGNALS[sig], work)
    check_stopped(r, SIGNALS[sig])
    assert not (work / "result").exists()
    if sig == "KILL":  # the export runs before the result folder is renamed into place: its temporary is left too
        assert len(hidden(work)) == 1 and hidden(work)[0].startswith(".result.tmp-"), hidden(work)
    else:
        assert hidden(work) == []
    tex = work / "tex"
    visible = [p.name for p in tex.iterdir() if not p.name.startswith(".")] if tex.exists() else []
    assert visible == []  # no partial texture set
    if sig == "KILL":
        assert len(hidden(tex)) == 1 and hidden(tex)[0].startswith(".result.stage-")
    again = run_cli(argv, work)
    assert again.returncode == 0, again.stderr
    assert hidden(tex) == [] and hidden(work) == []
    assert (tex / "result.glb").is_file() and (tex / "result.json").is_file()
    files = json.loads((tex / "result.json").read_text())["files"]
    assert all((tex / f["file"]).is_file() for f in files.values())


def test_capture_overwrite_killed_between_its_renames_keeps_the_previous_result(setup):
    from scenes.atomic import recover_dir

    work, argv = setup
    assert run_cli(argv, work).returncode == 0
    before = (work / "result" / "capture.json").read_text()
    r = run_stopped(STOP_BETWEEN_RENAMES, [*argv, "--overwrite", "--seed", "3"], signal.SIGKILL, work)
    check_stopped(r, signal.SIGKILL)
    assert not (work / "result").exists()  # moved aside, the new one not yet in place
    assert any(n.startswith(".result.old-") for n in hidden(work))
    done = recover_dir(work / "result")  # what the next run does first
    assert any(d.startswith("restored result") for d in done) and any(d.startswith("removed") for d in done)
    assert (work / "result" / "capture.json").read_text() == before and hidden(work) == []
    again = run_cli([*argv, "--overwrite", "--seed", "3"], work)
    assert again.returncode == 0, again.stderr
    assert json.loads((work / "result" / "capture.json").read_text())["seed"] == 3 and hidden(work) == []


@pytest.mark.parametrize("sig", ["TERM", "KILL"])
def test_export_stopped_leaves_no_partial_texture_set(tmp_path, sphere_maps, sig):
    from matcap.results import write_result

    write_result(sphere_maps(16, varied=True), tmp_path / "result")
    tex = tmp_path / "tex"
    tex.mkdir()
    (tmp_path / "tex" / "notes.txt").write_text("the user's file")
    argv = ["export", str(tmp_path / "result"), "--out", str(tex)]
    r = run_stopped(STOP_IN_EXPORT, argv, SIGNALS[sig], tmp_path)
    check_stopped(r, SIGNALS[sig])
    assert sorted(p.name for p in tex.iterdir() if not p.name.startswith(".")) == ["notes.txt"]
    again = run_cli(argv, tmp_path)
    assert again.returncode == 0, again.stderr
    assert hidden(tex) == [] and (tex / "result.glb").is_file() and (tex / "notes.txt").read_text() == "the user's file"


def test_recover_files_finishes_a_complete_set_and_drops_an_incomplete_one(tmp_path):
    from scenes.atomic import recover_files

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    complete = tmp_path / f".mat.stage-{dead.pid}-abc"
    complete.mkdir()
    (complete / "mat_a.png").write_text("a")
    (complete / ".complete").touch()
    (tmp_path / "mat_b.png").write_text("b")  # moved before the kill
    partial = tmp_path / f".mat.stage-{dead.pid}-def"
    partial.mkdir()
    (partial / "mat_c.png").write_text("c")
    mine = tmp_path / f".mat.stage-{os.getpid()}-ghi"  # a live process's: left alone
    mine.mkdir()
    done = recover_files(tmp_path, "mat")
    assert done == [f"finished {complete.name}", f"removed {partial.name}"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [mine.name, "mat_a.png", "mat_b.png"]


def test_synth_killed_resumes_without_rerendering(tmp_path):
    out = tmp_path / "d"
    argv = ["synth", "--quiet", "--out", str(out), "--scenes", "4", "--resolution", "16", "--seed", "4",
            "--spp", "1"]
    stop_in_second_write = """
import matcap.synth as s
_orig = s.write_scene
_n = [0]
def write_scene(result, tmp):
    _n[0] += 1
    _orig(result, tmp)
    if _n[0] == 2:
        stop_here()  # scene 0 is finished; scene 1 is written but still in its temporary folder
s.write_scene = write_scene
"""
    r = run_stopped(stop_in_second_write, argv, signal.SIGKILL, tmp_path)
    check_stopped(r, signal.SIGKILL)
    first = out / "scene_000000" / "data.npz"
    assert first.is_file() and not (out / "scene_000001").exists()
    assert any(n.startswith(".tmp-scene_000001-") for n in hidden(out))
    stamp = first.stat().st_mtime_ns
    again = run_cli(argv, tmp_path)
    assert again.returncode == 0, again.stderr
    assert "3 rendered, 1 already done" in again.stdout
    assert first.stat().st_mtime_ns == stamp  # not rendered again
    assert not [n for n in hidden(out) if n.startswith((".tmp-", ".lock-"))]
    assert json.loads((out / "manifest.json").read_text())["scenes"] == [f"scene_{k:06d}" for k in range(4)]
