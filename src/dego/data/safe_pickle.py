"""A restricted unpickler for data files (mmdet3d infos): plain containers and numpy only.

:func:`load_pickle` reads a pickle whose globals resolve only through an allow-list: the
builtin containers and values (``dict``, ``list``, ``tuple``, ``set``, ``frozenset``,
``str``, ``bytes``, ``bytearray``, ``int``, ``float``, ``complex``, ``bool``, ``slice``,
``range``), ``collections.OrderedDict`` and ``collections.defaultdict``,
``_codecs.encode`` (latin-1 only: how protocol 2 stores bytes) and what numpy's own
pickles name (``_reconstruct``, ``ndarray``, ``dtype``, ``scalar``, ``_frombuffer``,
under ``numpy.core`` of numpy 1.x or ``numpy._core`` of numpy 2.x). Every other global
(``os.system``, ``builtins.eval``, any class) and every persistent id raises
:class:`UnsafePickleError` before anything is called, so nothing in the file can run
code. Objects inside object arrays go through the same check.

**What the file can make the loader allocate is bounded by design, not opcode by
opcode.** A name the allow-list admits resolves to a checked constructor, never to the
builtin itself, so every way a pickle can call it (``REDUCE``, ``NEWOBJ``,
``NEWOBJ_EX``, protocol 0's ``INST``, protocol 1's ``OBJ``) goes through the same check:
no size arguments (``bytes(2**36)``), no ``str`` or ``bytes`` of a container, sized
arguments only (no iterators), and one running budget for everything the constructors
and numpy's array states build, :data:`BUDGET_PER_BYTE` bytes per byte of the file plus
:data:`BUDGET_ALLOWANCE` (shared references cannot multiply it: ``list()`` of one
memoised ``range`` a thousand times draws on the same budget). The rest of what a load
builds is made by opcodes, one object per opcode (as ``pickle.load`` does). Reads past
the end of the file and memo indices far beyond the entries made are refused before
they are attempted (:mod:`dego.data._pickle_scan`).

numpy's pickled state is not trusted either: ``numpy.ndarray`` is never callable from
the file (``ndarray(shape, object, buffer)`` would read raw memory as pointers), and
every dtype is rebuilt through numpy's validating constructor before an array or
scalar uses it (a pickled dtype state may carry field offsets past its item size).

With numba installed (the ``eval`` extra) the file is first scanned by a compiled pass
and then read by Python's C unpickler; without it, by the pure-Python unpickler (whose
memo is a dict and whose reads are checked one by one), several times slower. Either way
the cyclic garbage collector is paused for the load (process-wide, as ``gc.disable``):
the millions of containers a large file makes are not garbage yet.
"""

from __future__ import annotations

import _compat_pickle
import collections
import gc
import io
import math
import os
import pickle
import struct
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar, NoReturn, cast

import numpy as np

from dego._npz import open_regular_file
from dego._typing import typechecked
from dego.data import _pickle_scan

PathLike = str | os.PathLike[str]

__all__ = ["UnsafePickleError", "load_pickle"]

_ALLOWED_MESSAGE = (
    "only plain containers (dict, list, tuple, set), numbers, strings and numpy arrays are allowed"
)

BUDGET_PER_BYTE = 8
"""Bytes the allowed constructors and numpy's array states may build, all together, per
byte of the file (a real infos file uses about two: protocol 2 stores each array's data
twice over, as a string and as the array)."""
BUDGET_ALLOWANCE = 16 << 20
"""Bytes allowed on top of :data:`BUDGET_PER_BYTE` per byte, whatever the file's size."""


def budget(file_size: int) -> int:
    """The bytes the allowed constructors may build, together, from a file of
    ``file_size`` bytes."""
    return BUDGET_PER_BYTE * file_size + BUDGET_ALLOWANCE


class UnsafePickleError(pickle.UnpicklingError, ValueError):
    """A pickle names a global or persistent id outside the allow-list of :func:`load_pickle`,
    or asks an allowed constructor for more than the file can justify.

    Subclasses both ``pickle.UnpicklingError`` and ``ValueError``; the message names the
    file and the refused global as ``module.name`` (or the refused size).
    """


