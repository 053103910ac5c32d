"""Mutation testing of chosen lines: does the test suite notice plausible one-line bugs?

Each mutant changes one operator, constant or statement on a selected line (``<`` to
``<=``, ``and`` to ``or``, ``not x`` to ``x``, ``+`` to ``-``, ``n`` to ``n + 1``,
``True`` to ``False``, a ``raise`` or a bare call statement to ``pass``, ...), is written
into a private copy of the tree and judged by the given test files: *killed* when they
fail (or time out), *survived* when they pass. Lines are chosen by a git diff (the lines a
change added) or by explicit ranges::

    python tools/mutate.py --base f5cc0df src/dego/_policy.py=tests/test_policy.py
    python tools/mutate.py \\
        src/dego/_npz.py:40-120=tests/test_file_faults.py,tests/data/test_occ3d_io.py

``FILE[:LINES]=TESTS``: ``LINES`` is ``a-b,c`` (default with ``--base``: the lines added
since that revision); ``TESTS`` a comma-separated list of pytest targets. Docstrings,
annotations and f-strings (messages) are never mutated. Survivors are printed with their
line. POSIX only: each run is a fork of this process, which imports torch once.
"""

from __future__ import annotations

import argparse
import ast
import copy
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_COMPARE_SWAPS: dict[type, type] = {
    ast.Lt: ast.LtE, ast.LtE: ast.Lt, ast.Gt: ast.GtE, ast.GtE: ast.Gt,
    ast.Eq: ast.NotEq, ast.NotEq: ast.Eq, ast.In: ast.NotIn, ast.NotIn: ast.In,
    ast.Is: ast.IsNot, ast.IsNot: ast.Is,
}  # fmt: skip
_BINOP_SWAPS: dict[type, type] = {
    ast.Add: ast.Sub, ast.Sub: ast.Add, ast.Mult: ast.Div, ast.Div: ast.Mult,
    ast.FloorDiv: ast.Mult, ast.Mod: ast.FloorDiv, ast.Pow: ast.Mult,
    ast.BitAnd: ast.BitOr, ast.BitOr: ast.BitAnd, ast.LShift: ast.RShift,
}  # fmt: skip


@dataclass(frozen=True)
class Mutant:
    file: Path
    line: int
    description: str
    source: str  # the whole mutated module


def _skipped_nodes(tree: ast.AST) -> set[int]:
    """Docstrings and everything inside type annotations and f-strings."""
    ids = set()
    for node in ast.walk(tree):
        annotations = []
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            annotations.append(node.returns)
        elif isinstance(node, (ast.arg, ast.AnnAssign)):
            annotations.append(node.annotation)
        if isinstance(node, ast.JoinedStr):  # message text
            annotations.append(node)
        for annotation in annotations:
            if annotation is not None:
                ids.update(id(inner) for inner in ast.walk(annotation))
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                ids.add(id(body[0].value))
    return ids


def _points(tree: ast.Module, lines: set[int]) -> Iterator[tuple[int, str, object]]:
    """``(line, description, edit)`` for every mutation point on ``lines``; ``edit`` is a
    ``(node_path, change)`` applied to a deep copy of the tree."""
    skip = _skipped_nodes(tree)
    for node in ast.walk(tree):
        line = getattr(node, "lineno", None)
        if line is None or line not in lines or id(node) in skip:
            continue
        if isinstance(node, ast.Compare):
            for i, op in enumerate(node.ops):
                if type(op) in _COMPARE_SWAPS:
                    new = _COMPARE_SWAPS[type(op)].__name__
                    yield line, f"{type(op).__name__} -> {new}", ("compare", node, i)
        elif isinstance(node, ast.BoolOp):
            other = "Or" if isinstance(node.op, ast.And) else "And"
            yield line, f"{type(node.op).__name__} -> {other}", ("boolop", node, None)
        elif isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.Not, ast.USub)):
            yield line, f"drop {type(node.op).__name__}", ("unary", node, None)
        elif isinstance(node, (ast.BinOp, ast.AugAssign)) and type(node.op) in _BINOP_SWAPS:
            new = _BINOP_SWAPS[type(node.op)].__name__
            yield line, f"{type(node.op).__name__} -> {new}", ("binop", node, None)
        elif isinstance(node, ast.Constant):
            value = node.value
            if isinstance(value, bool):
                yield line, f"{value} -> {not value}", ("const", node, not value)
            elif isinstance(value, int):
                yield line, f"{value} -> {value + 1}", ("const", node, value + 1)
            elif isinstance(value, float):
                new = 1.0 if value == 0 else value * 2
                yield line, f"{value} -> {new}", ("const", node, new)
        elif isinstance(node, ast.Raise):
            yield line, "raise -> pass", ("stmt", node, None)
        elif isinstance(node, ast.Expr) and isinstance(node.value, ast.Call):
            yield line, "call statement -> pass", ("stmt", node, None)
        elif isinstance(node, ast.Return) and node.value is not None:
            yield line, "return value -> None", ("return", node, None)


