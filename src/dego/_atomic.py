"""Atomic output files and output folders of the ``dego`` commands.

:func:`write_files` writes a set of files all or nothing: each goes to a temporary file
beside it (flushed and fsynced), and only when every one is complete are they moved into
place with ``os.replace``. A failure while writing (a full disk, an interrupt) removes the
temporary files and leaves every previous file as it was, so a reader never sees a
truncated file nor a new file beside an old one of the same run. A target that is a
directory is refused before the first move, and a move that fails midway puts back the
files already replaced.

:func:`make_output_dir` creates an output folder up front and checks that files can be
created in it; :func:`check_output_files` checks every file a command will write before
its work starts; :func:`remove_empty_dirs` takes back the folders they made when a command
ends without writing anything into them.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import threading
import uuid
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path


def temporary_name(path: Path) -> Path:
    """A fresh temporary path beside ``path``: ``.<name>.<hex>.tmp``. A leading ``.`` keeps
    it apart from real entries."""
    return path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")


def write_files(files: Mapping[Path, str | bytes]) -> list[Path]:
    """Write every ``path: content`` of ``files`` (``str``: UTF-8 text), all or nothing;
    parents are created. Returns the paths, in order.

    Every content is written to a temporary file beside its path and fsynced first; then
    every target is checked (an existing directory is an ``IsADirectoryError``) and the
    temporary files are moved into place with ``os.replace`` (Ctrl-C is held back during
    these renames, which do not allocate space). An error before the moves leaves every
    existing file unchanged and no temporary file behind; a move that fails midway puts
    the files already replaced back (each previous file is kept as a hard link until every
    move is done). An ``OSError`` about a temporary file is raised naming its target."""
    staged: list[tuple[Path, Path]] = []
    try:
        for path, content in files.items():
            path = Path(path)
            data = content.encode("utf-8") if isinstance(content, str) else bytes(content)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = temporary_name(path)
            try:
                # os.open honours the umask, unlike tempfile.mkstemp's 0600.
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
                staged.append((tmp, path))
                with os.fdopen(fd, "wb") as file:
                    file.write(data)
                    file.flush()
                    os.fsync(file.fileno())
            except OSError as error:
                raise _naming(error, tmp, path) from error
        for _, path in staged:
            if path.is_dir():
                raise IsADirectoryError(errno.EISDIR, "is a directory, not a file", str(path))
        with _sigint_held():
            _move_all(staged)
    finally:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
    for folder in {Path(path).parent for path in files}:
        _fsync_dir(folder)
    return [Path(path) for path in files]


def _move_all(staged: list[tuple[Path, Path]]) -> None:
    """``os.replace`` every ``(tmp, path)`` of ``staged`` (emptied as it goes). On a
    failure the paths already replaced get their previous files back (a path that had
    none is removed again) and the error is raised, naming its path."""
    done: list[tuple[Path, bool, Path | None]] = []  # (path, existed, link to the old file)
    try:
        while staged:
            tmp, path = staged[0]
            existed = os.path.lexists(path)
            backup = _hard_link(path) if existed else None
            try:
                os.replace(tmp, path)
            except OSError as error:
                if backup is not None:
                    backup.unlink(missing_ok=True)
                raise _naming(error, tmp, path) from error
            done.append((path, existed, backup))
            staged.pop(0)
    except BaseException:
        for path, existed, backup in reversed(done):
            with contextlib.suppress(OSError):
                if backup is not None:
                    os.replace(backup, path)
                elif not existed:
                    path.unlink()
        raise
    finally:
        for _, _, backup in done:
            if backup is not None:
                with contextlib.suppress(OSError):
                    backup.unlink(missing_ok=True)


def _hard_link(path: Path) -> Path | None:
    """A hard link beside ``path`` to the file there, or ``None`` where the file system
    has no hard links (that file cannot be put back)."""
    backup = temporary_name(path)
    try:
        os.link(path, backup, follow_symlinks=False)
    except OSError:
        return None
    return backup


def _naming(error: OSError, tmp: Path, path: Path) -> OSError:
    """``error`` naming ``path`` where it named the temporary file ``tmp`` or no file (an
    ``OSError`` of the same kind: ``OSError(errno, ...)`` picks the subclass)."""
    named = error.filename
    if error.errno is None or (named is not None and os.fspath(named) != os.fspath(tmp)):
        return error
    return OSError(error.errno, error.strerror or os.strerror(error.errno), str(path))


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


def check_output_files(paths: Iterable[Path]) -> list[Path]:
    """:func:`check_output_file` of every path of ``paths`` (the files a command writes,
    checked before its work starts); return the folders created, outermost first. On the
    first failure the folders this call made are removed again and the ``OSError`` is
    raised, naming the path."""
    created: list[Path] = []
    try:
        for path in paths:
            created += check_output_file(Path(path))
    except OSError:
        remove_empty_dirs(created)
        raise
    return created


def same_file(first: Path, second: Path) -> bool:
    """Whether two paths name one file: the same path once symbolic links, ``..`` and the
    current folder are resolved, or (both existing) the same inode, as hard links are."""
    if Path(first).resolve() == Path(second).resolve():
        return True
    try:
        return os.path.samefile(first, second)
    except OSError:
        return False


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
