"""Atomic writes: the one helper every package uses to write a file or a whole folder.

A file is written under a temporary name in its destination folder and renamed into place when complete, so a
reader never sees half a file and an interrupted run never destroys the previous version. The temporary file is
created private (``mkstemp``: 0600) and given the usual permissions (0666 minus the umask) before the rename; a
folder built by :func:`atomic_dir` likewise gets 0777 minus the umask.

Standard library + numpy only (it lives in the lowest package so that ``networks``, ``renderers`` and ``matcap``
can all use it):

    with atomic_path("model.safetensors") as tmp:   # any writer that takes a path
        save_file(state, tmp)
    write_text_atomic("results.md", text)
    write_json_atomic("capture.json", info)         # numpy scalars / arrays and paths are converted
    with atomic_dir("result/") as tmp:              # a whole folder, swapped in when complete
        ...
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[str]:
    """Yield a temporary path next to ``path`` (same suffix, so format-sniffing writers still work); on success it
    gets the usual permissions and is renamed onto ``path``. On an exception it is deleted and ``path`` is left
    as it was. Creates the parent folders."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600 files
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    write_bytes_atomic(path, text.encode("utf-8"))


def json_default(obj: Any) -> Any:
    """``json.dumps(default=...)`` for numpy scalars and arrays, paths and sets (anything else: TypeError)."""
    import numpy as np

    if isinstance(obj, (np.integer, np.floating, np.bool_)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def json_text(obj: Any, indent: int | None = 2) -> str:
    """The text :func:`write_json_atomic` writes: ``json.dumps`` with :func:`json_default` and a final newline."""
    return json.dumps(obj, indent=indent, default=json_default) + "\n"


def write_json_atomic(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> None:
    """Write ``obj`` as JSON (see :func:`json_text`) to ``path`` atomically."""
    write_text_atomic(path, json_text(obj, indent))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # someone else's process (or cannot tell): leave its files alone
    return True


def _dead_owner(entry: Path, marker: str) -> bool:
    """Whether ``entry`` (named ``...{marker}{pid}-...`` or ``...{marker}{pid}``) belongs to a process that no
    longer runs, i.e. one killed before it could clean up (``kill -9``, a power cut)."""
    rest = entry.name.split(marker, 1)[1] if marker in entry.name else ""
    digits = rest.split("-", 1)[0]
    return digits.isdigit() and int(digits) != os.getpid() and not _pid_alive(int(digits))


def recover_dir(path: str | os.PathLike) -> list[str]:
    """Tidy what an :func:`atomic_dir` for ``path`` killed part-way left beside it: temporary folders of dead
    processes are deleted; a previous ``path`` that was moved aside (``.NAME.old-PID``) when the run was killed
    between its two renames is put back if ``path`` is missing, else deleted. Returns what was done (for tests)."""
    path = Path(path).absolute()
    done: list[str] = []
    if not path.parent.is_dir():
        return done
    for entry in sorted(path.parent.glob(f".{glob_escape(path.name)}.*")):
        if entry.name.startswith(f".{path.name}.tmp-") and _dead_owner(entry, ".tmp-"):
            shutil.rmtree(entry, ignore_errors=True)
            done.append(f"removed {entry.name}")
        elif entry.name.startswith(f".{path.name}.old-") and _dead_owner(entry, ".old-"):
            if not path.exists():
                os.replace(entry, path)
                done.append(f"restored {path.name} from {entry.name}")
            else:
                shutil.rmtree(entry, ignore_errors=True)
                done.append(f"removed {entry.name}")
    return done


def glob_escape(name: str) -> str:
    """``name`` with glob's special characters escaped."""
    import glob

    return glob.escape(name)


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a fresh temporary folder next to ``path``; on success it replaces ``path`` (a previous folder there
    is kept until the new one is complete, then deleted). On an exception the temporary folder is deleted and
    ``path`` is left as it was. The caller decides whether replacing an existing folder is allowed.

    The temporary names carry the process id (``.NAME.tmp-PID-xxxx``, ``.NAME.old-PID``), so what a killed run
    (``kill -9``) leaves is recognised and tidied by the next one (:func:`recover_dir`)."""
    path = Path(path).absolute()
    path.parent.mkdir(parents=True, exist_ok=True)
    recover_dir(path)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-{os.getpid()}-", dir=path.parent))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes 0700 folders
        old = None
        if path.exists():
            old = path.parent / f".{path.name}.old-{os.getpid()}"
            os.replace(path, old)
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


_COMPLETE = ".complete"


def recover_files(folder: str | os.PathLike, tag: str) -> list[str]:
    """Tidy what an :func:`atomic_files` for ``(folder, tag)`` killed part-way left in ``folder``: a staging folder
    of a dead process is finished if it was complete (its files are moved into place) and deleted otherwise.
    Returns what was done (for tests)."""
    folder = Path(folder)
    done: list[str] = []
    if not folder.is_dir():
        return done
    for stage in sorted(folder.glob(f".{glob_escape(tag)}.stage-*")):
        if not (stage.is_dir() and _dead_owner(stage, ".stage-")):
            continue
        if (stage / _COMPLETE).exists():
            _move_all(stage, folder)
            done.append(f"finished {stage.name}")
        else:
            done.append(f"removed {stage.name}")
        shutil.rmtree(stage, ignore_errors=True)
    return done


def _move_all(stage: Path, folder: Path, last: str | None = None) -> None:
    names = sorted(p.name for p in stage.iterdir() if p.name != _COMPLETE)
    if last in names:
        names.remove(last)
        names.append(last)
    for name in names:
        os.replace(stage / name, folder / name)


@contextlib.contextmanager
def atomic_files(folder: str | os.PathLike, tag: str, last: str | None = None) -> Iterator[Path]:
    """A set of files written into an existing (or new) ``folder`` that may hold other files: yield a hidden
    staging folder inside it (``.TAG.stage-PID-xxxx``); write the files there; on success they are moved into
    ``folder`` (``last``, e.g. the set's JSON index, moved last) and the staging folder is deleted. On an
    exception nothing reaches ``folder``. A staging folder left by a killed run is finished (if it was complete)
    or deleted by the next run with the same tag (:func:`recover_files`)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    recover_files(folder, tag)
    stage = Path(tempfile.mkdtemp(prefix=f".{tag}.stage-{os.getpid()}-", dir=folder))
    try:
        yield stage
        for p in stage.iterdir():
            if p.is_file():
                os.chmod(p, 0o666 & ~_umask())
        (stage / _COMPLETE).touch()  # from here on the set is committed: a killed run is finished by the next
        _move_all(stage, folder, last)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
