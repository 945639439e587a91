"""`matcap synth` orchestration: CLI errors, output layout, resume, shards, re-draw of failed scenes."""
import json
import os

import numpy as np
import pytest

from matcap.cli import main

pytest.importorskip("mitsuba")


def _run(*args):
    return main(["synth", "--no-progress", *args])


@pytest.mark.parametrize("args, words", [
    (["--shard", "3/2"], "shard"),
    (["--shard", "x"], "shard"),
    (["--assets", "/nonexistent/assets"], "no such folder"),
    (["--scenes", "0"], "scenes"),
])
def test_bad_input_is_one_line_exit_2(tmp_path, capsys, args, words):
    base = ["--out", str(tmp_path / "d"), "--scenes", "2"]
    code = _run(*(base + args))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and words in err[0] and err[0].startswith("matcap synth: error:")


def test_empty_assets_dir_is_an_error(tmp_path, capsys):
    (tmp_path / "assets").mkdir()
    assert _run("--out", str(tmp_path / "d"), "--scenes", "1", "--assets", str(tmp_path / "assets")) == 2


def test_layout_resume_shards_and_settings_guard(tmp_path, capsys):
    from matcap.imageio import read_exr, read_image

    out = tmp_path / "d"
    common = ["--out", str(out), "--scenes", "3", "--resolution", "32", "--seed", "4", "--spp", "2"]
    assert _run(*common, "--shard", "1/2") == 0  # scene 1 only
    m = json.loads((out / "manifest.json").read_text())
    assert m["scenes"] == ["scene_000001"] and not m["complete"]
    assert _run(*common, "--shard", "0/2") == 0  # scenes 0, 2
    m = json.loads((out / "manifest.json").read_text())
    assert m["scenes"] == ["scene_000000", "scene_000001", "scene_000002"] and m["complete"]
    assert (m["split"], m["resolution"], m["seed"]) == ("train", 32, 4) and "generator_version" in m
    scene = out / "scene_000001"
    stamp = (scene / "000.png").stat().st_mtime_ns
    assert _run(*common) == 0  # resume: nothing re-rendered
    assert (scene / "000.png").stat().st_mtime_ns == stamp
    assert "0 rendered, 3 already done" in capsys.readouterr().out
    # files
    for k in range(10):
        img = read_image(scene / f"{k:03d}.png").pixels
        assert img.dtype == np.uint16 and img.shape == (32, 32, 3)
    mask = read_image(scene / "mask.png").pixels[..., 0]
    assert mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
    normal = read_exr(scene / "normal.exr")
    assert normal.dtype == np.float32 and normal.shape == (32, 32, 3)
    assert np.all(normal[mask == 0] == 0) and normal[..., 2].min() >= 0
    d = np.load(scene / "data.npz")
    assert d["basis"].shape == (8, 32, 32, 3) and d["basis"].dtype == np.float16
    assert list(d["basis_kind"]) == ["env"] * 2 + ["directional"] * 3 + ["point"] * 3
    assert d["images"].shape == (10, 32, 32, 3) and d["mask"].dtype == bool
    assert d["roughness"].shape == (32, 32) and d["base_color"].shape == (32, 32, 3)
    lights = json.loads((scene / "lights.json").read_text())
    assert len(lights["images"]) == 10 and all(x["config"] in "abcde" for x in lights["images"])
    # image k = clip(exposure * sum_b w_b basis_b)
    x = lights["images"][0]
    again = np.clip(np.tensordot(np.float32(x["weights"]), d["basis"].astype(np.float32), 1) * x["exposure"], 0, 1)
    assert np.abs(again - d["images"][0].astype(np.float32)).max() < 3e-3
    spec = json.loads((scene / "spec.json").read_text())
    assert spec["name"] == "scene_000001" and spec["index"] == 1
    # the stored spec reads back into the spec that made the scene (its extra keys are derived)
    from scenes.synth_spec import scene_from_dict

    again = json.loads(json.dumps(scene_from_dict(spec).to_dict()))
    assert again == {k: v for k, v in spec.items() if k != "ground_truth_stats"}
    assert not [p for p in os.listdir(out) if p.startswith(".tmp-")]
    # other settings into the same folder are refused
    assert _run("--out", str(out), "--scenes", "3", "--resolution", "64", "--seed", "4") == 2


def test_failed_scene_is_redrawn_and_logged(tmp_path, monkeypatch):
    import matcap.synth as S

    real = S.render_spec

    def flaky(spec, cache, spp):
        result = real(spec, cache, spp)
        if spec.attempt == 0:
            result.problems = ["image 3 is (nearly) black"]
        return result

    monkeypatch.setattr(S, "render_spec", flaky)
    stats = S.run_synth(tmp_path / "d", 1, resolution=24, seed=2, spp=1, progress=False)
    assert stats["rendered"] == 1 and stats["redrawn"] == 1
    log = [json.loads(line) for line in (tmp_path / "d" / "failures.log").read_text().splitlines()]
    assert log[0]["scene"] == "scene_000000" and log[0]["attempt"] == 0
    spec = json.loads((tmp_path / "d" / "scene_000000" / "spec.json").read_text())
    assert spec["attempt"] == 1


def test_a_shard_is_rendered_by_one_process_at_a_time(tmp_path, capsys):
    import socket
    import subprocess
    import sys

    out = tmp_path / "d"
    common = ["--out", str(out), "--scenes", "1", "--resolution", "16", "--seed", "4", "--spp", "1"]
    out.mkdir()
    lock = out / ".lock-shard-0-of-1"
    # a live process of this host holds the shard: refused, nothing rendered, its lock kept
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock.write_text(f"{sleeper.pid} {socket.gethostname()}\n")
        assert _run(*common) == 2
        err = capsys.readouterr().err
        assert f"shard 0/1 of {out} is being rendered by process {sleeper.pid}" in err and err.count("\n") == 1
        assert not (out / "scene_000000").exists() and lock.exists()
    finally:
        sleeper.kill()
        sleeper.wait()
    # its process is gone: the stale lock is taken over, and released at the end
    assert _run(*common) == 0
    assert (out / "scene_000000" / "data.npz").exists() and not lock.exists()
    # a lock from another machine is not second-guessed
    lock.write_text("12345 some-other-host\n")
    assert _run("--out", str(out), "--scenes", "2", "--resolution", "16", "--seed", "4", "--spp", "1") == 2
    assert "on some-other-host" in capsys.readouterr().err


def test_sigterm_stops_cleanly(tmp_path):
    """`kill` (SIGTERM) unwinds like Ctrl-C: exit 130, no half-written scene, manifest rebuilt, shard lock gone."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "d"
    p = subprocess.Popen([sys.executable, "-m", "matcap", "synth", "--no-progress", "--out", str(out), "--scenes", "500",
                          "--resolution", "16", "--seed", "4", "--spp", "1"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 240
    while not (out / "scene_000000").exists() and time.time() < deadline and p.poll() is None:
        time.sleep(0.1)
    assert p.poll() is None, p.communicate()
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    assert "Traceback" not in err
    names = os.listdir(out)
    assert not [n for n in names if n.startswith((".tmp-", ".lock-"))], names
    done = sorted(n for n in names if n.startswith("scene_"))
    assert 1 <= len(done) < 500 and json.loads((out / "manifest.json").read_text())["scenes"] == done
    assert all((out / n / "data.npz").exists() for n in done)
