"""The ``dego`` command's entry point: answers ``dego --version`` before importing the
commands (which import most of dego), and makes Ctrl-C while they import no traceback."""

from __future__ import annotations

import sys

from dego._version import __version__


def main() -> int:
    """Run ``dego`` with ``sys.argv``; the exit status."""
    if sys.argv[1:] == ["--version"]:
        print(f"dego {__version__}")
        return 0
    try:
        from dego.cli import main as run
    except KeyboardInterrupt:
        print("dego: interrupted", file=sys.stderr)
        return 130
    return run()


__all__ = ["main"]
