"""Progress output: a bar on a terminal, one line per stage (with its time) in logs."""
from __future__ import annotations

import io
import subprocess
import sys

import pytest

from networks.progress import LineProgress, mode, progress


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


class Tty(io.StringIO):
    def isatty(self):
        return True


def test_mode_follows_the_stream_and_the_override(monkeypatch):
    monkeypatch.delenv("MATCAP_PROGRESS", raising=False)
    assert mode(io.StringIO()) == "lines" and mode(Tty()) == "bar"
    monkeypatch.setenv("MATCAP_PROGRESS", "off")
    assert mode(Tty()) == "off"
    monkeypatch.setenv("MATCAP_PROGRESS", "bar")
    assert mode(io.StringIO()) == "bar"


def test_lines_one_at_the_end_and_one_per_interval():
    out, clock = io.StringIO(), FakeClock()
    bar = LineProgress(total=10, desc="synth test", unit="scene", file=out, interval=60, clock=clock)
    for _ in range(4):
        clock.t += 20
        bar.update(1)
    bar.set_postfix(loss="0.1234")
    bar.close()
    bar.close()  # idempotent
    assert out.getvalue().splitlines() == [
        "synth test: 3/10 scenes, 60 s so far",
        "synth test: 4/10 scenes in 80.0 s (stopped early), loss=0.1234",
    ]


def test_a_stage_that_ends_after_the_interval_writes_only_its_closing_line():
    out, clock = io.StringIO(), FakeClock()
    bar = LineProgress(total=2, desc="colour decision", unit="decoding", file=out, interval=60, clock=clock)
    clock.t += 50
    bar.update(1)
    clock.t += 64
    bar.update(1)  # the last step, past the interval: no "so far" line before the closing one
    bar.close()
    assert out.getvalue().splitlines() == ["colour decision: 2/2 decodings in 114.0 s"]


def test_iterating_writes_one_line_and_no_carriage_returns(monkeypatch):
    monkeypatch.delenv("MATCAP_PROGRESS", raising=False)
    out = io.StringIO()
    assert list(progress(range(3), desc="orbit frames", unit="frame", file=out)) == [0, 1, 2]
    text = out.getvalue()
    assert "\r" not in text and text.count("\n") == 1 and text.startswith("orbit frames: 3/3 frames in ")
    out = io.StringIO()
    assert list(progress(range(3), desc="x", file=out, enabled=False)) == [0, 1, 2] and out.getvalue() == ""


def test_total_set_later_as_capture_does(monkeypatch):
    monkeypatch.delenv("MATCAP_PROGRESS", raising=False)
    out = io.StringIO()
    bar = progress(total=None, desc="normal network", unit="px", file=out)
    bar.total, bar.n = 500, 500
    bar.refresh()
    bar.close()
    assert out.getvalue().startswith("normal network: 500/500 px in ")


def test_a_terminal_gets_a_tqdm_bar(monkeypatch):
    monkeypatch.delenv("MATCAP_PROGRESS", raising=False)
    out = Tty()
    for _ in progress(range(3), desc="bar", file=out):
        pass
    assert "\r" in out.getvalue() and "3/3" in out.getvalue()


def test_a_gallery_run_logged_to_a_file_has_one_line_per_stage(tmp_path, sphere_maps):
    pytest.importorskip("mitsuba")
    from matcap.results import write_result

    write_result(sphere_maps(16), tmp_path / "result")
    r = subprocess.run([sys.executable, "-m", "matcap", "gallery", str(tmp_path / "result"), "--orbit", "3",
                        "--size", "16", "--spp", "1", "--orbit-spp", "1", "--out", str(tmp_path / "g")],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "\r" not in r.stderr
    lines = r.stderr.splitlines()
    assert any(line.startswith("environment renders: 1/1 render in ") for line in lines), r.stderr
    assert any(line.startswith("orbit frames: 3/3 frames in ") for line in lines), r.stderr
    assert len(r.stderr) < 1000, r.stderr
