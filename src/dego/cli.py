"""The ``dego`` command: assembles the subcommands and maps how they end to exit statuses.

Each command lives in the package whose work it does (:data:`COMMANDS`): ``dego demo`` in
:mod:`dego.demo.command`, ``dego study`` in :mod:`dego.demo.study.command`, ``dego train``
in :mod:`dego.demo.feedforward.command`, ``dego eval`` in :mod:`dego.evaluation.command`
``dego data`` in :mod:`dego.evaluation.data_command` and ``dego view`` in
:mod:`dego.viz.command`. Every command module has the same names:
``DESCRIPTION`` and ``EPILOG`` (its ``--help``), ``add_arguments(parser)`` and
``run_command(args, parser, created) -> int``. Only the module of the command that runs
is imported, so ``dego eval`` never loads the demo.

``dego eval`` is core (:mod:`dego.evaluation` may not import :mod:`dego.viz`), so its
recording flags (``--rerun``, ``--limit``) come from :mod:`dego.viz.command`, which wraps
it (:data:`WRAPPERS`).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import sys
from collections.abc import Iterable
from pathlib import Path
from types import ModuleType

from dego._atomic import remove_empty_dirs
from dego._cli_args import (
    INTERRUPTED_STATUS,
    SigintIgnored,
    UsageError,
    apply_threads,
    isatty,
)
from dego._version import __version__

PROGRAM_DESCRIPTION = (
    "Run Deformable Gaussian Occupancy (DeGO) end to end on synthetic driving clips. "
    "'dego demo' fits static, rigid and decoupled Gaussians (and reference rows) to one clip "
    "and scores them; 'dego study' repeats the fits over seeds and Gaussian budgets; "
    "'dego train' trains a feed-forward network on many clips with and without deformation; "
    "'dego eval' scores a folder of occupancy predictions with the rules of any of six "
    "benchmarks; 'dego data write-tree' writes a small synthetic tree of any of them; 'dego view' "
    "opens a recording of demo or eval (--rerun) in rerun's viewer."
)


@dataclasses.dataclass(frozen=True)
class Command:
    """A subcommand: the module that defines it and its line in ``dego --help``."""

    module: str
    help: str


COMMANDS = {
    "demo": Command(
        "dego.demo.command",
        "fit static, rigid and decoupled Gaussians to a synthetic clip and score them",
    ),
    "study": Command(
        "dego.demo.study.command",
        "when does decoupling pay off? variants x seeds x Gaussian budgets, with CIs",
    ),
    "train": Command(
        "dego.demo.feedforward.command",
        "train a feed-forward Gaussian network on many scenes, with and without deformation",
    ),
    "eval": Command(
        "dego.evaluation.command",
        "score occupancy predictions on any benchmark (--benchmark): mIoU, IoU, RayIoU",
    ),
    "data": Command(
        "dego.evaluation.data_command",
        "write a small synthetic tree of any benchmark (dego data write-tree --benchmark NAME OUT)",
    ),
    "view": Command(
        "dego.viz.command",
        "open a .rrd recording (dego demo --rerun, dego eval --rerun) in rerun's viewer",
    ),
}
"""The subcommands, in ``dego --help`` order."""

WRAPPERS = {"eval": ("add_eval_recording_arguments", "run_eval_recording")}
"""Options an outer layer adds to a core command: ``{command: (add, run)}``, functions of
:mod:`dego.viz.command`; ``run(args, parser, created, score)`` calls ``score()``."""


def build_parser(load: Iterable[str] | None = None) -> argparse.ArgumentParser:
    """The ``dego`` parser. ``load``: the commands whose modules are imported and whose
    options are added (default: all); the others are listed by name and help line only."""
    loaded = set(COMMANDS if load is None else load)
    parser = argparse.ArgumentParser(prog="dego", description=PROGRAM_DESCRIPTION)
    parser.add_argument("--version", action="version", version=f"dego {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    for name, command in COMMANDS.items():
        if name not in loaded:
            commands.add_parser(name, help=command.help)
            continue
        module = importlib.import_module(command.module)
        sub = commands.add_parser(
            name, help=command.help, description=module.DESCRIPTION, epilog=module.EPILOG
        )
        module.add_arguments(sub)
        if name in WRAPPERS:
            getattr(_wrapper_module(), WRAPPERS[name][0])(sub)
        sub.set_defaults(command_module=module, command_parser=sub)
    return parser


def _wrapper_module() -> ModuleType:
    return importlib.import_module("dego.viz.command")


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``dego`` console script.

    Every flag is checked, and the output folder created, before any work starts: a bad
    value is a usage error (exit status 2, one ``error:`` line naming the flag). Ctrl-C
    ends any command with exit status 130 and one line, ``dego: interrupted``, on
    stderr; the outputs are written all or nothing at the end, and output folders the
    command made itself are removed again when it ends without filling them."""
    created: list[Path] = []
    try:
        code = _dispatch(sys.argv[1:] if argv is None else argv, created)
    except KeyboardInterrupt:
        with SigintIgnored():  # a second Ctrl-C does not cut the cleanup short
            remove_empty_dirs(created)
            print(("\n" if isatty(sys.stderr) else "") + "dego: interrupted", file=sys.stderr)
        return INTERRUPTED_STATUS
    except BaseException:
        remove_empty_dirs(created)
        raise
    if code != 0:
        remove_empty_dirs(created)
    return code


def _dispatch(argv: list[str], created: list[Path]) -> int:
    # The first word that is not an option names the command (dego's own options take no
    # value); only that command's module is imported.
    name = next((word for word in argv if not word.startswith("-")), None)
    args = build_parser(load=[name] if name in COMMANDS else []).parse_args(argv)
    module: ModuleType = args.command_module
    parser: argparse.ArgumentParser = args.command_parser
    if hasattr(args, "threads"):  # --threads auto resolved once: the command sees a count
        args.threads = apply_threads(args.threads, quiet=getattr(args, "quiet", False))
    try:
        if args.command in WRAPPERS:
            run = getattr(_wrapper_module(), WRAPPERS[args.command][1])
            return run(args, parser, created, lambda: module.run_command(args, parser, created))
        return module.run_command(args, parser, created)
    except UsageError as error:
        parser.error(str(error))


if __name__ == "__main__":
    sys.exit(main())
