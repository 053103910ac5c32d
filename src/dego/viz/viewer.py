"""``dego view``: open a ``.rrd`` recording in rerun's viewer (native, or the web viewer)."""

from __future__ import annotations

import importlib.util
import ipaddress
import os
import subprocess
import sys
from pathlib import Path

RRD_MAGIC = b"RRF2"
"""The first bytes of a rerun recording file."""

VIEWER_HINT = (
    "dego view needs rerun's viewer, which comes with rerun-sdk: "
    'pip install -e ".[rerun]" in your dego clone'
)


LOCAL_BIND = "127.0.0.1"
"""The address ``dego view`` has rerun's servers listen on unless ``--bind`` says otherwise:
this machine only (rerun's own default, ``0.0.0.0``, is every interface)."""

WEB_VIEWER_PORT = 9090
"""The port of rerun's web viewer page (``--port``; rerun's default)."""

GRPC_PORT = 9876
"""The port rerun's viewer streams the recording from (``--grpc-port``; rerun's default)."""


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


def viewer_command(
    path: Path,
    *,
    web: bool = False,
    bind: str = LOCAL_BIND,
    port: int | None = None,
    grpc_port: int | None = None,
) -> list[str]:
    """The command that opens ``path``: rerun's CLI of this Python (``python -m rerun``),
    its servers listening on ``bind`` (this machine only by default); with ``web`` the web
    viewer's page on ``port`` (:data:`WEB_VIEWER_PORT` when ``None``) and the recording on
    ``grpc_port`` (:data:`GRPC_PORT`); the native viewer's own server on ``grpc_port`` where
    given (else rerun's default, the same port).

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
    command = [sys.executable, "-m", "rerun", str(path), "--bind", bind]
    if web:
        command += ["--web-viewer", "--web-viewer-port", str(port or WEB_VIEWER_PORT)]
        command += ["--port", str(grpc_port or GRPC_PORT)]
    elif grpc_port is not None:
        command += ["--port", str(grpc_port)]
    return command


def open_viewer(
    path: Path,
    *,
    web: bool = False,
    bind: str = LOCAL_BIND,
    port: int | None = None,
    grpc_port: int | None = None,
) -> int:
    """Open ``path`` in rerun's viewer (:func:`viewer_command`) and wait until it closes;
    returns its exit status. With ``web``, first one line on stderr: where it is served."""
    check_recording(path)
    command = viewer_command(path, web=web, bind=bind, port=port, grpc_port=grpc_port)
    if web:
        ports = f"ports {port or WEB_VIEWER_PORT} and {grpc_port or GRPC_PORT}"
        where = (
            f"this machine only ({bind}; over SSH forward {ports}; --bind 0.0.0.0 serves "
            "every interface)"
            if ipaddress.ip_address(bind).is_loopback
            else f"{bind}, {ports}"
        )
        print(f"dego view: serving rerun's web viewer on {where}", file=sys.stderr, flush=True)
    return subprocess.call(command)
