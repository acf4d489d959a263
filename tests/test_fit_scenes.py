"""The benchmark scene set (procedural scenes and assimp-testmodels meshes, train and held-out
scenes) and `torch-ao fit --leave-one-out`: each fold is the fit on the other scenes, scored on the
scene left out."""
from __future__ import annotations

import json

import pytest

from torch_ao.cli import main
from torch_ao.datasets import (BENCHMARK_SCENES, FIT_SCENES, HELDOUT_SCENES, SCENE_SETS, parse_scenes,
                               reference_view)
from torch_ao.reference import MESH_SCENES, SCENES, get_scene
import torch_ao.reference.scenes as scenes_module
from conftest import mesh_scenes_missing

RESERVED = ("spider", "duck", "engine", "wuson")


@mesh_scenes_missing()
def test_train_and_heldout_scenes_are_disjoint_known_and_exclude_the_reserved_models():
    assert not set(FIT_SCENES) & set(HELDOUT_SCENES)
    assert set(BENCHMARK_SCENES) <= set(SCENES) and set(MESH_SCENES) <= set(SCENES)
    assert any(s in MESH_SCENES for s in FIT_SCENES) and any(s in MESH_SCENES for s in HELDOUT_SCENES)
    for name, (path, _) in MESH_SCENES.items():
        assert not any(r in (name + path).lower() for r in RESERVED), name
    assert parse_scenes("fence,heldout,fence") == ["fence", *HELDOUT_SCENES]
    assert parse_scenes("benchmark") == list(SCENE_SETS["benchmark"])


def test_unknown_or_missing_scenes_are_refused_by_name(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="--scenes: unknown scene.*atlantis"):
        parse_scenes("fence,atlantis")
    monkeypatch.setattr(scenes_module, "MESH_DIR", tmp_path)
    with pytest.raises(ValueError, match="--scenes: scene 'mesh_regr01' needs .*assimp-testmodels"):
        parse_scenes("fence,mesh_regr01")
    with pytest.raises(FileNotFoundError, match="apt-get install assimp-testmodels"):
        get_scene("mesh_regr01")
    assert main(["fit", "--scenes", "mesh_concave", "--out", str(tmp_path / "o")]) == 2


def test_a_set_keeps_the_scenes_this_machine_has(tmp_path, monkeypatch):
    """Without assimp-testmodels the default `--scenes fit` is its procedural scenes, with a warning naming
    the package; a set of meshes alone is refused naming it."""
    from torch_ao.datasets import TRAIN_SCENES

    monkeypatch.setattr(scenes_module, "MESH_DIR", tmp_path)
    with pytest.warns(RuntimeWarning, match=r"--scenes: 5 mesh scene\(s\) of the set left out .*assimp-testmodels"):
        assert parse_scenes("fit") == list(TRAIN_SCENES)
    with pytest.raises(ValueError, match="--scenes: scene 'mesh_empty_mat' needs .*assimp-testmodels"):
        parse_scenes("meshes")


@mesh_scenes_missing("mesh_concave")
def test_mesh_scene_orbits_differ_per_seed_and_frame_the_mesh(tmp_path):
    views = [get_scene("mesh_concave", seed).view for seed in (None, 1, 2)]
    assert len({tuple(round(x, 6) for x in v.eye) for v in views}) == 3
    assert views[1].target == views[2].target  # the mesh's centre
    ref = reference_view("mesh_concave", 1, height=24, width=32, spp=16, max_distance=1.0, cache_dir=tmp_path)
    ids = ref.gbuffer.object_id
    mesh = ids == 1
    assert 0.02 < float(mesh.float().mean()) < 0.9  # the mesh is in view, the floor around it
    floor = (ids == 2) & ref.gbuffer.valid
    assert float(ref.reference[floor].min()) < 0.9 < float(ref.reference[floor].max())  # contact shadow, open floor


TINY = ["--size", "16x12", "--spp", "16", "--train-views", "1", "--steps", "4", "--hard-every", "2",
        "--max-steps", "8", "--no-denoise", "--method", "gtao", "--no-progress", "--holdout-scenes", "none"]


@pytest.mark.slow
def test_leave_one_out_folds_are_fits_on_the_other_scenes(tmp_path):
    cache = str(tmp_path / "cache")
    out = tmp_path / "loo"
    args = ["fit", *TINY, "--scenes", "fence,stairs,mesh_concave", "--cache", cache, "--leave-one-out"]
    assert main([*args, "--out", str(out)]) == 0
    data = json.loads((out / "params.json").read_text())
    folds = data["leave_one_out"]
    assert list(folds) == ["fence", "stairs", "mesh_concave"]
    report = (out / "report.md").read_text()
    mean = sum(f["fitted"] for f in folds.values()) / 3
    assert "| **mean** | " in report and f"| {mean:.2f} |" in report
    for scene, f in folds.items():
        assert f"| {scene} | {f['default']:.2f} | {f['fitted']:.2f} | {f['gtao']:.2f} |" in report
    # the fold without stairs is the plain fit on fence and mesh_concave, scored on stairs as a held-out scene
    alone = tmp_path / "alone"
    assert main(["fit", *TINY[:-1], "stairs", "--scenes", "fence,mesh_concave", "--cache", cache,
                 "--out", str(alone)]) == 0
    plain = json.loads((alone / "params.json").read_text())
    assert plain["parameters"] == pytest.approx(folds["stairs"]["parameters"])
    assert plain["per_view"]["fitted"]["stairs/s1000"]["psnr"] == pytest.approx(folds["stairs"]["fitted"], rel=1e-6)
    assert plain["parameters"] != pytest.approx(data["parameters"])  # the main fit saw stairs too
    # resumed from the folds' checkpoints: the same report
    assert sorted(p.name for p in (out / "leave_one_out").iterdir()) == ["fence.pt", "mesh_concave.pt", "stairs.pt"]
    assert main([*args, "--out", str(out)]) == 0
    assert json.loads((out / "params.json").read_text())["leave_one_out"] == folds