try:  # numpy >= 2
    from numpy._core import multiarray as _multiarray
    from numpy._core import numeric as _numeric
except ImportError:  # pragma: no cover - numpy 1.x
    from numpy.core import multiarray as _multiarray  # type: ignore[no-redef]
    from numpy.core import numeric as _numeric  # type: ignore[no-redef]


# -- the running budget of one load ------------------------------------------------------

_LOAD = threading.local()
"""The load in progress on this thread: its budget and its dtype checks."""


class _Budget:
    def __init__(self, size: int) -> None:
        self.left = budget(size)
        self.size = size

    def refuse(self, nbytes: int, what: str) -> NoReturn:
        raise UnsafePickleError(
            f"refused {what}: {nbytes:,} bytes where {max(self.left, 0):,} of the "
            f"{budget(self.size):,} a {self.size:,}-byte file may build remain"
        )


def _charge(nbytes: int, what: str, count: int) -> None:
    """Charge ``nbytes`` to this thread's load; ``what.format(count)`` names it if refused."""
    current: _Budget | None = getattr(_LOAD, "budget", None)
    if current is not None:  # outside a load (a user's call later on): nothing to bound
        if nbytes > current.left:
            current.refuse(nbytes, what.format(count))
        current.left -= nbytes


# -- the checked constructors ------------------------------------------------------------

_SIZED = (list, tuple, set, frozenset, dict, str, bytes, bytearray, range)
_HASHED = (set, frozenset, dict, collections.OrderedDict, collections.defaultdict)


def _item_bytes(kind: type) -> int:
    """Bytes one item costs in a container of ``kind`` (pointers; hash tables more)."""
    return 32 if issubclass(kind, _HASHED) else 8


_MADE_PER_ITEM: dict[type, int] = {range: 32, str: 64}
"""Bytes of the new object each item of these arguments makes when iterated (an int, a
one-character string; an array's scalar or sub-array: 112)."""


def _sized(kind: type, value: Any) -> int:
    """``len(value)`` of a sized argument; anything else (an iterator, a number) refused."""
    if isinstance(value, np.ndarray):
        return int(value.size)
    if not isinstance(value, _SIZED):
        raise UnsafePickleError(
            f"refused {kind.__name__}() of a {type(value).__name__}: only sized containers"
        )
    return len(value)


class _Constructor(type):
    """The type of the checked constructors: a pickle cannot change them (``BUILD`` on a
    global sets attributes)."""

    kind: type

    def __setattr__(cls, name: str, value: Any) -> None:
        raise UnsafePickleError(f"refused setting {name!r} on {cls.__name__}")

    def __repr__(cls) -> str:
        return f"<checked {cls.kind.__name__}>"


class _Checked(metaclass=_Constructor):
    """Stands for an allowed builtin: calling it (or its ``__new__``) checks the arguments,
    charges the load's budget and returns the builtin's object, never an instance."""

    kind: ClassVar[type] = object

    def __new__(cls, *args: Any, **kwargs: Any) -> Any:
        return cls.build(*args, **kwargs)

    @classmethod
    def build(cls, *args: Any, **kwargs: Any) -> Any:
        raise NotImplementedError


class _Container(_Checked):
    """``list``, ``tuple``, ``set``, ``frozenset``, ``dict``, ``OrderedDict``: of at most
    one sized argument (and, for the dicts, keywords)."""

    @classmethod
    def build(cls, *args: Any, **kwargs: Any) -> Any:
        if len(args) > 1 or (kwargs and not issubclass(cls.kind, dict)):
            raise UnsafePickleError(f"refused {cls.kind.__name__}() of {len(args)} arguments")
        items = (_sized(cls.kind, args[0]) if args else 0) + len(kwargs)
        # iterating a range, a string or an array makes a new object per item
        made = (
            0
            if not args
            else 112
            if isinstance(args[0], np.ndarray)
            else _MADE_PER_ITEM.get(type(args[0]), 0)
        )
        cost = items * (_item_bytes(cls.kind) + made)
        _charge(cost, cls.kind.__name__ + "() of {:,} items", items)
        nested = args and cls.kind in (tuple, frozenset)  # the scan counts the opcodes' nesting
        if nested and any(type(item) in (tuple, frozenset) for item in args[0]):
            raise UnsafePickleError(f"refused {cls.kind.__name__}() of nested tuples")
        return cls.kind(*args, **kwargs)


