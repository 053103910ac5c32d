"""``dego view``: open a ``.rrd`` recording in rerun's viewer (native, or the web viewer)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

RRD_MAGIC = b"RRF2"
"""The first bytes of a rerun recording file."""

VIEWER_HINT = (
    "dego view needs rerun's viewer, which comes with rerun-sdk: "
    'pip install "dego-occupancy[rerun]"'
)


class ViewerUnavailableError(RuntimeError):
    """No viewer can be started here (rerun-sdk missing, or no screen for the native one)."""


def check_recording(path: Path) -> None:
    """Raise ``ValueError`` (one line) unless ``path`` is a readable rerun recording."""
    if path.is_dir():
        raise ValueError(
            f"{path} is a directory; expected a rerun recording file (FILE.rrd, as "
            "written by dego demo --rerun or dego eval --rerun)"
        )
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    try:
        with path.open("rb") as file:
            head = file.read(len(RRD_MAGIC))
    except OSError as error:
        raise ValueError(f"{path}: cannot be read ({error.strerror or error})") from None
    if head != RRD_MAGIC:
        raise ValueError(f"{path}: not a rerun recording (.rrd files start with {RRD_MAGIC!r})")


def has_screen() -> bool:
    """Whether a native window can open: always off Linux, else with an X or Wayland display."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def viewer_command(path: Path, *, web: bool = False) -> list[str]:
    """The command that opens ``path``: rerun's CLI of this Python (``python -m rerun``).

    Raises :class:`ViewerUnavailableError` without rerun-sdk, or for the native viewer where
    there is no screen (the message offers ``--web``)."""
    if importlib.util.find_spec("rerun") is None:
        raise ViewerUnavailableError(VIEWER_HINT)
    if not web and not has_screen():
        raise ViewerUnavailableError(
            "no screen here (DISPLAY and WAYLAND_DISPLAY are not set) for the native viewer: "
            f"run 'dego view {path} --web' and open the address it prints in a browser "
            "(over SSH: forward its ports), or copy the file to a machine with a screen"
        )
    return [sys.executable, "-m", "rerun", str(path), *(["--web-viewer"] if web else [])]


def open_viewer(path: Path, *, web: bool = False) -> int:
    """Open ``path`` in rerun's viewer and wait until it closes; returns its exit status."""
    check_recording(path)
    return subprocess.call(viewer_command(path, web=web))
