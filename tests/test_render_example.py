"""The worked example of docs/reference.md ("a mesh file alone, negative coordinates, back-face depth"),
run line by line as written: ``python -c CODE`` lines are executed in-process, ``torch-ao ...`` lines
through :func:`torch_ao.cli.main`."""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
import torch

from torch_ao.cli import main
from torch_ao.io import load_gbuffer

DOC = Path(__file__).resolve().parents[1] / "docs" / "reference.md"


def example_lines() -> list[str]:
    text = DOC.read_text()
    block = re.search(r"<!-- example: render-mesh.*?-->\s*```bash\n(.*?)```", text, re.S)
    assert block, "docs/reference.md lost its render-mesh example"
    return [line for line in block.group(1).replace("\\\n", " ").splitlines() if line.strip()]


def test_reference_doc_example_runs(tmp_path, monkeypatch, capsys):
    pytest.importorskip("trimesh", reason="the example writes and reads a GLB through trimesh")
    monkeypatch.chdir(tmp_path)
    lines = example_lines()
    assert [shlex.split(line, comments=True)[0] for line in lines] == ["python", "torch-ao", "python"]
    for line in lines:
        argv = shlex.split(line, comments=True)
        if argv[0] == "python":
            assert argv[1] == "-c"
            exec(compile(argv[2], "<docs example>", "exec"), {})
        else:
            assert main(argv[1:] + ["--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "ring thickness" in out
    gb, extras = load_gbuffer(tmp_path / "ring.npz")
    assert (tmp_path / "ring.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    M = extras["world_to_view"][0].double()
    assert torch.allclose(-M[:3, :3].T @ M[:3, 3], torch.tensor([-2.5, 1.5, -3.0], dtype=torch.float64), atol=1e-9)
    oid, depth, back = gb.object_id, gb.depth, gb.backface_depth
    ring, plane = oid == 1, oid == 2
    assert ring.sum() > 200 and plane.sum() > 200
    thickness = (back - depth)[ring]
    # a tube of radius 0.3: positive everywhere, 0.6 through its axis, and no chord longer than
    # the ring's outer diameter
    assert bool((thickness > 0).all()) and float(thickness.max()) > 0.5 and float(thickness.max()) < 2.6
    assert bool(torch.isinf(back[plane]).all()) and bool(torch.isinf(back[~gb.valid]).all())
    # the plane lies under the lowest vertex, y = -1.3
    p = extras["position"][0].double().reshape(3, -1)
    world = M[:3, :3].T @ (p - M[:3, 3:4])
    assert float((world[1][plane[0, 0].reshape(-1)] + 1.3).abs().max()) < 1e-3
