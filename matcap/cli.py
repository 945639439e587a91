"""`matcap` command line: thin entry points over library functions.

Each sub-command lives in ``matcap/commands/<name>.py`` and exposes ``register(subparsers)``, which adds its
parser and sets ``func`` (a callable taking the parsed ``argparse.Namespace`` and returning an exit code).
Command modules import heavy libraries (torch, mitsuba) inside ``func`` only, so ``matcap --help`` is fast.

Errors a user can fix (bad input, existing outputs, missing files) end with one line on stderr and exit code 2.
Set ``MATCAP_DEBUG=1`` to get the traceback instead.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings

from matcap.errors import MatcapError, sigterm_as_interrupt

COMMANDS = [
    "capture",
    "calibrate",
    "refine",
    "relight",
    "gallery",
    "export",
    "tile",
    "eval",
    "synth",
    "train",
    "models",
    "weights",
    "reference_check",
]


class OneLineErrors(argparse.ArgumentParser):
    """Usage mistakes end like every other user error: one line on stderr (no usage block) and exit code 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineErrors(
        prog="matcap",
        description="Material capture and relighting: photos under several lights -> SVBRDF maps -> new light.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"matcap.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"matcap.commands.{name}":
                continue
            raise
        module.register(sub)
    return parser


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    """Warnings as one line on stderr (the default adds the source line); MATCAP_DEBUG=1 keeps the default."""
    return f"matcap: warning: {' '.join(str(message).split())}\n"


def _passive_threads() -> None:
    """OpenMP threads that sleep, not spin, while they wait for work (torch's and MKL's thread teams; read once, when
    torch loads, so before any command imports it). Spinning threads take the cores that other jobs, or the
    command's own threads, need: on a busy machine every small operation then waits for a thread that lost its
    core. ``OMP_WAIT_POLICY`` set by the user is kept."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def main(argv: list[str] | None = None) -> int:
    _passive_threads()
    saved = warnings.formatwarning
    if not os.environ.get("MATCAP_DEBUG"):
        warnings.formatwarning = _one_line_warning
    try:
        return _main(argv)
    finally:
        warnings.formatwarning = saved


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        with sigterm_as_interrupt():
            code = args.func(args)
    except KeyboardInterrupt:
        print("matcap: interrupted", file=sys.stderr)
        return 130
    except (MatcapError, ValueError, OSError) as exc:
        if os.environ.get("MATCAP_DEBUG"):
            raise
        message = " ".join(str(exc).split()) or type(exc).__name__
        print(f"matcap {args.command}: error: {message}", file=sys.stderr)
        return 2
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