class _DefaultDict(_Checked):
    kind = collections.defaultdict

    @classmethod
    def build(cls, factory: Any = None, *args: Any) -> Any:
        if factory is not None and not (
            isinstance(factory, _Constructor) and issubclass(factory, _Container)
        ):
            raise UnsafePickleError("defaultdict's factory may only be an allowed container")
        real = factory.kind if factory is not None else None
        items = _sized(dict, args[0]) if args else 0
        if len(args) > 1:
            raise UnsafePickleError(f"refused defaultdict() of {1 + len(args)} arguments")
        _charge(items * _item_bytes(dict), "defaultdict() of {:,} items", items)
        return collections.defaultdict(real, *args)


_ENCODINGS = frozenset({"latin1", "latin-1", "latin_1", "utf-8", "utf8", "ascii"})


class _Binary(_Checked):
    """``bytes`` and ``bytearray``: of nothing, of bytes or a list of ints, or of a string
    and an encoding; never of a size."""

    @classmethod
    def build(cls, *args: Any) -> Any:
        name = cls.kind.__name__
        if args and isinstance(args[0], int):
            raise UnsafePickleError(
                f"refused {name}({args[0]}): a size argument would allocate memory the "
                "file does not hold"
            )
        if len(args) == 2 and isinstance(args[0], str) and args[1] in _ENCODINGS:
            _charge(4 * len(args[0]), name + "() of {:,} characters", len(args[0]))
            return cls.kind(args[0], args[1])
        if len(args) > 1 or (args and not isinstance(args[0], bytes | bytearray | list | tuple)):
            raise UnsafePickleError(f"refused {name}() of these arguments")
        count = len(args[0]) if args else 0
        _charge(count, name + "() of {:,} bytes", count)
        return cls.kind(*args)


class _Text(_Checked):
    """``str``: of nothing or of a string (no ``str`` of a container: its repr could be
    exponentially long over shared references, nor a decode with any codec)."""

    kind = str

    @classmethod
    def build(cls, *args: Any) -> Any:
        if len(args) > 1 or (args and not isinstance(args[0], str)):
            raise UnsafePickleError("refused str() of anything but a string")
        return str(*args)


_NUMBERS = (int, float, complex, bool, str, np.generic)


class _Value(_Checked):
    """``int``, ``float``, ``complex``, ``bool``, ``slice``, ``range``: of numbers (or a
    numeral) only."""

    @classmethod
    def build(cls, *args: Any) -> Any:
        if len(args) > 3 or any(not isinstance(a, _NUMBERS) and a is not None for a in args):
            raise UnsafePickleError(f"refused {cls.kind.__name__}() of these arguments")
        return cls.kind(*args)


def _checked(kind: type, base: type[_Checked]) -> type[_Checked]:
    return cast(type[_Checked], _Constructor(f"Checked{kind.__name__}", (base,), {"kind": kind}))


_BUILTINS: dict[str, type[_Checked]] = {
    **{k.__name__: _checked(k, _Container) for k in (list, tuple, set, frozenset, dict)},
    **{k.__name__: _checked(k, _Binary) for k in (bytes, bytearray)},
    **{k.__name__: _checked(k, _Value) for k in (int, float, complex, bool, slice, range)},
    "str": _Text,
}


class _CheckedArray(np.ndarray):
    """What ``_reconstruct`` builds: its ``__setstate__`` checks the dtype and charges the
    load's budget before numpy fills it.

    :func:`load_pickle` turns every such array into a plain ``numpy.ndarray`` (a view).
    """

    __slots__ = ()

    def __setstate__(self, state: Any) -> None:
        if type(state) is not tuple or len(state) not in (4, 5):
            raise ValueError("numpy.ndarray: malformed pickled array state")
        if len(state) == 5:
            version, shape, dtype, fortran, data = state
        else:
            version, (shape, dtype, fortran, data) = 0, state
        if type(dtype) is not _PickledDtype:
            raise ValueError(f"expected a numpy dtype, got {type(dtype).__name__}")
        dtype = dtype.built
        count = math.prod(shape) if type(shape) is tuple else -1
        if type(count) is not int or count < 0 or (shape and min(shape) < 0):
            raise ValueError("numpy.ndarray: malformed pickled shape")
        _charge(8 * count if dtype.hasobject else count * dtype.itemsize, _ARRAY, count)
        rebuilt = (
            (version, shape, dtype, fortran, data)
            if len(state) == 5
            else (shape, dtype, fortran, data)
        )
        _ndarray_setstate(self, rebuilt)  # type: ignore[arg-type]