def _apply(tree: ast.Module, target: ast.AST, kind: str, arg: object) -> ast.Module:
    memo: dict[int, object] = {}
    mutated = copy.deepcopy(tree, memo)
    node = memo[id(target)]
    if kind == "compare":
        node.ops[arg] = _COMPARE_SWAPS[type(node.ops[arg])]()
    elif kind == "boolop":
        node.op = ast.Or() if isinstance(node.op, ast.And) else ast.And()
    elif kind == "binop":
        node.op = _BINOP_SWAPS[type(node.op)]()
    elif kind == "const":
        node.value = arg
    elif kind in ("unary", "stmt", "return"):
        replacement: ast.AST
        if kind == "unary":
            replacement = node.operand
        elif kind == "stmt":
            replacement = ast.Pass()
        else:
            replacement = ast.Return(value=ast.Constant(value=None))
        _replace(mutated, node, replacement)
    return ast.fix_missing_locations(mutated)


def _replace(tree: ast.AST, old: ast.AST, new: ast.AST) -> None:
    for parent in ast.walk(tree):
        for field, value in ast.iter_fields(parent):
            if value is old:
                setattr(parent, field, new)
                return
            if isinstance(value, list):
                for i, item in enumerate(value):
                    if item is old:
                        value[i] = new
                        return


def mutants(file: Path, lines: set[int]) -> list[Mutant]:
    source = file.read_text()
    tree = ast.parse(source)
    out = []
    for line, description, (kind, node, arg) in _points(tree, lines):
        mutated = ast.unparse(_apply(tree, node, kind, arg))
        out.append(Mutant(file, line, description, mutated))
    return out


def added_lines(base: str, file: Path) -> set[int]:
    diff = subprocess.run(
        ["git", "diff", "-U0", base, "--", str(file)],
        cwd=ROOT, capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    lines: set[int] = set()
    for match in re.finditer(r"^@@ -\S+ \+(\d+)(?:,(\d+))? @@", diff, re.M):
        start, count = int(match[1]), int(match[2] or 1)
        lines.update(range(start, start + count))
    if (
        not diff
        and subprocess.run(
            ["git", "ls-files", "--error-unmatch", str(file)], cwd=ROOT, capture_output=True
        ).returncode
    ):  # untracked: every line is new
        lines = set(range(1, len(file.read_text().splitlines()) + 1))
    return lines


def parse_ranges(text: str) -> set[int]:
    lines: set[int] = set()
    for part in text.split(","):
        a, _, b = part.partition("-")
        lines.update(range(int(a), int(b or a) + 1))
    return lines


def _workspace() -> Path:
    where = Path(tempfile.mkdtemp(prefix="dego-mutate-"))
    for name in ("src", "tests", "pyproject.toml", "docs", "examples", "README.md"):
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, where / name, ignore=shutil.ignore_patterns("__pycache__"))
        elif path.exists():
            shutil.copy2(path, where / name)
    return where


_PYTEST_ARGS = ["-x", "-q", "-n", "0", "-p", "no:cacheprovider", "-W", "ignore"]


