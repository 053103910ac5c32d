"""A restricted unpickler for data files (mmdet3d infos): plain containers and numpy only.

:func:`load_pickle` reads a pickle with an unpickler whose ``find_class`` resolves only
an allow-list of globals: the builtin containers and values (``dict``, ``list``,
``tuple``, ``set``, ``frozenset``, ``str``, ``bytes``, ``bytearray``, ``int``,
``float``, ``complex``, ``bool``, ``slice``, ``range``), ``collections.OrderedDict`` and
``collections.defaultdict``, ``_codecs.encode`` (latin-1 only: how protocol 2 stores
bytes) and what numpy's own pickles name (``_reconstruct``, ``ndarray``, ``dtype``,
``scalar``, ``_frombuffer``, under ``numpy.core`` of numpy 1.x or ``numpy._core`` of
numpy 2.x). Every other global (``os.system``, ``builtins.eval``, any class) and every
persistent id raises :class:`UnsafePickleError` before anything is called, so nothing in
the file can run code. Objects inside object arrays go through the same check.

numpy's pickled state is not trusted either: ``numpy.ndarray`` is never callable from
the file (``ndarray(shape, object, buffer)`` would read raw memory as pointers), and
every dtype is rebuilt through numpy's validating constructor before an array or
scalar uses it (a pickled dtype state may carry field offsets past its item size).

Nor are the sizes a file declares: what a few bytes can make the loader allocate is
bounded by the file's size. The unpickler is Python's pure-Python one, whose memo is a
dict (the C unpickler grows an array to the largest memo index: ``LONG_BINPUT 2**31``
in 10 bytes asked for 16 GB); a read past the end of the file (a ``BINBYTES8`` or frame
declaring more than the file holds) is refused before it is attempted; the allowed
constructors refuse a size argument (``bytes(2**36)``, ``bytearray(2**32)``) and an
iterable longer than :func:`item_limit` (``list(range(10**9))``), whether the file calls
them (``REDUCE``) or their ``__new__`` (``NEWOBJ``); numpy arrays declared
larger than the file holds fail numpy's own size check.
"""

from __future__ import annotations

import _compat_pickle
import collections
import os
import pickle
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar, cast

import numpy as np

from dego._npz import open_regular_file
from dego._typing import typechecked

PathLike = str | os.PathLike[str]

__all__ = ["UnsafePickleError", "load_pickle"]

_ALLOWED_MESSAGE = (
    "only plain containers (dict, list, tuple, set), numbers, strings and numpy arrays are allowed"
)


class UnsafePickleError(pickle.UnpicklingError, ValueError):
    """A pickle names a global or persistent id outside the allow-list of :func:`load_pickle`.

    Subclasses both ``pickle.UnpicklingError`` and ``ValueError``; the message names the
    file and the refused global as ``module.name``.
    """


try:  # numpy >= 2
    from numpy._core import multiarray as _multiarray
    from numpy._core import numeric as _numeric
except ImportError:  # pragma: no cover - numpy 1.x
    from numpy.core import multiarray as _multiarray  # type: ignore[no-redef]
    from numpy.core import numeric as _numeric  # type: ignore[no-redef]


class _CheckedArray(np.ndarray):
    """What ``_reconstruct`` builds: its ``__setstate__`` rebuilds the dtype first.

    :func:`load_pickle` turns every such array into a plain ``numpy.ndarray`` (a view).
    """

    __slots__ = ()

    def __setstate__(self, state: Any) -> None:
        if not isinstance(state, tuple) or len(state) not in (4, 5):
            raise ValueError("numpy.ndarray: malformed pickled array state")
        if len(state) == 5:  # version, shape, dtype, is_fortran, data
            state = (state[0], state[1], _checked_dtype(state[2]), state[3], state[4])
        else:
            state = (state[0], _checked_dtype(state[1]), state[2], state[3])
        super().__setstate__(state)


class _NdarrayMarker:
    """Stands for ``numpy.ndarray`` in a pickle: only ``_reconstruct`` may take it."""

    __slots__ = ()

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        raise UnsafePickleError(
            "numpy.ndarray may only be passed to numpy's _reconstruct, not called"
        )

    def __reduce__(self) -> Any:
        raise TypeError("not picklable")


_NDARRAY = _NdarrayMarker()


