"""A pass over a pickle's opcodes that makes the C unpickler safe to run on it.

Python's C unpickler allocates two things from numbers a file declares before it reads
what they describe: its memo array grows to twice the largest memo index a ``PUT`` or
``LONG_BINPUT`` names (zeroed: ``LONG_BINPUT 2**30`` in 5 bytes touches 16 GB), and
``BINBYTES``, ``BINBYTES8`` and ``BYTEARRAY8`` allocate their declared length before
reading it. The scan walks the opcodes exactly as the unpickler parses them (each
opcode's argument layout is taken from :mod:`pickletools`) and refuses, before anything is
built, a memo index above the number of memo entries made so far (plus
:data:`MEMO_SLACK`), a length or frame longer than what remains of the file, a line
opcode without its newline and an opcode the unpickler does not know. Everything else
the unpickler allocates is proportional to the opcodes it reads, or made by the
constructors :mod:`dego.data.safe_pickle` allows, which keep their own budget.

The scan is compiled by numba when it is installed (the ``eval`` extra); a Python loop
over tens of millions of opcodes would cost more than the load itself, so without numba
:func:`compiled_scan` returns ``None`` and the caller uses the pure-Python unpickler.
"""

from __future__ import annotations

import functools
import pickletools
from collections.abc import Callable
from typing import Any

import numpy as np

MEMO_SLACK = 1024
"""How far a memo index may run ahead of the number of memo entries made so far (the
pickler numbers them 0, 1, 2, ...; this leaves room for writers with gaps)."""

TUPLE_NODES_PER_BYTE = 16
"""A tuple (or frozenset) the opcodes build may hold, counting every nested tuple as often
as it is referenced, at most this many nodes per byte read so far, plus
:data:`TUPLE_NODE_ALLOWANCE`: hashing a tuple walks all of them, and shared references
(``DUP``, the memo) could otherwise nest 2**60 of them in a few hundred bytes."""
TUPLE_NODE_ALLOWANCE = 4096

# What follows each opcode: its kind, and the width of its fixed-size argument.
UNKNOWN, NO_ARGUMENT, FIXED, COUNTED1, COUNTED4, SIGNED4, COUNTED8 = range(7)
LINE, TWO_LINES, STOP, FRAME, LONG_BINPUT, PUT, BINPUT, MEMOIZE = range(7, 15)
# What each opcode does to the stack, where the scan models more than pops and pushes.
GENERIC, MARK, DUP, GET, TUPLE_LIKE = range(5)

# the reasons the scan returns (0: a complete pickle)
OK, TRUNCATED, BAD_OPCODE, MEMO_INDEX, LENGTH, NO_STOP, STACK, NESTING = range(8)
REASONS = {
    TRUNCATED: "it ends inside an opcode",
    BAD_OPCODE: "an opcode the unpickler does not know",
    MEMO_INDEX: "a memo index far beyond the memo entries made so far",
    LENGTH: "a length or frame longer than the rest of the file",
    NO_STOP: "it ends without a STOP opcode",
    STACK: "an opcode takes more from the stack than it holds",
    NESTING: "a tuple nesting shared references far beyond the file's size",
}

_COUNTED = {-2: COUNTED1, -3: SIGNED4, -4: COUNTED4, -5: COUNTED8}
_SPECIAL = {
    ".": STOP,
    "\x95": FRAME,
    "r": LONG_BINPUT,
    "p": PUT,
    "q": BINPUT,
    "\x94": MEMOIZE,
    "c": TWO_LINES,
    "i": TWO_LINES,
}
_STACK_SPECIAL = {
    "(": MARK,
    "2": DUP,
    "g": GET,
    "h": GET,
    "j": GET,
    ")": TUPLE_LIKE,
    "t": TUPLE_LIKE,
    "\x85": TUPLE_LIKE,
    "\x86": TUPLE_LIKE,
    "\x87": TUPLE_LIKE,
    "\x91": TUPLE_LIKE,
}


def opcode_tables() -> np.ndarray:
    """Per opcode byte (rows): its argument's kind and fixed width, its stack model, and
    how many items it takes from below a mark (-1: no mark), above it and puts back."""
    table = np.zeros((256, 6), dtype=np.int64)
    table[:, 3] = -1
    for opcode in pickletools.opcodes:
        row = table[ord(opcode.code)]
        argument = opcode.arg
        if opcode.code in _SPECIAL:
            row[0] = _SPECIAL[opcode.code]
        elif argument is None:
            row[0] = NO_ARGUMENT
        elif argument.n == pickletools.UP_TO_NEWLINE:
            row[0] = LINE
        elif argument.n >= 0:
            row[0], row[1] = FIXED, argument.n
        else:
            row[0] = _COUNTED[argument.n]
        row[2] = _STACK_SPECIAL.get(opcode.code, GENERIC)
        before = opcode.stack_before
        if pickletools.markobject in before:
            row[3] = before.index(pickletools.markobject)  # below the mark
            row[4] = 0
        else:
            row[4] = len(before)
        row[5] = len(opcode.stack_after)
    return table


