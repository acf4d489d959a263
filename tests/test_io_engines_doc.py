"""docs/engines.md's worked example runs as written: its Python block, then its ``torch-ao`` lines."""
import os
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from torch_ao.cli import main
from torch_ao.examples import example_gbuffer
from torch_ao.io import read_npz

pytest.importorskip("OpenEXR", reason="needs the exr extra: pip install -e '.[exr]'")

DOC = Path(__file__).resolve().parents[1] / "docs" / "engines.md"


def _worked_example() -> tuple[str, list[str]]:
    text = DOC.read_text().split("## Worked example", 1)[1]
    python = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    bash = re.search(r"```bash\n(.*?)```", text, re.S).group(1)
    return python, [line for line in bash.splitlines() if line.startswith("torch-ao ")]


def test_worked_example_runs(tmp_path, capsys):
    python, commands = _worked_example()
    assert len(commands) == 3
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        exec(compile(python, "docs/engines.md", "exec"), {})
        matrix = capsys.readouterr().out.strip()
        assert f"--view-matrix {matrix}" in commands[1]  # the doc's command uses the matrix it printed
        for line in commands:
            assert main(shlex.split(line)[1:]) == 0, line
        printed = capsys.readouterr().out
    finally:
        os.chdir(cwd)
    summary = re.search(r"frame\.exr: 160x90, \d+ valid pixels \(depth [\d.]+\.\.[\d.]+\); normals", printed).group(0)
    assert summary in DOC.read_text().replace("\n", " ").replace("->  ", "-> ")  # the doc quotes it
    gb = example_gbuffer(90, 160)
    raw = read_npz(tmp_path / "frame.npz")
    valid = gb.valid[0, 0].numpy().copy()
    valid[0, :8] = False
    assert np.array_equal(np.isfinite(raw["depth"][0]), valid)
    n = gb.normals[0].permute(1, 2, 0).numpy()
    assert np.allclose(raw["normal"][0][valid], n[valid], atol=1e-6)
    assert (tmp_path / "ao.npz").is_file() and (tmp_path / "frame.png").is_file()