def _checked_dtype(dtype: Any) -> np.dtype:
    """The same dtype rebuilt by numpy's validating constructors (``ValueError`` if not)."""
    if not isinstance(dtype, np.dtype):
        raise ValueError(f"expected a numpy dtype, got {type(dtype).__name__}")
    try:
        if dtype.subdtype is not None:
            base, shape = dtype.subdtype
            rebuilt = np.dtype((_checked_dtype(base), shape))
        elif dtype.names is not None:
            fields = dtype.fields
            assert fields is not None
            entries = [fields[name] for name in dtype.names]
            # numpy's stubs type a fields dict as a TypedDict of literal keys; this one is built
            spec: Any = {
                "names": list(dtype.names),
                "formats": [_checked_dtype(entry[0]) for entry in entries],
                "offsets": [int(entry[1]) for entry in entries],
                "itemsize": int(dtype.itemsize),
            }
            if any(len(entry) > 2 for entry in entries):
                spec["titles"] = [entry[2] if len(entry) > 2 else None for entry in entries]
            rebuilt = np.dtype(spec, align=bool(dtype.isalignedstruct))
        else:
            rebuilt = np.dtype(dtype.str)
    except (TypeError, ValueError, KeyError, OverflowError) as exc:
        raise ValueError(f"malformed numpy dtype {dtype!r} ({exc})") from None
    if rebuilt.itemsize != dtype.itemsize or rebuilt != dtype:
        raise ValueError(f"malformed numpy dtype {dtype!r}")
    return rebuilt


def _reconstruct(subtype: Any, shape: Any, typecode: Any) -> np.ndarray:
    if subtype is not _NDARRAY:
        raise UnsafePickleError(
            f"numpy _reconstruct may only rebuild numpy.ndarray, got {type(subtype).__name__}"
        )
    return cast(np.ndarray, _multiarray._reconstruct(_CheckedArray, (0,), b"b"))


def _scalar(dtype: Any, *data: Any) -> Any:
    return _multiarray.scalar(_checked_dtype(dtype), *data)


def _frombuffer(buffer: Any, dtype: Any, shape: Any, order: Any) -> np.ndarray:
    if not isinstance(buffer, bytes | bytearray):
        raise ValueError("numpy _frombuffer: expected in-band bytes")
    # numpy's stubs leave out the private _frombuffer (what ndarray.__reduce__ pickles)
    return _numeric._frombuffer(  # type: ignore[attr-defined]
        buffer, _checked_dtype(dtype), shape, order
    )


def _dtype(obj: Any, align: Any = False, copy: Any = False) -> np.dtype:
    if not isinstance(obj, str):
        raise ValueError(f"numpy.dtype: expected a type string, got {type(obj).__name__}")
    return np.dtype(obj, bool(align), bool(copy))


def _latin1_encode(text: Any, encoding: Any = "utf-8") -> bytes:
    # protocol 2 stores bytes as _codecs.encode(str, "latin1")
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1", "latin_1"):
        raise UnsafePickleError("_codecs.encode is allowed only for latin-1 strings")
    return text.encode("latin-1")


ITEMS_PER_BYTE = 16
"""Items one allowed constructor may build per byte of the file (each item needs at least
one byte of opcode, so this is generous)."""
ITEM_ALLOWANCE = 65_536
"""Items allowed on top of :data:`ITEMS_PER_BYTE` per byte, whatever the file's size."""


def item_limit(file_size: int) -> int:
    """The most items one allowed constructor may build from a file of ``file_size`` bytes."""
    return ITEMS_PER_BYTE * file_size + ITEM_ALLOWANCE


_SIZED = frozenset({list, tuple, set, frozenset, dict, bytes, bytearray, str})


def _check_sizes(kind: Any, args: tuple[Any, ...], path: Path, limit: int) -> None:
    """Before ``kind(*args)`` (``REDUCE``) or ``kind.__new__(kind, *args)`` (``NEWOBJ``) of
    an allowed container: no size argument, no iterable longer than ``limit``."""
    if kind not in _SIZED:
        return
    name = kind.__name__
    if args and kind in (bytes, bytearray) and isinstance(args[0], int):
        raise UnsafePickleError(
            f"{path}: refused {name}({args[0]}): a size argument would allocate memory the "
            "file does not hold"
        )
    for value in args:
        sized = isinstance(value, range | str | bytes | bytearray | list | tuple | set | dict)
        if sized and len(value) > limit:
            raise UnsafePickleError(
                f"{path}: refused {name}() of {len(value):,} items: at most {limit:,} for a "
                "file of this size"
            )