_ARRAY = "an array of {:,} items"
_ndarray_setstate = np.ndarray.__setstate__


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


class _PickledDtype:
    """What the file's ``numpy.dtype(...)`` builds: a dtype made by numpy's constructors,
    whose pickled state (``BUILD``) is turned into constructor arguments and checked
    against the state numpy itself would pickle, never handed to numpy's
    ``dtype.__setstate__`` (which trusts it: field offsets past the item size, or a
    ``SystemError``). Arrays, scalars and :func:`load_pickle`'s result get the dtype."""

    __slots__ = ("align", "built")

    def __init__(self, built: np.dtype, align: bool) -> None:
        self.built, self.align = built, align

    def __setstate__(self, state: Any) -> None:
        self.built = _dtype_from_state(self.built, state, self.align)

    def __reduce__(self) -> Any:
        raise TypeError("not picklable")


def _checked_dtype(dtype: Any) -> np.dtype:
    """The dtype a file's dtype object stands for (``ValueError`` for anything else)."""
    if type(dtype) is not _PickledDtype:
        raise ValueError(f"expected a numpy dtype, got {type(dtype).__name__}")
    return dtype.built


def _dtype_from_state(base: np.dtype, state: Any, align: bool) -> np.dtype:
    """The dtype ``state`` (numpy's pickled dtype state) describes, built by numpy's
    constructors from ``base`` (``ValueError`` if numpy would pickle it differently)."""
    if type(state) is not tuple or len(state) not in (8, 9):
        raise ValueError("numpy.dtype: malformed pickled state")
    order, sub, names, fields = state[1:5]
    try:
        if sub is not None:
            if type(sub) is not tuple or len(sub) != 2:
                raise ValueError("malformed subarray")
            built = np.dtype((_checked_dtype(sub[0]), sub[1]))
        elif names is not None:
            if (
                type(names) is not tuple
                or type(fields) is not dict
                or not set(names) <= set(fields)
            ):
                raise ValueError("malformed fields")
            entries = [fields[name] for name in names]
            if any(type(entry) is not tuple or len(entry) not in (2, 3) for entry in entries):
                raise ValueError("malformed fields")
            # numpy's stubs type a fields dict as a TypedDict of literal keys; this one is built
            spec: Any = {
                "names": list(names),
                "formats": [_checked_dtype(entry[0]) for entry in entries],
                "offsets": [int(entry[1]) for entry in entries],
                "itemsize": int(state[5]),
            }
            if any(len(entry) > 2 for entry in entries):
                spec["titles"] = [entry[2] if len(entry) > 2 else None for entry in entries]
            aligned = align or (type(state[7]) is int and state[7] & _ALIGNED_STRUCT)
            built = np.dtype(spec, align=bool(aligned))
        elif len(state) == 9 and base.kind in "mM":  # datetime64, timedelta64: the unit
            unit, count = state[8][1][:2]
            built = np.dtype(f"{base.str[:2]}8[{int(count)}{unit.decode('ascii')}]")
        else:
            built = base
        if order in ("<", ">") and built.byteorder != "|":
            built = built.newbyteorder(order)
        expected = built.__reduce__()[2]
    except (TypeError, ValueError, KeyError, IndexError, OverflowError, AttributeError) as exc:
        raise ValueError(f"malformed numpy dtype state ({exc})") from None
    if _plain_state(state) != expected:
        raise ValueError(f"malformed numpy dtype state: numpy pickles {built!r} differently")
    return built


