"""The product speaks of itself as it is: no development history in tracked text.

Docs, README, code comments, docstrings, settings comments, model cards and test names must not say which
working session or tracker issue made something: the word followed by its number, a range of them, "as before"
one. History belongs in CHANGELOG.md, by date. pytest's ``scope="session"`` and "session-scoped" carry no number
and are not history. (The examples below are assembled from parts, so that this file tells no history either.)
"""
from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

#: Files allowed to tell history: the changelog.
ALLOWED = {"CHANGELOG.md"}
S, I = "session", "issue"  # the words the patterns look for, kept apart from their numbers in this file

HISTORY = re.compile(
    r"\bsessions?[ _-]?#?\d+"                   # the word, then a number: "-5", "s 4-7", " #3"
    r"|\bsession of (?:\d|the )"                # the word, then "of" and a date
    r"|\b(?:this|last|previous|earlier|next|the first|a second) (?:gpu )?sessions?\b"
    r"|\bbefore (?:the )?session\b"
    r"|\bissues?[ _-]?#?\d+"                    # the word, then a number: " #18", "-4", "s 16/17"
    r"|\bPR ?#\d+",                             # a pull request by number
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
    for line in [f"the solver before {S} 17", f"{S}s 4-7 ran CPU continuations", f"{S.title()} 1 (CPU)",
                 f"as before {S} 4", f"speed work of {I} #18", f"the {I}-4 target", f"({I} 17)",
                 f"the {S}-5 loss", f"## {S.title()} of 2026-11-23 evening", f"{S.upper()} 12",
                 f"a second GPU {S}"]:
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
