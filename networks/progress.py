"""Progress reporting shared by every command: a tqdm bar on a terminal, plain lines everywhere else.

A bar redraws itself with ``\\r``; written into a log file (``nohup``, CI, ``2> log``) that is kilobytes of bar
fragments. So when the stream is not a terminal, :func:`progress` returns a :class:`LineProgress` instead: one line
when the stage ends (``orbit frames: 36/36 frames in 12.3 s``) and, for long stages, one line every ``interval``
seconds in between. ``MATCAP_PROGRESS=bar|lines|off`` overrides the choice.

Lives in ``networks`` (the lowest package that both ``networks.train`` and ``matcap`` may import); no torch.
"""
from __future__ import annotations

import os
import sys
import time
from typing import Iterable, TextIO

MODES = ("bar", "lines", "off")


def mode(file: TextIO | None = None) -> str:
    """``"bar"`` when ``file`` (default stderr) is a terminal, else ``"lines"``; ``MATCAP_PROGRESS`` overrides."""
    forced = os.environ.get("MATCAP_PROGRESS", "").strip().lower()
    if forced in MODES:
        return forced
    stream = file if file is not None else sys.stderr
    try:
        return "bar" if stream.isatty() else "lines"
    except (AttributeError, ValueError):  # closed or not a real stream
        return "lines"


def _plural(unit: str, n: float) -> str:
    """"frame" -> "frames" (not for abbreviations such as "px")."""
    return unit if n == 1 or unit.endswith("s") or unit in ("px", "it") or not unit.isalpha() else unit + "s"


class LineProgress:
    """The subset of tqdm's interface the commands use (iterate, ``update``, ``n``/``total``, ``refresh``,
    ``set_postfix``, ``close``, context manager), writing whole lines: one at the end, one per ``interval`` s."""

    def __init__(self, iterable: Iterable | None = None, *, total: float | None = None, desc: str = "",
                 unit: str = "it", initial: float = 0, file: TextIO | None = None, interval: float = 60.0,
                 clock=time.monotonic):
        self.iterable = iterable
        if total is None and iterable is not None:
            try:
                total = len(iterable)  # type: ignore[arg-type]
            except TypeError:
                total = None
        self.total, self.desc, self.unit, self.n = total, desc, unit, initial
        self.initial = initial
        self.file, self.interval, self._clock = file, interval, clock
        self.postfix = ""
        self._t0 = self._last = clock()
        self.closed = False

    def _stream(self) -> TextIO:
        return self.file if self.file is not None else sys.stderr

    def _line(self, final: bool) -> str:
        count = f"{self.n:g}/{self.total:g}" if self.total is not None else f"{self.n:g}"
        seconds = self._clock() - self._t0
        text = f"{self.desc}: {count} {_plural(self.unit, self.total if self.total is not None else self.n)}"
        text += f" in {seconds:.1f} s" if final else f", {seconds:.0f} s so far"
        if final and self.total is not None and self.n < self.total:
            text += " (stopped early)"
        if self.postfix:
            text += f", {self.postfix}"
        return text

    def _write(self, final: bool) -> None:
        stream = self._stream()
        stream.write(self._line(final) + "\n")
        stream.flush()

    def refresh(self) -> None:
        now = self._clock()
        finished = self.total is not None and self.n >= self.total  # the closing line says it
        if not self.closed and not finished and self.interval > 0 and now - self._last >= self.interval:
            self._last = now
            self._write(final=False)

    def update(self, n: float = 1) -> None:
        self.n += n
        self.refresh()

    def set_postfix(self, **values) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in values.items())

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._write(final=True)

    def __iter__(self):
        try:
            for item in self.iterable:  # type: ignore[union-attr]
                yield item
                self.update(1)
        finally:
            self.close()

    def __enter__(self) -> "LineProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Silent(LineProgress):
    def _write(self, final: bool) -> None:
        pass


def progress(iterable: Iterable | None = None, *, total: float | None = None, desc: str = "", unit: str = "it",
             initial: float = 0, enabled: bool = True, leave: bool = True, file: TextIO | None = None,
             interval: float = 60.0):
    """A progress reporter for a stage: a tqdm bar on a terminal, else a :class:`LineProgress` (see the module
    docstring); silent when ``enabled`` is false or ``MATCAP_PROGRESS=off``. Use it like tqdm: iterate over it, or
    call ``update(n)`` / set ``n`` and ``total`` then ``refresh()``, and ``close()`` (or use ``with``)."""
    how = mode(file) if enabled else "off"
    if how == "bar":
        from tqdm import tqdm

        return tqdm(iterable, total=total, desc=desc, unit=unit, initial=initial, leave=leave,
                    file=file if file is not None else sys.stderr, dynamic_ncols=True)
    cls = LineProgress if how == "lines" else _Silent
    return cls(iterable, total=total, desc=desc, unit=unit, initial=initial, file=file, interval=interval)
