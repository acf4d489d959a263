"""Conventions that cannot go silently wrong: each common mistake reading an engine's G-buffer either
gives the right AO or one error line naming the flag that fixes it."""
import argparse

import numpy as np
import pytest
import torch

from torch_ao.cli import build_parser, main
from torch_ao.engine_io import ENGINE_OPTIONS


def _input_flags(command: str) -> dict[str, str]:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    parser = sub.choices[command]
    return {a.option_strings[0]: a.help for a in parser._actions
            if a.dest in {o.name for o in ENGINE_OPTIONS} and a.help is not argparse.SUPPRESS}


def test_every_command_reading_gbuffers_has_the_same_input_flags():
    flags = {c: _input_flags(c) for c in ("ao", "bench", "fit", "convert")}
    assert set(flags["ao"]) == {"--" + o.name.replace("_", "-") for o in ENGINE_OPTIONS}
    for command in ("bench", "fit", "convert"):
        assert flags[command] == flags["ao"], command


@pytest.mark.parametrize("argv, message", [
    (["ao", "--far", "10"], "torch-ao ao: error: --far: applies to a GBUFFER file, and none was given"),
    (["fit", "--normal-space", "world"], "torch-ao fit: error: --normal-space: applies to --reference files, and none was given"),
    (["bench", "--fov", "60"], "torch-ao bench: error: --fov: applies to --reference files, and none was given"),
    (["ao", "x.npz", "--fov", "60", "--intrinsics", "1,1,0,0"], "torch-ao ao: error: --fov: give fov or intrinsics, not both"),
])
def test_input_flags_without_files_or_contradicting_are_refused(argv, message, capsys, tmp_path):
    assert main(argv + ["--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err.strip() == message
    assert list(tmp_path.iterdir()) == []
