"""benchmarks/before_after.py: two runs of bench_vs_shader.py merged cell by cell."""
from __future__ import annotations

import importlib.util
from pathlib import Path


def _module():
    spec = importlib.util.spec_from_file_location("before_after", Path(__file__).parents[1] / "benchmarks" / "before_after.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


BEFORE = """shader: llvmpipe; torch_ao from /tmp/before, backend auto

**a frame**, CPU ms (ratio)

| case | target | 640×360, 4 × 4 | peak MB of fwd+bwd (≤ 1024), 640×360: 4 × 4 |
|---|---|---:|---:|
| shader on llvmpipe | | 110 | |
| `BitmaskAO` hard | ≤ 1× the shader | 78 (0.71×) |  |
| `GTAO` fwd+bwd, depth + normals | ≤ 3× `GTAO` | 1862 (**27.04×**) | 4104 |
"""

AFTER = """shader: llvmpipe; torch_ao from /work, backend kernel

**a frame**, CPU ms (ratio)

| case | target | 640×360, 4 × 4 | peak MB of fwd+bwd (≤ 1024), 640×360: 4 × 4 |
|---|---|---:|---:|
| shader on llvmpipe | | 110 | |
| `BitmaskAO` hard | ≤ 1× the shader | 58 (0.53×) |  |
| `GTAO` fwd+bwd, depth + normals | ≤ 3× `GTAO` | 202 (**3.87×**) | 52 |
| `HBAO` fwd+bwd, depth + normals | ≤ 3× `HBAO` | 51 (1.85×) | 21 |
"""


def test_cells_read_before_then_after_and_rows_only_after_keep_their_cell():
    lines = _module().merged(BEFORE, AFTER).splitlines()
    assert lines[0] == "**a frame**, CPU ms (ratio), before → after"
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.strip().strip("|").split("|")] for line in lines[4:] if line}
    assert rows["shader on llvmpipe"][2] == "110"  # the same in both runs: one value
    assert rows["`BitmaskAO` hard"][2] == "78 (0.71×) → 58 (0.53×)"
    assert rows["`GTAO` fwd+bwd, depth + normals"][2:] == ["1862 (**27.04×**) → 202 (**3.87×**)", "4104 → 52"]
    assert rows["`HBAO` fwd+bwd, depth + normals"][2:] == ["51 (1.85×)", "21"]  # no before row


def test_main_writes_the_merged_tables(tmp_path, capsys):
    before, after = tmp_path / "before.md", tmp_path / "after.md"
    before.write_text(BEFORE, encoding="utf-8")
    after.write_text(AFTER, encoding="utf-8")
    assert _module().main([str(before), str(after)]) == 0
    assert "| `BitmaskAO` hard | ≤ 1× the shader | 78 (0.71×) → 58 (0.53×) |  |" in capsys.readouterr().out
