"""load_pickle's bounds hold by design (issue 50): the fault audit's reproductions, the scan
against the unpickler's own parse, and a property over generated and mutated pickles.

The property: whatever the bytes, ``load_pickle`` returns or raises ``ValueError`` (its
``UnsafePickleError`` is one), its peak traced memory stays under 16x the file's size
plus 64 MiB, and it ends (a hang guard, not a timing assertion). Both engines run it: the
compiled scan with the C unpickler (numba present) and the pure-Python unpickler.
"""

from __future__ import annotations

import contextlib
import pickle
import signal
import tracemalloc
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dego.data import UnsafePickleError, _pickle_scan, load_pickle, safe_pickle

ENGINES = ["python"] + (["c"] if _pickle_scan.compiled_scan() is not None else [])
MEMORY_PER_BYTE = 16
MEMORY_ALLOWANCE = 64 << 20


def _unicode(text: bytes) -> bytes:
    return b"X" + len(text).to_bytes(4, "little") + text


def _str_of_a_list_dag(levels: int) -> bytes:
    """``str(l)``, ``l = [l', l']`` nested ``levels`` deep through the memo: 2**levels
    reprs of ``None`` from a few bytes a level."""
    data = b"\x80\x02cbuiltins\nstr\n]Naq\x000"
    for k in range(levels):
        data += b"](h%sh%seq%s0" % (bytes([k]), bytes([k]), bytes([k + 1]))
    return data + b"h" + bytes([levels]) + b"\x85R."


AUDIT = {
    # protocol 0's INST reached bytearray unchecked: a 1 GiB bytearray from 34 bytes
    "inst-bytearray": b"(I1073741824\nibuiltins\nbytearray\n.",
    # protocol 1's OBJ: list(range(10**8)) from 42 bytes
    "obj-list-range": b"(cbuiltins\nlist\ncbuiltins\nrange\n(J\x00\xe1\xf5\x05tRo.",
    # str() of a list DAG: 2**22 reprs
    "str-of-a-dag": _str_of_a_list_dag(22),
    # list() of one memoised range(90_000), 300 times: each call within the former per-call
    # limit (16 items per byte + 65,536), together 27 M items from 1.8 KB
    "repeated-range": b"\x80\x02cbuiltins\nrange\nJ\x90_\x01\x00\x85Rq\x00cbuiltins\nlist\nq\x01("
    + b"h\x01h\x00\x85R" * 300
    + b"l.",
    # str(b'abc', 'nope'): a LookupError escaped
    "unknown-codec": b"\x80\x03cbuiltins\nstr\nC\x03abc" + _unicode(b"nope") + b"\x86R.",
    # a bytearray extended while an array views its buffer: a BufferError escaped
    "buffer-export": b"\x80\x02cbuiltins\nbytearray\nC\x08abcdefgh\x85Rq\x010"
    + b"cnumpy._core.numeric\n_frombuffer\n(h\x01cnumpy\ndtype\n"
    + _unicode(b"u1")
    + b"\x89\x88\x87RK\x08\x85"
    + _unicode(b"C")
    + b"tRh\x01(K\x01K\x02e\x86.",
    # hashing a tuple DAG: ((),()) nested 40 deep by DUP is 2**40 nodes, hashed as a key
    "hashed-tuple-dag": b"\x80\x02}q\x00)" + b"2\x86" * 40 + b"Ns.",
    # LONG_BINPUT 2**30: the C unpickler's memo array would grow to 16 GB (zeroed)
    "memo-index": b"\x80\x02Nr\x00\x00\x00\x40.",
    # BINBYTES8 of 2**56: allocated before it is read
    "binbytes8": b"\x80\x04\x8e\x00\x00\x00\x00\x00\x00\x00\x01.",
}


class _HangError(Exception):
    pass


@contextlib.contextmanager
def _hang_guard(seconds: int) -> Iterator[None]:
    """Fail (not hang) when the block runs past ``seconds``: a guard, not a timing check."""

    def stop(signum: int, frame: Any) -> None:
        raise _HangError(f"still loading after {seconds} s")

    previous = signal.signal(signal.SIGALRM, stop)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def _bounded_load(path: Path, engine: str) -> tuple[str, int]:
    """(``"loaded"`` or the refusal's class, peak traced bytes) of one load."""
    tracemalloc.start()
    try:
        with _hang_guard(120):
            safe_pickle._load(path, engine)
        outcome = "loaded"
    except ValueError as error:  # UnsafePickleError is one
        assert str(path) in str(error)
        outcome = type(error).__name__
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return outcome, peak


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("name", list(AUDIT))
def test_the_audit_s_files_are_refused_within_bounds(
    tmp_path: Path, engine: str, name: str
) -> None:
    path = tmp_path / f"{name}.pkl"
    path.write_bytes(AUDIT[name])
    safe_pickle._load(_benign(tmp_path), engine)  # first use: compiles, checks arguments
    outcome, peak = _bounded_load(path, engine)
    # the pure-Python unpickler's memo is a dict: a far index there is one entry, harmless
    harmless = name == "memo-index" and engine == "python"
    assert outcome in ("UnsafePickleError", "ValueError") or harmless, outcome
    assert peak <= MEMORY_PER_BYTE * len(AUDIT[name]) + MEMORY_ALLOWANCE, peak


