"""The `bench` command imports only the module of the command asked for, and knows every command."""
import argparse
import importlib
import subprocess
import sys

import pytest

from bench.cli import COMMAND_MODULES, build_parser


def test_every_command_a_module_adds_is_routed_to_that_module():
    for module in set(COMMAND_MODULES.values()):
        parser = argparse.ArgumentParser()
        subparsers = parser.add_subparsers()
        importlib.import_module(module).add_commands(subparsers)
        for command in subparsers.choices:
            assert COMMAND_MODULES.get(command) == module, f"`bench {command}` is added by {module}"


def test_full_parser_lists_every_command():
    parser = build_parser(None)
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert set(subparsers.choices) == set(COMMAND_MODULES)


def test_bench_node_does_not_import_studies_reports_or_the_launcher():
    code = ("import sys; from bench.cli import build_parser; build_parser('node'); "
            "print(','.join(m for m in sys.modules if m.startswith('bench.')))")
    loaded = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True,
                            timeout=120).stdout.strip().split(",")
    heavy = [m for m in loaded if m.startswith(("bench.studies", "bench.report", "bench.launcher"))]
    assert "bench.runtime.node_cli" in loaded
    assert heavy == []


def test_unknown_command_is_a_usage_error_naming_it(capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser("no-such-command").parse_args(["no-such-command"])
    assert exc.value.code == 2
    assert "no-such-command" in capsys.readouterr().err
