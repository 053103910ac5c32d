"""``dego.cli`` is a table: each command's parser and main live in its own package, every
command module has the same four names, and only the command that runs is imported."""

from __future__ import annotations

import argparse
import importlib
import inspect
import json
import subprocess
import sys

import pytest

from dego.cli import COMMANDS, WRAPPERS, build_parser


@pytest.mark.parametrize("name", list(COMMANDS))
def test_every_command_module_has_the_four_names(name: str) -> None:
    module = importlib.import_module(COMMANDS[name].module)
    assert isinstance(module.DESCRIPTION, str) and module.DESCRIPTION
    assert module.EPILOG is None or isinstance(module.EPILOG, str)
    parser = argparse.ArgumentParser()
    assert module.add_arguments(parser) is parser
    assert list(inspect.signature(module.run_command).parameters) == ["args", "parser", "created"]


def test_the_table_is_the_help_and_the_wrappers_exist() -> None:
    parser = build_parser()
    (subparsers,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert list(subparsers.choices) == list(COMMANDS)
    lines = {action.dest: action.help for action in subparsers._choices_actions}
    assert lines == {name: command.help for name, command in COMMANDS.items()}
    wrapper = importlib.import_module("dego.viz.command")
    for add, run in WRAPPERS.values():
        assert callable(getattr(wrapper, add)) and callable(getattr(wrapper, run))


def test_a_parser_of_one_command_lists_the_others_by_name_only() -> None:
    parser = build_parser(load=["view"])
    (subparsers,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert list(subparsers.choices) == list(COMMANDS)
    assert subparsers.choices["view"].description
    assert subparsers.choices["demo"].description is None  # not loaded
    args = parser.parse_args(["view", "x.rrd", "--web"])
    assert args.web and args.command_module.__name__ == "dego.viz.command"


@pytest.mark.slow
def test_dego_eval_does_not_import_the_demo_or_the_studies() -> None:
    code = """
import json, sys
from dego.cli import main
try:
    main(["eval", "--help"])
except SystemExit:
    pass
print(json.dumps(sorted(m for m in sys.modules if m.startswith(("dego.demo", "dego.study")))))
"""
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=600, check=True
    )
    assert json.loads(result.stdout.strip().splitlines()[-1]) == []