_ALIGNED_STRUCT = 0x80
"""numpy's ``NPY_ALIGNED_STRUCT`` flag in a pickled dtype state's flags."""


def _plain_state(state: Any) -> Any:
    """``state`` with every file dtype object as its dtype (to compare with numpy's)."""
    if type(state) is _PickledDtype:
        return state.built
    if type(state) is tuple:
        return tuple(_plain_state(item) for item in state)
    if type(state) is dict:
        return {key: _plain_state(value) for key, value in state.items()}
    return state


_EMPTY = (0,)


def _reconstruct(subtype: Any, shape: Any, typecode: Any) -> np.ndarray:
    if subtype is not _NDARRAY:
        raise UnsafePickleError(
            f"numpy _reconstruct may only rebuild numpy.ndarray, got {type(subtype).__name__}"
        )
    return _multiarray._reconstruct(_CheckedArray, _EMPTY, b"b")  # type: ignore[return-value]


def _scalar(dtype: Any, *data: Any) -> Any:
    if data and isinstance(data[0], bytes | bytearray):
        _charge(len(data[0]), "a numpy scalar of {:,} bytes", len(data[0]))
    return _multiarray.scalar(_checked_dtype(dtype), *data)


def _frombuffer(buffer: Any, dtype: Any, shape: Any, order: Any) -> np.ndarray:
    if not isinstance(buffer, bytes | bytearray):
        raise ValueError("numpy _frombuffer: expected in-band bytes")
    # numpy's stubs leave out the private _frombuffer (what ndarray.__reduce__ pickles)
    array = _numeric._frombuffer(  # type: ignore[attr-defined]
        buffer, _checked_dtype(dtype), shape, order
    )
    return cast(np.ndarray, array.view(_CheckedArray))  # a BUILD on it is checked too


def _dtype(obj: Any, align: Any = False, copy: Any = False) -> _PickledDtype:
    if not isinstance(obj, str):
        raise ValueError(f"numpy.dtype: expected a type string, got {type(obj).__name__}")
    return _PickledDtype(np.dtype(obj, bool(align), True), bool(align))


def _latin1_encode(text: Any, encoding: Any = "utf-8") -> bytes:
    # protocol 2 stores bytes as _codecs.encode(str, "latin1")
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1", "latin_1"):
        raise UnsafePickleError("_codecs.encode is allowed only for latin-1 strings")
    _charge(len(text), "_codecs.encode() of {:,} characters", len(text))
    return text.encode("latin-1")


_NUMPY = {
    "_reconstruct": ("multiarray", _reconstruct),
    "scalar": ("multiarray", _scalar),
    "_frombuffer": ("numeric", _frombuffer),
}

_ALLOWED: dict[tuple[str, str], Any] = {
    **{("builtins", name): checked for name, checked in _BUILTINS.items()},
    ("collections", "OrderedDict"): _checked(collections.OrderedDict, _Container),
    ("collections", "defaultdict"): _DefaultDict,
    ("_codecs", "encode"): _latin1_encode,
    ("numpy", "ndarray"): _NDARRAY,
    ("numpy", "dtype"): _dtype,
    **{
        (f"numpy.{package}.{module}", name): function
        for package in ("core", "_core")
        for name, (module, function) in _NUMPY.items()
    },
}


def _allowed(path: Path, module: str, name: str) -> Any:
    """What ``module.name`` resolves to (:class:`UnsafePickleError` if not allowed)."""
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
        f"{path}: refused the global {key[0]}.{key[1]}{written}: {_ALLOWED_MESSAGE}"
    )


def _refuse_persistent_id(path: Path, pid: Any) -> Any:
    # the repr of a file's object could be exponentially long (shared references)
    shown = repr(pid)[:80] if isinstance(pid, str | bytes | int) else type(pid).__name__
    raise UnsafePickleError(f"{path}: refused the persistent id {shown}: {_ALLOWED_MESSAGE}")


# -- the two unpicklers ------------------------------------------------------------------


class _AllowList:
    """What both unpicklers resolve: allowed globals only, no persistent ids."""

    _path: Path

    def find_class(self, module: str, name: str) -> Any:
        return _allowed(self._path, module, name)

    def persistent_load(self, pid: Any) -> Any:
        return _refuse_persistent_id(self._path, pid)