def _benign(folder: Path) -> Path:
    path = folder / "benign.pkl"
    path.write_bytes(pickle.dumps({"a": [1, 2.0, (3,)], "b": np.arange(3)}, protocol=2))
    return path


@pytest.mark.parametrize(
    "name, error, pattern",
    [
        ("inst-bytearray", UnsafePickleError, r"bytearray\(1073741824\): a size argument"),
        ("obj-list-range", UnsafePickleError, r"list\(\) of 100,000,000 items"),
        ("str-of-a-dag", UnsafePickleError, r"str\(\) of anything but a string"),
        ("repeated-range", UnsafePickleError, r"list\(\) of 90,000 items: 3,600,000 bytes"),
        ("unknown-codec", UnsafePickleError, r"str\(\) of anything but a string"),
        ("buffer-export", ValueError, r"BufferError"),
        ("hashed-tuple-dag", ValueError, r"tuple nesting shared references"),
    ],
)
def test_refusals_name_what_was_refused(
    tmp_path: Path, name: str, error: type[Exception], pattern: str
) -> None:
    path = tmp_path / f"{name}.pkl"
    path.write_bytes(AUDIT[name])
    with pytest.raises(error, match=pattern):
        load_pickle(path)


# -- the compiled scan parses as the unpickler does ---------------------------------------

_leaf = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.floats(allow_nan=False),
    st.text(max_size=300),
    st.binary(max_size=300),
)
_data = st.recursive(
    _leaf,
    lambda inner: st.one_of(
        st.lists(inner, max_size=5),
        st.tuples(inner, inner),
        st.dictionaries(st.text(max_size=4), inner, max_size=4),
        st.frozensets(st.integers(), max_size=4),
    ),
    max_leaves=20,
)


@settings(max_examples=60, suppress_health_check=[HealthCheck.too_slow])
@given(_data, st.integers(0, 5))
def test_the_scan_accepts_what_the_pickler_writes(data: Any, protocol: int) -> None:
    written = pickle.dumps(data, protocol=protocol)
    array = np.frombuffer(written, dtype=np.uint8)
    assert _pickle_scan.python_scan(array) == (_pickle_scan.OK, len(written))
    compiled = _pickle_scan.compiled_scan()
    if compiled is not None:
        assert tuple(int(v) for v in compiled(array)) == (_pickle_scan.OK, len(written))


# -- the property: generated opcode programs and mutated real pickles ---------------------

_GLOBALS = [
    b"builtins\nlist",
    b"builtins\ntuple",
    b"builtins\nset",
    b"builtins\nfrozenset",
    b"builtins\ndict",
    b"builtins\nstr",
    b"builtins\nbytes",
    b"builtins\nbytearray",
    b"builtins\nrange",
    b"builtins\nint",
    b"builtins\ncomplex",
    b"collections\nOrderedDict",
    b"collections\ndefaultdict",
    b"_codecs\nencode",
    b"numpy\ndtype",
    b"numpy\nndarray",
    b"numpy._core.multiarray\n_reconstruct",
    b"numpy._core.multiarray\nscalar",
    b"numpy._core.numeric\n_frombuffer",
    b"os\nsystem",
    b"builtins\neval",
]
_NUMBERS = [0, 1, 7, 255, 256, 65535, 2**20, 2**30, 2**31 - 1, 2**31, 2**32 - 1]

