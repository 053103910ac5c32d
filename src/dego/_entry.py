"""The ``dego`` command's entry point: answers ``dego --version`` before importing the
commands (which import most of dego), and makes Ctrl-C while they import no traceback."""

from __future__ import annotations

import sys

from dego._version import __version__

_PY_EVAL_INPUT = 258  # Python.h's Py_eval_input


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


def forget_caught_interrupts() -> None:
    """Keep ``python -m dego``'s exit status when a Ctrl-C was caught.

    CPython notes a ``KeyboardInterrupt`` that leaves code run through ``PyRun_String``
    (which some extensions call) even when Python code catches it later, and under ``-m``
    it then ends the process by SIGINT instead of with the status ``main`` returned (seen
    as -2, not 130, by ``subprocess``). Running one trivial expression through
    ``PyRun_String`` clears that note; where there is no ``pythonapi`` (not CPython) there
    is nothing to clear."""
    try:
        import ctypes

        run = ctypes.pythonapi.PyRun_String
    except (ImportError, AttributeError):  # pragma: no cover - not CPython
        return
    run.restype = ctypes.py_object
    run.argtypes = [ctypes.c_char_p, ctypes.c_int, ctypes.py_object, ctypes.py_object]
    run(b"0", _PY_EVAL_INPUT, {}, {})


__all__ = ["forget_caught_interrupts", "main"]
