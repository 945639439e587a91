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


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a fresh temporary folder next to ``path``; on success it replaces ``path`` (a previous folder there
    is kept until the new one is complete, then deleted). On an exception the temporary folder is deleted and
    ``path`` is left as it was. The caller decides whether replacing an existing folder is allowed."""
    path = Path(path).absolute()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
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
