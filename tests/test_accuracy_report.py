"""benchmarks/accuracy_report.py --mesh: the real-mesh section, on a small mesh file written here."""
from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torch_ao import GTAO, error_metrics
from torch_ao.fit import load_views


def _report():
    spec = importlib.util.spec_from_file_location("accuracy_report", Path(__file__).parents[1] / "benchmarks" / "accuracy_report.py")
    report = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("accuracy_report", report)  # dataclasses look their module up there
    spec.loader.exec_module(report)
    return report


def test_mesh_section_scores_every_method_on_the_mesh_view(tmp_path):
    import trimesh

    mesh = tmp_path / "plank.obj"
    trimesh.creation.box(extents=(1.0, 0.3, 0.5)).export(mesh)
    out, rows_json = tmp_path / "meshes.md", tmp_path / "rows.json"
    argv = ["--mesh", str(mesh), "--size", "32x20", "--spp", "16", "--rays", "8", "--presets", "low", "--mesh-radius", "0.3",
            "--cache-dir", str(tmp_path / "cache"), "--out", str(out), "--png", str(tmp_path / "plot.png"),
            "--rows-json", str(rows_json)]
    assert _report().main(argv) == 0
    text = out.read_text()
    assert text.startswith("## Real meshes") and "`plank.obj`" in text and "R = 0.3" in text
    data = json.loads(rows_json.read_text())
    rows, screen = data["rows"], data["screen"]
    assert {r["pipeline"] for r in rows} == {"ssao", "hbao", "ue4_ssao", "gtao", "pssao", "bitmask"}
    assert {r["scene"] for r in rows} == {"mesh:plank"} and len(rows) == 12  # 6 methods, with and without the denoiser
    assert [r["thickness"] for r in screen] == ["inf", "0.5"]
    # the cached reference is the mesh at R = 0.3 (fraction of its unit size), and the gtao row is its error
    (path,) = (tmp_path / "cache" / "meshes").glob("*.npz")
    assert float(np.load(path)["max_distance"]) == pytest.approx(0.3)
    view = load_views([path])[0]
    assert 0.05 < float(view.gbuffer.valid.float().mean()) < 1.0 and float(view.reference[view.gbuffer.valid].min()) < 0.9
    with torch.no_grad():
        vis = GTAO(preset="low", radius=0.3)(view.gbuffer).visibility
    row = next(r for r in rows if r["pipeline"] == "gtao" and not r["denoise"])
    assert row["ref_mae"] == pytest.approx(error_metrics(vis, view.reference, view.gbuffer.valid)["mae"], rel=1e-6)
    assert row["ref_psnr"] != row["truth_psnr"]  # the split: against the reference and against the truth differ