class _FastUnpickler(_AllowList, pickle.Unpickler):  # the C one: run only on a scanned file
    def __init__(self, file: Any, path: Path) -> None:
        super().__init__(file)
        self._path = path


class _BoundedFile:
    """The file as the pure-Python unpickler reads it: a read of more than the rest of
    the file is refused before any buffer for it is allocated."""

    def __init__(self, stream: Any, size: int) -> None:
        self._stream, self._size = stream, size

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

    def tell(self) -> int:
        return cast(int, self._stream.tell())


class _PythonUnpickler(_AllowList, pickle._Unpickler):  # the pure-Python one: memo a dict
    def __init__(self, file: Any, path: Path, size: int) -> None:
        self._bounded = _BoundedFile(file, size)
        super().__init__(self._bounded)
        self._path = path
        self._tuple_nodes: dict[int, tuple[Any, int]] = {}  # id -> (tuple, nodes)

    def _count_nodes(self) -> None:
        """The tuple (or frozenset) just built: its nodes, counting shared ones as often as
        they are referenced, bounded as the compiled scan bounds them."""
        made = self.stack[-1]  # type: ignore[attr-defined]
        nodes = 1
        for item in made:
            known = self._tuple_nodes.get(id(item))
            nodes += known[1] if known is not None and known[0] is item else 1
        read = self._bounded.tell()
        bound = _pickle_scan.TUPLE_NODES_PER_BYTE * read + _pickle_scan.TUPLE_NODE_ALLOWANCE
        if nodes > bound:
            raise ValueError(_pickle_scan.REASONS[_pickle_scan.NESTING])
        self._tuple_nodes[id(made)] = (made, nodes)

    dispatch: ClassVar[dict[int, Callable[[Any], None]]] = dict(pickle._Unpickler.dispatch)
    for _code in (pickle.TUPLE, pickle.TUPLE1, pickle.TUPLE2, pickle.TUPLE3, pickle.FROZENSET):

        def _counted(self: Any, _load: Any = dispatch[_code[0]]) -> None:
            _load(self)
            self._count_nodes()

        dispatch[_code[0]] = _counted
    del _code, _counted


_CORRUPT = (
    pickle.UnpicklingError,
    EOFError,
    ValueError,
    TypeError,
    AttributeError,
    LookupError,  # IndexError, KeyError, an unknown codec
    BufferError,
    struct.error,
    OverflowError,
    RuntimeError,
    MemoryError,
    RecursionError,
    UnicodeError,
    ImportError,
)


