"""Helpers of tests/test_cli_faults.py, also used by

- tests/demo/test_train_command.py
- tests/evaluation/test_evaluation.py
- tests/viz/test_rerun_commands.py
- tests/test_cli_threads.py
"""

from __future__ import annotations

import errno
import io
import os
from pathlib import Path

import pytest

from dego.cli import main


class FullDisk:
    """Replaces ``io.open`` / ``open``: of the files opened for writing in ``folder``, the
    ``fail_at``-th takes half of what is written to it and then raises ENOSPC, like a disk
    that fills up. (A file descriptor opened for writing counts as in ``folder``.)"""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, folder: Path, fail_at: int = 2) -> None:
        self.real, self.folder, self.fail_at, self.opened = io.open, folder, fail_at, 0
        monkeypatch.setattr(io, "open", self)
        monkeypatch.setattr("builtins.open", self)

    def __call__(self, file, mode="r", *args, **kwargs):  # type: ignore[no-untyped-def]
        handle = self.real(file, mode, *args, **kwargs)
        if not any(flag in mode for flag in "wxa+"):
            return handle
        if not isinstance(file, int) and self.folder not in Path(file).resolve().parents:
            return handle
        self.opened += 1
        return _Filling(handle) if self.opened == self.fail_at else handle


class _Filling:
    def __init__(self, handle) -> None:  # type: ignore[no-untyped-def]
        self._handle = handle

    def write(self, data):  # type: ignore[no-untyped-def]
        self._handle.write(data[: len(data) // 2])
        self._handle.flush()
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def __getattr__(self, name: str):  # type: ignore[no-untyped-def]
        return getattr(self._handle, name)

    def __enter__(self) -> _Filling:
        return self

    def __exit__(self, *exc: object) -> None:
        self._handle.close()


def usage_error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """The error line of an argparse usage error (rc 2) of ``dego argv``: the usage line
    and the error come from the subcommand's parser (``dego demo: error: ...``)."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    out, err = capsys.readouterr()
    assert out == "" and "Traceback" not in err
    lines = err.strip().splitlines()
    assert lines[0].startswith(f"usage: dego {argv[0]} ")
    assert lines[-1].startswith(f"dego {argv[0]}: error: ")
    return lines[-1]


class ReadOnly:
    """Makes ``folder`` read-only for this process, as ``chmod a-w`` does for anyone but
    root (whom the tests may run as): creating, opening for writing, replacing, linking or
    making anything in it or below it fails with EACCES (``os.open``, ``os.replace``,
    ``os.link``, ``os.mkdir``)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, folder: Path) -> None:
        self.folder = Path(folder).resolve()
        real_open, real_replace, real_link, real_mkdir = os.open, os.replace, os.link, os.mkdir
        writing = os.O_WRONLY | os.O_RDWR | os.O_CREAT

        def open_(path, flags, *args, **kwargs):  # type: ignore[no-untyped-def]
            if flags & writing:
                self._check(path)
            return real_open(path, flags, *args, **kwargs)

        def replace(src, dst, *args, **kwargs):  # type: ignore[no-untyped-def]
            self._check(src, dst)
            return real_replace(src, dst, *args, **kwargs)

        def link(src, dst, *args, **kwargs):  # type: ignore[no-untyped-def]
            self._check(dst)
            return real_link(src, dst, *args, **kwargs)

        def mkdir(path, *args, **kwargs):  # type: ignore[no-untyped-def]
            self._check(path)
            return real_mkdir(path, *args, **kwargs)

        monkeypatch.setattr(os, "open", open_)
        monkeypatch.setattr(os, "replace", replace)
        monkeypatch.setattr(os, "link", link)
        monkeypatch.setattr(os, "mkdir", mkdir)

    def _check(self, *paths: object) -> None:
        for path in paths:
            if self.folder in Path(os.fspath(path)).resolve().parents:  # type: ignore[arg-type]
                raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fspath(path))  # type: ignore[arg-type]