class _BoundedFile:
    """The file as the unpickler reads it: a read of more than the rest of the file is
    refused before any buffer for it is allocated."""

    def __init__(self, stream: Any, path: Path, size: int) -> None:
        self._stream, self._path, self._size = stream, path, size

    def read(self, n: int = -1) -> bytes:
        remaining = self._size - self._stream.tell()
        if n > remaining:
            raise ValueError(f"it declares {n:,} bytes where {max(remaining, 0):,} remain")
        return cast(bytes, self._stream.read(n))

    def readinto(self, buffer: Any) -> int:
        if len(buffer) > self._size - self._stream.tell():
            raise ValueError("it declares more bytes than the file holds")
        return cast(int, self._stream.readinto(buffer))

    def readline(self) -> bytes:
        return cast(bytes, self._stream.readline(self._size - self._stream.tell()))


_NUMPY = {
    "_reconstruct": ("multiarray", _reconstruct),
    "scalar": ("multiarray", _scalar),
    "_frombuffer": ("numeric", _frombuffer),
}

_ALLOWED: dict[tuple[str, str], Any] = {
    **{
        ("builtins", kind.__name__): kind
        for kind in (
            dict,
            list,
            tuple,
            set,
            frozenset,
            str,
            bytes,
            bytearray,
            int,
            float,
            complex,
            bool,
            slice,
            range,
        )
    },
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("collections", "defaultdict"): collections.defaultdict,
    ("_codecs", "encode"): _latin1_encode,
    ("numpy", "ndarray"): _NDARRAY,
    ("numpy", "dtype"): _dtype,
    **{
        (f"numpy.{package}.{module}", name): function
        for package in ("core", "_core")
        for name, (module, function) in _NUMPY.items()
    },
}


class _RestrictedUnpickler(pickle._Unpickler):  # the pure-Python one: its memo is a dict
    def __init__(self, file: Any, path: Path, size: int) -> None:
        super().__init__(_BoundedFile(file, path, size))
        self._path = path
        self._limit = item_limit(size)

    def find_class(self, module: str, name: str) -> Any:
        key = (module, name)
        # Python 2 names, as protocols 0-2 write them (``__builtin__.set``, ``xrange``)
        if key in _compat_pickle.NAME_MAPPING:
            key = _compat_pickle.NAME_MAPPING[key]
        elif module in _compat_pickle.IMPORT_MAPPING:
            key = (_compat_pickle.IMPORT_MAPPING[module], name)
        if key in _ALLOWED:
            return _ALLOWED[key]
        written = "" if key == (module, name) else f" (written as {module}.{name})"
        raise UnsafePickleError(
            f"{self._path}: refused the global {key[0]}.{key[1]}{written}: {_ALLOWED_MESSAGE}"
        )

    # REDUCE, NEWOBJ and NEWOBJ_EX call what find_class allowed: check the sizes first
    def _load_reduce(self) -> None:
        _check_sizes(self.stack[-2], self.stack[-1], self._path, self._limit)  # type: ignore[attr-defined]
        super().load_reduce()  # type: ignore[misc]

    def _load_newobj(self) -> None:
        _check_sizes(self.stack[-2], self.stack[-1], self._path, self._limit)  # type: ignore[attr-defined]
        super().load_newobj()  # type: ignore[misc]

    def _load_newobj_ex(self) -> None:
        _check_sizes(self.stack[-3], self.stack[-2], self._path, self._limit)  # type: ignore[attr-defined]
        super().load_newobj_ex()  # type: ignore[misc]

    dispatch: ClassVar[dict[int, Callable[[Any], None]]] = {
        **pickle._Unpickler.dispatch,
        pickle.REDUCE[0]: _load_reduce,
        pickle.NEWOBJ[0]: _load_newobj,
        pickle.NEWOBJ_EX[0]: _load_newobj_ex,
    }

    def persistent_load(self, pid: Any) -> Any:
        raise UnsafePickleError(
            f"{self._path}: refused the persistent id {pid!r}: {_ALLOWED_MESSAGE}"
        )


