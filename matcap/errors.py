"""User-facing errors.

Anything raised as :class:`MatcapError` (or ``ValueError`` / ``OSError`` from the lower packages) is printed by
the CLI as one line and ends the process with exit code 2; it never shows a traceback (set ``MATCAP_DEBUG=1``
to see one).
"""
from __future__ import annotations

import contextlib
import signal
import threading


class MatcapError(Exception):
    """A problem with the user's input or environment, explained in one line."""


@contextlib.contextmanager
def sigterm_as_interrupt():
    """While active, SIGTERM (``kill``, a scheduler, ``timeout``) raises KeyboardInterrupt like Ctrl-C, so a run
    unwinds the same way: ``finally`` blocks run, temporary folders are removed, no partial output is left.
    Main thread only (elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, _frame):
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