def _read(file: Path, stream: Any, engine: str) -> Any:
    size = os.fstat(stream.fileno()).st_size
    scan = _pickle_scan.compiled_scan() if engine in ("auto", "c") else None
    if engine == "c" and scan is None:
        raise RuntimeError("the c engine needs numba (pip install numba)")
    _LOAD.budget = _Budget(size)
    collecting = gc.isenabled()
    gc.disable()  # millions of new containers, none garbage yet: no collection passes
    try:
        if scan is None:
            return _plain(_PythonUnpickler(stream, file, size).load(), {})
        data = stream.read()
        if len(data) != size:
            raise ValueError("the file changed while it was read")
        reason, position = scan(np.frombuffer(data, dtype=np.uint8))
        if reason != _pickle_scan.OK:
            raise ValueError(f"{_pickle_scan.REASONS[int(reason)]} (at byte {int(position):,})")
        # buffered: the C unpickler then reads ahead instead of calling read() per opcode
        return _plain(_FastUnpickler(io.BufferedReader(io.BytesIO(data)), file).load(), {})
    finally:
        del _LOAD.budget
        if collecting:
            gc.enable()


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
            file and the refused global ``module.name`` (or persistent id, or the size an
            allowed constructor was asked for); nothing from the file has been called.
        ValueError: naming the file when it is truncated, corrupt or holds malformed
            numpy state.
    """
    return _load(Path(path), "auto")


def _load(file: Path, engine: str) -> object:
    """:func:`load_pickle` with the unpickler ``engine`` names: ``"c"`` (numba's scan, then
    the C unpickler), ``"python"`` (the pure-Python unpickler) or ``"auto"`` (``"c"`` where
    numba is installed)."""
    if not file.exists():
        raise FileNotFoundError(f"{file}: no such pickle file")
    if file.is_dir():
        raise IsADirectoryError(f"{file}: expected a pickle file, got a directory")
    try:
        # A FIFO (or socket, device) is refused here rather than blocking in open().
        with open_regular_file(file, "a pickle file") as stream:
            return _read(file, stream, engine)
    except UnsafePickleError as exc:
        if str(file) in str(exc):
            raise
        raise UnsafePickleError(f"{file}: {exc}") from None
    except _CORRUPT as exc:
        # args[0], not str(exc): a KeyError's str is the repr of the file's key
        detail = exc.args[0] if exc.args and isinstance(exc.args[0], str) else ""
        raise ValueError(
            f"{file}: not a readable pickle of plain data ({type(exc).__name__}: {detail[:300]})"
        ) from None


def _plain_keys(obj: dict[Any, Any], seen: dict[int, Any]) -> dict[Any, Any]:
    """:func:`_plain` of a dict with keys that may change (tuples, frozensets)."""
    items = [(_plain(k, seen), k, _plain(v, seen), v) for k, v in obj.items()]
    if any(nk is not k for nk, k, _, _ in items):
        obj.clear()
        obj.update((nk, nv) for nk, _, nv, _ in items)
    else:
        for nk, _, nv, v in items:
            if nv is not v:
                obj[nk] = nv
    return obj


_NUMPY_SCALARS = {kind for kind in np.sctypeDict.values() if not issubclass(kind, np.void)}
_LEAVES = frozenset({str, int, float, bool, bytes, complex, type(None), *_NUMPY_SCALARS})


def _plain(obj: Any, seen: dict[int, Any]) -> Any:
    """``obj`` with every checked array as a plain ndarray, every dtype rebuilt and every
    checked constructor as its builtin.

    Mutable containers are updated in place (shared references and cycles survive);
    tuples and frozensets are rebuilt only when an item changes.
    """
    kind = type(obj)
    if kind in _LEAVES:
        return obj
    key = id(obj)
    if key in seen:
        return seen[key]
    if kind is _CheckedArray:
        out: Any = obj.view(np.ndarray)
        seen[key] = out
        if out.dtype.hasobject:
            for index, item in enumerate(out.flat):
                new = _plain(item, seen)
                if new is not item:
                    out.flat[index] = new
        return out
    if kind is list:
        seen[key] = obj
        for index, item in enumerate(obj):
            if type(item) not in _LEAVES and (new := _plain(item, seen)) is not item:
                obj[index] = new
        return obj
    if isinstance(obj, dict):  # dict, OrderedDict, defaultdict
        seen[key] = obj
        for k, v in obj.items():  # the usual case: leaf keys (str); values changed in place
            if type(k) not in _LEAVES:
                return _plain_keys(obj, seen)
            value_kind = type(v)
            if value_kind in _LEAVES:
                continue
            if value_kind is _CheckedArray and id(v) not in seen and not v.dtype.hasobject:
                seen[id(v)] = obj[k] = v.view(np.ndarray)  # the usual array, inline
            elif (new := _plain(v, seen)) is not v:
                obj[k] = new  # same key: the dict keeps its size and order
        return obj
    if kind is _PickledDtype:
        seen[key] = obj.built
        return obj.built
    if isinstance(obj, _Constructor):  # a global the file only named
        return obj.kind
    if isinstance(obj, list | set):  # set; a list subclass cannot be built
        seen[key] = obj
        new_items = [_plain(item, seen) for item in obj]
        if any(n is not o for n, o in zip(new_items, obj, strict=True)):
            obj.clear()
            obj.extend(new_items) if isinstance(obj, list) else obj.update(new_items)
        return obj
    if isinstance(obj, tuple | frozenset):
        old = list(obj)
        new_items = [_plain(item, seen) for item in old]
        out = obj if all(n is o for n, o in zip(new_items, old, strict=True)) else kind(new_items)
        seen[key] = out
        return out
    return obj  # numpy scalars, slices, ranges, bytearrays
