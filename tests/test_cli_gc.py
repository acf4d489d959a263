"""A command runs with the objects alive at its start (the imported modules) left out of the garbage
collector's full collections, and leaves the collector as it found them, whether it succeeds or fails."""
import argparse
import gc

import pytest

import torch_ao.cli as cli


def _parser_running(func):
    parser = argparse.ArgumentParser(prog="torch-ao")
    parser.set_defaults(command="probe", func=func)
    return parser


@pytest.mark.parametrize("fails", [False, True])
def test_a_command_runs_with_the_imports_frozen_and_leaves_none_frozen(monkeypatch, capsys, fails):
    assert gc.get_freeze_count() == 0
    seen = {}

    def command(args):
        seen["frozen"] = gc.get_freeze_count()
        # an object made during the command is still collected
        cycle = []
        cycle.append(cycle)
        del cycle
        seen["collected"] = gc.collect() > 0
        if fails:
            raise ValueError("depth: expected a positive map")
        return 0

    monkeypatch.setattr(cli, "build_parser", lambda: _parser_running(command))
    status = cli.main([])
    assert status == (2 if fails else 0)
    assert seen["frozen"] > 10_000  # torch, kornia and torch_ao's modules
    assert seen["collected"]
    assert gc.get_freeze_count() == 0
    if fails:
        assert "error: depth: expected a positive map" in capsys.readouterr().err
