"""Built-in scenes (registry, randomisation, renderability), the file format and `torch-ao render`."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torch_ao.cli import main
from torch_ao.io import load_gbuffer, read_npz
from torch_ao.reference import MESH_SCENES, SCENES, Mesh, get_scene, list_scenes, render_reference

from conftest import mesh_scenes_missing

STRESS = ["sphere_on_plane", "fence", "room_corner", "stairs", "floating", "poles", "grazing_floor", "large_depth_range"]


def test_registry_has_the_stress_scenes_and_test_scenes():
    names = [n for n, _ in list_scenes()]
    for name in STRESS + ["infinite_wall", "closed_box", "mesh_on_floor"]:
        assert name in names and SCENES[name].description


@pytest.mark.parametrize("name", [pytest.param(n, marks=mesh_scenes_missing(n) if n in MESH_SCENES else ()) for n in SCENES])
def test_scene_defaults_randomisation_and_gbuffer(name):
    default = get_scene(name)
    assert default.name == name
    a, b, c = get_scene(name, seed=1), get_scene(name, seed=1), get_scene(name, seed=2)
    assert repr(a.objects) == repr(b.objects) and repr(a.view) == repr(b.view)
    if name not in ("infinite_plane",):
        assert repr(a.objects) + repr(a.view) + repr(a.light) != repr(c.objects) + repr(c.view) + repr(c.light)
    ref = render_reference(a, height=9, width=16, spp=2, max_distance=0.5, progress=False)
    gb = ref.gbuffer
    assert gb.valid.float().mean() > 0.3, "the default view should mostly see geometry"
    ids = {o.object_id for o in a.objects}
    assert set(gb.object_id[gb.valid].tolist()) <= ids and bool((gb.object_id[~gb.valid] == 0).all())
    assert bool(torch.isfinite(gb.light).all()) and bool((gb.light >= 0).all())
    assert bool(((ref.ao >= 0) & (ref.ao <= 1)).all())
    n = gb.normals[:, :, gb.valid[0, 0]]
    assert torch.allclose(n.norm(dim=1), torch.ones(()), atol=1e-4)


def test_large_depth_range_spans_decades():
    ref = render_reference(get_scene("large_depth_range"), height=90, width=160, spp=2, progress=False)
    d = ref.gbuffer.depth[ref.gbuffer.valid]
    assert float(d.max() / d.min()) > 1000


def test_saved_file_round_trips(tmp_path):
    ref = render_reference(get_scene("stairs"), height=12, width=20, spp=4, max_distance=0.5, indirect=True, progress=False)
    path = ref.save(tmp_path / "stairs.npz")
    gb, extras = load_gbuffer(path)
    assert torch.equal(gb.valid, ref.gbuffer.valid)
    assert torch.allclose(gb.depth[gb.valid], ref.gbuffer.depth[gb.valid])
    for key in ("ao", "ao_stderr", "ao_uniform", "ao_uniform_stderr", "albedo", "position", "indirect_reference",
                "indirect_reference_stderr"):
        assert key in extras, key
    assert torch.allclose(extras["ao"], ref.ao) and torch.allclose(extras["indirect_reference"], ref.indirect)
    assert float(extras["max_distance"]) == 0.5
    raw = read_npz(path)
    assert raw["normal"].shape == (1, 12, 20, 3) and raw["object_id"].dtype == np.int64


def test_cli_list(capsys):
    assert main(["render", "--list"]) == 0
    out = capsys.readouterr().out
    for name in STRESS:
        assert name in out


def test_cli_render_writes_npz_and_png(tmp_path, capsys):
    out, png = tmp_path / "o.npz", tmp_path / "o.png"
    code = main(["render", "room_corner", "--width", "16", "--height", "9", "--spp", "4", "--max-distance", "0.5",
                 "--eye", "3,2,3", "--target", "0.5,0.2,0.5", "--fov", "50", "--seed", "3", "--out", str(out),
                 "--png", str(png), "--no-progress"])
    assert code == 0
    assert " s " in capsys.readouterr().out  # prints the time taken
    gb, extras = load_gbuffer(out)
    assert gb.shape == (1, 1, 9, 16) and float(extras["max_distance"]) == 0.5
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_mesh_file(tmp_path):
    trimesh = pytest.importorskip("trimesh", reason="trimesh is needed to load mesh files")
    mesh_path = tmp_path / "box.ply"
    trimesh.creation.box(extents=(2.0, 1.0, 1.0)).export(mesh_path)
    m = Mesh.load(mesh_path, normalize=True)
    assert m.faces.shape == (12, 3) and abs(float(m.vertices[:, 1].min())) < 1e-9
    assert abs(float((m.vertices.max(0).values - m.vertices.min(0).values).max()) - 1) < 1e-9
    out = tmp_path / "m.npz"
    assert main(["render", "mesh_on_floor", "--mesh", str(mesh_path), "--mesh-normalize", "--width", "12", "--height", "8",
                 "--spp", "2", "--out", str(out), "--no-progress", "--mesh-backend", "torch"]) == 0
    gb, _ = load_gbuffer(out)
    assert int(gb.object_id.max()) <= 4


@pytest.mark.parametrize("argv, match", [
    (["render", "nope", "--out", "x.npz"], "SCENE: unknown scene"),
    (["render", "stairs"], "--out"),
    (["render", "stairs", "--out", "x.txt"], "--out"),
    (["render", "stairs", "--out", "x.npz", "--eye", "1,2"], "--eye"),
    (["render", "stairs", "--out", "x.npz", "--spp", "17"], "--spp"),
    (["render", "stairs", "--out", "x.npz", "--max-distance", "-2"], "--max-distance"),
    (["render", "stairs", "--out", "x.npz", "--fov", "200"], "--fov"),
    (["render", "stairs", "--out", "x.npz", "--width", "0"], "--width"),
    (["render", "stairs", "--out", "x.npz", "--mesh", "/no/such.obj"], "mesh"),
])
def test_cli_errors_name_the_argument_and_write_nothing(argv, match, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv + ["--width", "8", "--height", "6", "--no-progress"] if "--width" not in argv else argv + ["--no-progress"]) == 2
    assert match in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