def _run_tests(where: Path, tests: list[str], timeout: float) -> str:
    """Run pytest on ``tests`` against the tree at ``where`` in a forked child of this
    process (torch is imported once, here; dego afresh in each child)."""
    pid = os.fork()
    if pid == 0:  # the child: never returns
        code = 3
        try:
            fd = os.open(os.devnull, os.O_WRONLY)
            os.dup2(fd, 1)
            os.dup2(fd, 2)
            os.chdir(where)
            sys.path[:0] = [str(where / "src"), str(where)]
            sys.dont_write_bytecode = True
            import pytest

            code = int(pytest.main([*_PYTEST_ARGS, *tests]))
        finally:
            os._exit(code)
    deadline = time.monotonic() + timeout
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return "survived" if os.waitstatus_to_exitcode(status) == 0 else "killed"
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return "timeout"
        time.sleep(0.05)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("targets", nargs="+", help="FILE[:LINES]=TEST[,TEST...]")
    parser.add_argument("--base", help="git revision: mutate the lines added since it")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds per mutant")
    parser.add_argument("--jobs", type=int, default=1, help="mutants judged at once")
    parser.add_argument("--list", action="store_true", help="print the mutants, run nothing")
    parser.add_argument(
        "--sample", type=int, help="judge a uniform random sample of this many mutants"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of --sample (0)")
    parser.add_argument(
        "--no-baseline",
        action="store_true",
        help="skip the unmutated run of each test set (when the suite is known to pass)",
    )
    args = parser.parse_args(argv)
    plan: list[tuple[Mutant, list[str]]] = []
    for target in args.targets:
        spec, _, tests = target.partition("=")
        name, _, ranges = spec.partition(":")
        file = (ROOT / name).resolve()
        if ranges:
            lines = parse_ranges(ranges)
        elif args.base:
            lines = added_lines(args.base, file)
        else:
            parser.error(f"{target}: give line ranges or --base")
        plan += [(m, tests.split(",")) for m in mutants(file, lines)]
    print(f"{len(plan)} mutants", flush=True)
    if args.sample is not None and args.sample < len(plan):
        chosen = sorted(random.Random(args.seed).sample(range(len(plan)), args.sample))
        plan = [plan[i] for i in chosen]
        print(f"judging a sample of {len(plan)} (seed {args.seed})", flush=True)
    if args.list:
        for mutant, _ in plan:
            print(f"{mutant.file.relative_to(ROOT)}:{mutant.line} {mutant.description}")
        return 0
    if "dego" in sys.modules:
        parser.error("dego is imported already; the children must import the mutated copy")
    import numpy  # noqa: F401  (imported once here, shared by every forked child)
    import torch  # noqa: F401

    workspaces = [_workspace() for _ in range(max(args.jobs, 1))]
    for tests in set() if args.no_baseline else {tuple(t) for _, t in plan}:
        # the copies are identical: check one
        if _run_tests(workspaces[0], list(tests), args.timeout) != "survived":
            print(f"baseline fails: {' '.join(tests)}", file=sys.stderr)
            return 2
    free = list(workspaces)
    results: list[tuple[Mutant, str]] = []

    def judge(item: tuple[Mutant, list[str]]) -> tuple[Mutant, str]:
        mutant, tests = item
        where = free.pop()
        path = where / mutant.file.relative_to(ROOT)
        original = path.read_text()
        try:
            path.write_text(mutant.source)
            return mutant, _run_tests(where, tests, args.timeout)
        finally:
            path.write_text(original)
            free.append(where)

    with ThreadPoolExecutor(len(workspaces)) as pool:
        for mutant, verdict in pool.map(judge, plan):
            results.append((mutant, verdict))
            text = mutant.file.read_text().splitlines()[mutant.line - 1].strip()
            rel = mutant.file.relative_to(ROOT)
            print(f"{verdict:8} {rel}:{mutant.line} {mutant.description}: {text}", flush=True)
    killed = sum(verdict != "survived" for _, verdict in results)
    total = len(results)
    print(f"killed {killed} of {total} ({100 * killed / max(total, 1):.1f}%)")
    for where in workspaces:
        shutil.rmtree(where, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
