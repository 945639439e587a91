"""The product speaks of itself as it is: no development history in tracked text.

Docs, README, code comments, docstrings, settings comments, model cards and test names must not say which
session or issue made something ("session 17", "sessions 4-7", "issue #18", "the issue-4 target", "as before
session 4"). History belongs in CHANGELOG.md, by date. pytest's ``scope="session"`` and "session-scoped" carry no
number and are not history.
"""
from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

#: Files allowed to tell history: the changelog, and this test (it names the patterns).
ALLOWED = {"CHANGELOG.md", "tests/test_no_history.py"}

HISTORY = re.compile(
    r"\bsessions?[ _-]?#?\d+"                   # session 4, session-5, sessions 4-7, session #3
    r"|\bsession of (?:\d|the )"                # "session of 2026-11-23", "session of the ..."
    r"|\b(?:this|last|previous|earlier|next|the first|a second) (?:gpu )?sessions?\b"
    r"|\bbefore (?:the )?session\b"
    r"|\bissues?[ _-]?#?\d+"                    # issue 17, issue #18, issue-4, issues 16/17
    r"|\bPR ?#\d+",                             # PR #12
    re.IGNORECASE,
)


def _tracked_text_files() -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=REPO,
                             capture_output=True, check=True, timeout=60).stdout
    except (OSError, subprocess.SubprocessError):
        pytest.skip("not a git checkout (or git missing): nothing to list")
    files = []
    for name in sorted(set(out.decode("utf-8", "surrogateescape").split("\0"))):
        if not name or name in ALLOWED:
            continue
        path = REPO / name
        if path.is_file():
            files.append(path)
    return files


def _text(path: Path) -> str | None:
    data = path.read_bytes()
    if b"\0" in data[:8192]:
        return None  # binary (images, weights, archives)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def history_mentions(text: str) -> list[tuple[int, str]]:
    """(line number, line) for every line of ``text`` that names a session or an issue by number."""
    return [(i, line.strip()) for i, line in enumerate(text.splitlines(), 1) if HISTORY.search(line)]


def test_patterns_catch_history_and_spare_pytest_scopes():
    for line in ["the solver before session 17", "sessions 4-7 ran CPU continuations", "Session 1 (CPU)",
                 "as before session 4", "speed work of issue #18", "the issue-4 target", "(issue 17)",
                 "the session-5 loss", "## Session of 2026-11-23 evening", "SESSION 12", "a second GPU session"]:
        assert history_mentions(line), line
    for line in ['@pytest.fixture(scope="session")', "a session-scoped fixture", "sessions share the cache",
                 "docs/recipes/gpu_session.sh", "issues a warning", "see the issue tracker"]:
        assert not history_mentions(line), line


def test_no_development_history_in_tracked_text():
    offenders = []
    for path in _tracked_text_files():
        text = _text(path)
        if text is None:
            continue
        rel = path.relative_to(REPO).as_posix()
        offenders += [f"{rel}:{n}: {line[:100]}" for n, line in history_mentions(text)]
    if offenders:
        pytest.fail(f"{len(offenders)} lines tell development history (move it to CHANGELOG.md, by date, and say "
                    "what the product does now):\n" + "\n".join(offenders), pytrace=False)