def _scan_source() -> Callable[[np.ndarray, np.ndarray], tuple[int, int]]:
    def scan(data, table):
        """``(reason, position)`` for the pickle in ``data`` (uint8): ``OK`` and the
        position after its ``STOP``, or the reason it is refused and the opcode's position.

        Besides the argument checks, it models the stack as the size of each item (how
        many tuple nodes hashing it walks) and the memo likewise."""
        end = data.shape[0]
        sizes = np.empty(256, dtype=np.int64)  # the stack: grown by doubling
        depth = 0
        marks = np.empty(64, dtype=np.int64)  # stack depth at each mark
        nmarks = 0
        memo = np.zeros(1024, dtype=np.int64)  # 0: no entry
        puts = 0  # puts so far
        memo_len = 0  # entries made so far (MEMOIZE's index, as the unpickler counts)
        i = 0
        while i < end:
            at = i
            op = data[i]
            kind = table[op, 0]
            i += 1
            index: Any = -1  # the memo index of a put or get
            if kind == NO_ARGUMENT:
                pass
            elif kind == MEMOIZE:
                index = memo_len
            elif kind == FIXED:
                width = table[op, 1]
                if i + width > end:
                    return TRUNCATED, at
                if table[op, 2] == GET:  # BINGET, LONG_BINGET
                    index = 0
                    for k in range(width - 1, -1, -1):
                        index = index * 256 + np.int64(data[i + k])
                i += width
            elif kind == BINPUT:
                if i >= end:
                    return TRUNCATED, at
                index = np.int64(data[i])
                i += 1
            elif kind == STOP:
                return (OK, i) if depth >= 1 else (STACK, at)
            elif kind == UNKNOWN:
                return BAD_OPCODE, at
            elif kind in (LINE, TWO_LINES, PUT):
                first = i
                lines = 2 if kind == TWO_LINES else 1
                while lines > 0:
                    while i < end and data[i] != 10:
                        i += 1
                    if i >= end:
                        return TRUNCATED, at
                    i += 1
                    lines -= 1
                if kind == PUT or table[op, 2] == GET:  # GET, PUT: digits (as written)
                    if i - 1 - first < 1 or i - 1 - first > 12:
                        return MEMO_INDEX, at
                    index = 0
                    for k in range(first, i - 1):
                        digit = np.int64(data[k]) - 48
                        if digit < 0 or digit > 9:
                            return MEMO_INDEX, at
                        index = index * 10 + digit
            else:  # a little-endian number: a length, a frame size or a memo index
                width = 1 if kind == COUNTED1 else (8 if kind in (COUNTED8, FRAME) else 4)
                if i + width > end:
                    return TRUNCATED, at
                if width == 8 and data[i + 7] >= 128:
                    return LENGTH, at  # 2**63 bytes or more
                value: Any = 0
                for k in range(width - 1, -1, -1):
                    value = value * 256 + np.int64(data[i + k])
                i += width
                if kind == SIGNED4 and value >= 2**31:
                    return LENGTH, at  # negative: the unpickler refuses it too
                if kind == LONG_BINPUT:
                    index = value
                elif value > end - i:
                    return LENGTH, at
                elif kind != FRAME:  # a frame's opcodes follow; data is skipped
                    i += value
            # the memo: a put names at most MEMO_SLACK entries beyond those made
            is_put = kind in (PUT, BINPUT, LONG_BINPUT, MEMOIZE)
            if is_put:
                if index > puts + MEMO_SLACK:
                    return MEMO_INDEX, at
                if depth < 1:
                    return STACK, at
                if index >= memo.shape[0]:
                    grown = np.zeros(2 * index + 2, dtype=np.int64)
                    grown[: memo.shape[0]] = memo
                    memo = grown
                memo_len += memo[index] == 0
                memo[index] = sizes[depth - 1]
                puts += 1
                continue
            # the stack
            model = table[op, 2]
            if depth + 2 > sizes.shape[0]:
                grown = np.empty(2 * sizes.shape[0], dtype=np.int64)
                grown[:depth] = sizes[:depth]
                sizes = grown
            if model == MARK:
                if nmarks == marks.shape[0]:
                    more = np.empty(2 * nmarks, dtype=np.int64)
                    more[:nmarks] = marks[:nmarks]
                    marks = more
                marks[nmarks] = depth
                nmarks += 1
                continue
            if model == DUP:
                if depth < 1:
                    return STACK, at
                sizes[depth] = sizes[depth - 1]
                depth += 1
                continue
            if model == GET:
                known = 0 <= index < memo.shape[0] and memo[index] > 0
                sizes[depth] = memo[index] if known else 1  # an unknown index: refused there
                depth += 1
                continue
            below, above, after = table[op, 3], table[op, 4], table[op, 5]
            total = 1
            if below >= 0:  # takes everything above the last mark, and the mark
                if nmarks == 0:
                    return STACK, at
                nmarks -= 1
                top = marks[nmarks]
                for k in range(top, depth):
                    total += sizes[k]
                depth = top
                above = below
            if above > depth:
                return STACK, at
            if model == TUPLE_LIKE:
                for k in range(depth - above, depth):
                    total += sizes[k]
                if total > TUPLE_NODES_PER_BYTE * i + TUPLE_NODE_ALLOWANCE:
                    return NESTING, at
            depth -= above
            for _ in range(after):
                sizes[depth] = total if model == TUPLE_LIKE else 1
                depth += 1
        return NO_STOP, end

    return scan


@functools.cache
def compiled_scan() -> Callable[[np.ndarray], tuple[int, int]] | None:
    """The scan compiled by numba, with the opcode tables bound; ``None`` without numba
    (or where numba cannot compile it)."""
    try:
        import numba
    except ImportError:
        return None
    table = opcode_tables()
    source = _scan_source()
    try:
        try:
            kernel = numba.njit(cache=True)(source)
            kernel(np.frombuffer(b"N.", dtype=np.uint8), table)  # compile now
        except RuntimeError:  # no writable cache location: compile per process
            kernel = numba.njit(source)
            kernel(np.frombuffer(b"N.", dtype=np.uint8), table)
    except Exception:  # numba present but unusable here: no fast path
        return None
    return lambda data: kernel(data, table)


def python_scan(data: np.ndarray) -> tuple[int, int]:
    """The scan as plain Python (for tests: the compiled one must agree)."""
    reason, position = _scan_source()(data, opcode_tables())
    return int(reason), int(position)