_fragment = st.one_of(
    st.sampled_from(
        [bytes([c]) for c in b"N)]}\x8f(tlde\x85\x86\x87asu\x90\x9102\x94Rb\x81\x92o1\x88\x89"]
    ),
    st.builds(lambda g: b"c" + g + b"\n", st.sampled_from(_GLOBALS)),
    st.builds(lambda g: b"(i" + g + b"\n", st.sampled_from(_GLOBALS)),
    st.builds(lambda n: b"J" + (n % 2**32).to_bytes(4, "little"), st.sampled_from(_NUMBERS)),
    st.builds(lambda n: b"K" + bytes([n % 256]), st.sampled_from(_NUMBERS)),
    st.builds(lambda n: b"I%d\n" % n, st.sampled_from(_NUMBERS)),
    st.builds(lambda n: b"\x8a\x05" + (n * 64).to_bytes(5, "little"), st.sampled_from(_NUMBERS)),
    st.builds(lambda n: b"q" + bytes([n % 256]), st.integers(0, 5)),
    st.builds(lambda n: b"h" + bytes([n % 256]), st.integers(0, 5)),
    st.builds(lambda n: b"r" + (n % 2**32).to_bytes(4, "little"), st.sampled_from(_NUMBERS)),
    st.builds(lambda n: b"j" + (n % 2**32).to_bytes(4, "little"), st.sampled_from(_NUMBERS)),
    st.builds(lambda n: b"p%d\n" % n, st.sampled_from(_NUMBERS)),
    st.builds(lambda n: b"g%d\n" % n, st.integers(0, 5)),
    st.builds(
        lambda t: b"\x8c" + bytes([len(t)]) + t,
        st.sampled_from([b"u1", b"f8", b"O", b"latin1", b"C", b"nope", b"abc"]),
    ),
    st.builds(lambda b: b"C" + bytes([len(b)]) + b, st.binary(max_size=16)),
    st.builds(lambda n: b"B" + (n % 2**32).to_bytes(4, "little"), st.sampled_from(_NUMBERS)),
    st.builds(lambda n: b"\x8e" + (n * 2**20).to_bytes(8, "little"), st.sampled_from(_NUMBERS)),
    st.builds(lambda n: b"\x95" + (n % 2**32).to_bytes(8, "little"), st.sampled_from(_NUMBERS)),
    st.sampled_from([b"2\x86" * 12, b"h\x00h\x00\x86q\x00" * 12, b"](h\x00h\x00eq\x000" * 6]),
)
_program = st.builds(
    lambda proto, parts: (b"\x80" + bytes([proto]) if proto >= 2 else b"") + b"".join(parts) + b".",
    st.integers(0, 5),
    st.lists(_fragment, min_size=1, max_size=40),
)


def _mutate(data: bytes, edits: list[tuple[int, int, bytes]]) -> bytes:
    out = bytearray(data)
    for kind, where, value in edits:
        at = where % (len(out) + 1)
        if kind == 0:
            out[at:at] = value  # insert
        elif kind == 1:
            del out[at : at + len(value)]  # delete
        else:
            out[at : at + len(value)] = value  # overwrite
    return bytes(out)


_real = st.builds(
    lambda data, protocol: pickle.dumps(data, protocol=protocol),
    st.one_of(
        _data,
        st.builds(lambda n: {"a": np.arange(n, dtype=np.float64), "n": [n]}, st.integers(0, 9)),
    ),
    st.integers(0, 5),
)
_edit = st.tuples(
    st.integers(0, 2),
    st.integers(0, 2**16),
    st.one_of(
        st.binary(min_size=1, max_size=4),
        st.sampled_from(
            [b"\xff\xff\xff\x7f", b"r\x00\x00\x00\x40", b"(", b"\x86", b"2", b".", b"\x94"]
        ),
    ),
)
_mutated = st.builds(_mutate, _real, st.lists(_edit, min_size=1, max_size=4))


def _check(data: bytes, engine: str, folder: Path) -> None:
    path = folder / f"fuzz-{engine}.pkl"
    path.write_bytes(data)
    _, peak = _bounded_load(path, engine)
    assert peak <= MEMORY_PER_BYTE * len(data) + MEMORY_ALLOWANCE, (peak, data[:200])


def _property(engine: str, data: bytes, tmp_path: Path) -> None:
    _check(data, engine, tmp_path)


def _property_test(examples: int) -> Any:
    """The property over ``examples`` generated and mutated pickles, per engine."""
    test = given(data=st.one_of(_program, _mutated))(_property)
    checks = [HealthCheck.too_slow, HealthCheck.function_scoped_fixture]
    test = settings(max_examples=examples, deadline=None, suppress_health_check=checks)(test)
    return pytest.mark.parametrize("engine", ENGINES)(test)


test_any_bytes_load_or_are_refused_within_the_memory_bound = _property_test(150)
test_any_bytes_load_or_are_refused_within_the_memory_bound_long = pytest.mark.slow(
    _property_test(1500)
)
