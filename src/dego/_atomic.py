"""Atomic output files and output folders of the ``dego`` commands.

:func:`write_files` writes a set of files all or nothing: each goes to a temporary file
beside it (flushed and fsynced), and only when every one is complete are they moved into
place with ``os.replace``. A failure while writing (a full disk, an interrupt) removes the
temporary files and leaves every previous file as it was, so a reader never sees a
truncated file nor a new file beside an old one of the same run.

:func:`make_output_dir` creates an output folder up front and checks that files can be
created in it; :func:`remove_empty_dirs` takes back the folders it made when a command
ends without writing anything into them.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import uuid
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path


def temporary_name(path: Path) -> Path:
    """A fresh temporary path beside ``path``: ``.<name>.<hex>.tmp``. A leading ``.`` keeps
    it apart from real entries."""
    return path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")


def write_files(files: Mapping[Path, str | bytes]) -> list[Path]:
    """Write every ``path: content`` of ``files`` (``str``: UTF-8 text), all or nothing;
    parents are created. Returns the paths, in order.

    Every content is written to a temporary file beside its path and fsynced first; then
    the temporary files are moved into place with ``os.replace`` (Ctrl-C is held back
    during these renames, which do not allocate space). Until then an error leaves every
    existing file unchanged and no temporary file behind."""
    staged: list[tuple[Path, Path]] = []
    try:
        for path, content in files.items():
            path = Path(path)
            data = content.encode("utf-8") if isinstance(content, str) else bytes(content)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = temporary_name(path)
            # os.open honours the umask, unlike tempfile.mkstemp's 0600.
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            staged.append((tmp, path))
            with os.fdopen(fd, "wb") as file:
                file.write(data)
                file.flush()
                os.fsync(file.fileno())
        with _sigint_held():
            while staged:
                tmp, path = staged[0]
                os.replace(tmp, path)
                staged.pop(0)
    finally:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
    for folder in {Path(path).parent for path in files}:
        _fsync_dir(folder)
    return [Path(path) for path in files]


def write_text(path: Path, text: str) -> Path:
    """:func:`write_files` of one text file."""
    return write_files({path: text})[0]


def write_bytes(path: Path, data: bytes) -> Path:
    """:func:`write_files` of one binary file."""
    return write_files({path: data})[0]


def make_output_dir(path: Path) -> list[Path]:
    """Create the folder ``path`` (and its parents) and check that files can be created in
    it; return the folders this call created, outermost first.

    Raises ``OSError`` with a one-line reason when ``path`` is a file, lies below one,
    cannot be created or is not writable (folders made before the failure are removed)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(f"{path} exists and is not a directory")
    missing = []
    ancestor = path
    while not ancestor.exists():
        missing.append(ancestor)
        if ancestor.parent == ancestor:
            break
        ancestor = ancestor.parent
    if ancestor.exists() and not ancestor.is_dir():
        raise NotADirectoryError(f"{ancestor} is a file, so {path} cannot be a directory")
    created = missing[::-1]
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = temporary_name(path / "write-test")
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        probe.unlink()
    except OSError as error:
        remove_empty_dirs(created)
        reason = error.strerror or str(error)
        raise OSError(error.errno, f"cannot create files in {path}: {reason}") from None
    return created


def check_output_file(path: Path) -> list[Path]:
    """Check that a file can be written at ``path`` (not a directory; its folder is created
    with :func:`make_output_dir`); return the folders created, outermost first."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a directory, expected a file name")
    return make_output_dir(path.parent)


def remove_empty_dirs(created: Sequence[Path]) -> None:
    """Remove the folders of ``created`` (outermost first, as :func:`make_output_dir`
    returns them) that are empty, innermost first; a folder that holds anything stays."""
    for folder in reversed(created):
        try:
            folder.rmdir()
        except OSError:
            return


@contextlib.contextmanager
def _sigint_held() -> Iterator[None]:
    """Hold back SIGINT (Ctrl-C) for the block and deliver it after (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    try:
        previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    except (ValueError, OSError):  # no signals here
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if received:
            signal.raise_signal(signal.SIGINT)


def _fsync_dir(folder: Path) -> None:
    """Make the renames in ``folder`` durable where the platform allows it."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
