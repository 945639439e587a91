"""benchmarks/results.py: its table parsing and marker rewriting, and `--quick` end to end into a temporary folder
(the repository's docs/results.md and README.md are left alone)."""
from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def _module():
    spec = importlib.util.spec_from_file_location("results_script", REPO / "benchmarks" / "results.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def test_markdown_tables_are_read_by_row():
    r = _module()
    text = "header line\n| a | b |\n|---|---:|\n| x | 1.5 |\n| **mean** | 2 |\n\n| c |\n|---|\n| y |\n"
    t = r.tables(text)
    assert len(t) == 2 and t[0][0] == ["a", "b"] and t[1][1] == ["y"]
    assert r.num(r.row_by(t[0], "mean")[1]) == 2.0
    assert r.num("**1,234.5°**") == 1234.5
    with pytest.raises(r.RowFailed):
        r.row_by(t[0], "missing")


def test_renderer_log_lines_between_rows_do_not_split_a_table():
    """Mitsuba writes its warnings to standard output, in colour, between a benchmark's rows."""
    r = _module()
    warn = "\x1b[31m2026-11-27 10:28:51 WARN  [MultijitterSampler] Sample count rounded up to 35"
    text = f"| a | b |\n|---|---:|\n{warn}\n\x1b[0m| x | 1.5 |\n{warn}\n\x1b[0m| y | 2 |\n"
    t = r.tables(text)
    assert t == [[["a", "b"], ["x", "1.5"], ["y", "2"]]], t


def test_only_the_text_between_the_markers_is_replaced(tmp_path):
    r = _module()
    page = tmp_path / "page.md"
    page.write_text(f"before\n{r.START}\nold\n{r.END}\nafter\n")
    r.replace_between(page, r.START, r.END, "new\n")
    assert page.read_text() == f"before\n{r.START}\nnew\n{r.END}\nafter\n"
    fresh = tmp_path / "fresh.md"
    r.replace_between(fresh, r.START, r.END, "rows\n", "# title\n")
    assert fresh.read_text() == f"# title\n{r.START}\nrows\n{r.END}\n"
    with pytest.raises(SystemExit, match="markers"):
        r.replace_between(tmp_path / "page.md", r.SUM_START, r.SUM_END, "x\n")


def test_at_most_eight_summary_rows_and_every_row_has_a_key():
    r = _module()
    assert sum(bool(row.summary) for row in r.ROWS) <= 8
    assert len({row.key for row in r.ROWS}) == len(r.ROWS)


@pytest.mark.slow
def test_quick_run_writes_rows_with_numbers_and_commands(tmp_path):
    out, readme = tmp_path / "results.md", tmp_path / "README.md"
    readme.write_text("# x\n\n<!-- results-summary:start -->\nold\n<!-- results-summary:end -->\n\nend\n")
    proc = subprocess.run([sys.executable, "benchmarks/results.py", "--quick", "--out", str(out), "--readme",
                           str(readme), "--work", str(tmp_path / "work")], cwd=REPO, capture_output=True,
                          text=True, timeout=1800)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    text = out.read_text()
    assert "<!-- results:start -->" in text and "<!-- results:end -->" in text
    rows = [line for line in text.splitlines() if line.startswith("| ") and not line.startswith("| what")]
    measured = [line for line in rows if "not measured" not in line]
    # the rows that need no shared data: bunny, the normal network, relight, synth; with it, 7 more (8: margin)
    assert len(measured) >= (8 if SHARED_DATA.is_dir() else 4), text
    for line in measured:
        cells = line.split(" | ")
        assert re.search(r"\d", cells[1]), line  # a number in the value
        assert re.search(r"`(matcap|python) ", line), line  # the command that produced it
        assert re.search(r"20\d\d-\d\d-\d\d, \d+ cores", line), line  # when and on how many cores
    assert "`matcap capture examples/bunny" in text
    if not SHARED_DATA.is_dir():
        assert "needs ../shared/data" in text  # those rows skipped cleanly, and saying why
        pytest.skip(f"rows needing {SHARED_DATA} were skipped: not available here")
    assert "not measured" not in text, text
    assert "normals vs calibrated least squares" in text and "DATA_TEST" in text
    summary = readme.read_text()
    assert "old" not in summary and summary.endswith("end\n")
    assert 3 <= summary.count("\n| ") - 1 <= 8  # the summary rows, header excluded