_CORRUPT = (
    pickle.UnpicklingError,
    EOFError,
    ValueError,
    TypeError,
    AttributeError,
    IndexError,
    KeyError,
    struct.error,
    OverflowError,
    RuntimeError,
    MemoryError,
    RecursionError,
    UnicodeError,
    ImportError,
)


@typechecked
def load_pickle(path: PathLike) -> object:
    """Read a pickle that holds only plain containers, numbers, strings and numpy arrays.

    Args:
        path: the ``.pkl`` file.

    Returns:
        The unpickled object; numpy arrays come back as plain ``numpy.ndarray``.

    Raises:
        FileNotFoundError: naming ``path`` when it does not exist or is not a regular
            file (a FIFO, socket or device is refused without blocking).
        UnsafePickleError: (a ``pickle.UnpicklingError`` and a ``ValueError``) naming the
            file and the refused global ``module.name`` (or persistent id); nothing from
            the file has been called.
        ValueError: naming the file when it is truncated, corrupt or holds malformed
            numpy state.
    """
    file = Path(path)
    if not file.exists():
        raise FileNotFoundError(f"{file}: no such pickle file")
    if file.is_dir():
        raise IsADirectoryError(f"{file}: expected a pickle file, got a directory")
    try:
        # A FIFO (or socket, device) is refused here rather than blocking in open().
        with open_regular_file(file, "a pickle file") as stream:
            size = os.fstat(stream.fileno()).st_size
            loaded = _RestrictedUnpickler(stream, file, size).load()
        return _plain(loaded, {})
    except UnsafePickleError as exc:
        if str(file) in str(exc):
            raise
        raise UnsafePickleError(f"{file}: {exc}") from None
    except _CORRUPT as exc:
        raise ValueError(
            f"{file}: not a readable pickle of plain data ({type(exc).__name__}: {exc})"
        ) from None


_LEAVES = frozenset({str, int, float, bool, bytes, complex, type(None)})


def _plain(obj: Any, seen: dict[int, Any]) -> Any:
    """``obj`` with every checked array as a plain ndarray and every dtype rebuilt.

    Mutable containers are updated in place (shared references and cycles survive);
    tuples and frozensets are rebuilt only when an item changes.
    """
    kind = type(obj)
    if kind in _LEAVES:
        return obj
    key = id(obj)
    if key in seen:
        return seen[key]
    if isinstance(obj, _CheckedArray):
        out: Any = obj.view(np.ndarray)
        seen[key] = out
        if out.dtype.hasobject:
            for index, item in enumerate(out.flat):
                new = _plain(item, seen)
                if new is not item:
                    out.flat[index] = new
        return out
    if isinstance(obj, np.ndarray):  # from _frombuffer: never object dtype
        seen[key] = obj
        return obj
    if isinstance(obj, np.dtype):
        out = _checked_dtype(obj)
        seen[key] = out
        return out
    if isinstance(obj, list):
        seen[key] = obj
        for index, item in enumerate(obj):
            if type(item) not in _LEAVES and (new := _plain(item, seen)) is not item:
                obj[index] = new
        return obj
    if isinstance(obj, dict):  # dict, OrderedDict, defaultdict
        seen[key] = obj
        if all(type(k) in _LEAVES for k in obj):  # the usual case: str keys
            for k, v in obj.items():
                if type(v) not in _LEAVES and (new := _plain(v, seen)) is not v:
                    obj[k] = new  # same key: the dict keeps its size and order
            return obj
        items = [(_plain(k, seen), k, _plain(v, seen), v) for k, v in obj.items()]
        if any(nk is not k for nk, k, _, _ in items):
            obj.clear()
            obj.update((nk, nv) for nk, _, nv, _ in items)
        else:
            for nk, _, nv, v in items:
                if nv is not v:
                    obj[nk] = nv
        return obj
    if isinstance(obj, set):
        seen[key] = obj
        new_items = [_plain(item, seen) for item in obj]
        if any(n is not o for n, o in zip(new_items, obj, strict=True)):
            obj.clear()
            obj.update(new_items)
        return obj
    if isinstance(obj, tuple | frozenset):
        old = list(obj)
        new_items = [_plain(item, seen) for item in old]
        out = obj if all(n is o for n, o in zip(new_items, old, strict=True)) else kind(new_items)
        seen[key] = out
        return out
    return obj  # numpy scalars, slices, ranges
