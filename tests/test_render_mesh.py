"""`torch-ao render --mesh FILE` without a built-in scene: OBJ/PLY/glTF files alone, one object id per
file or glTF node, a glTF camera, a ground plane, negative coordinates, back-face depth, and bad files
(one line, exit status 2, nothing written)."""
from __future__ import annotations

import argparse
import json
import math
import struct

import pytest
import torch

from torch_ao.cli import main
from torch_ao.commands.args import add_float_list, allow_negative_lists, parse_float_list
from torch_ao.io import load_gbuffer
from torch_ao.reference import gltf_camera, load_mesh_file, look_at_matrix, mesh_scene, render_reference
from torch_ao.io.mesh import UP_AXES, up_axis_rotation

trimesh = pytest.importorskip("trimesh", reason="trimesh reads the mesh files")

SMALL = ["--width", "24", "--height", "16", "--spp", "2", "--no-progress"]


def _world_points(path):
    """World positions ``(H*W, 3)`` of a saved render's pixels, its object ids and valid mask."""
    gb, extras = load_gbuffer(path)
    M = extras["world_to_view"][0].double()
    p = extras["position"][0].double().reshape(3, -1)
    world = (M[:3, :3].T @ (p - M[:3, 3:4])).T
    return world, gb.object_id[0, 0].reshape(-1), gb.valid[0, 0].reshape(-1), extras


def _eye(extras):
    M = extras["world_to_view"][0].double()
    return -M[:3, :3].T @ M[:3, 3]


@pytest.fixture
def two_node_glb(tmp_path):
    """A GLB with two nodes: a box at x = 0 (node "a_box") and a sphere at x = 2 (node "b_ball")."""
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.icosphere(subdivisions=2, radius=0.5), node_name="b_ball",
                       transform=trimesh.transformations.translation_matrix([2.0, 0.5, 0.0]))
    scene.add_geometry(trimesh.creation.box(extents=(1.0, 1.0, 1.0)), node_name="a_box",
                       transform=trimesh.transformations.translation_matrix([0.0, 0.5, 0.0]))
    path = tmp_path / "two.glb"
    scene.export(path)
    return path


# ------------------------------------------------------------------------------ comma lists
def test_parse_float_list_counts_and_names_the_flag():
    assert parse_float_list("--eye", "-2,1,3", 3) == (-2.0, 1.0, 3.0)
    assert parse_float_list("--eye", "-.5,1e-3,+4", 3) == (-0.5, 0.001, 4.0)
    assert parse_float_list("--eye", None, 3) is None
    with pytest.raises(ValueError, match=r"--eye: expected 3 comma-separated numbers x,y,z, got 2 in '-2,1'"):
        parse_float_list("--eye", "-2,1", 3, names="x,y,z")
    with pytest.raises(ValueError, match="--up: expected 3 comma-separated numbers, got 'a,b,c'"):
        parse_float_list("--up", "a,b,c", 3)
    with pytest.raises(ValueError, match="--up: expected finite numbers"):
        parse_float_list("--up", "nan,1,2", 3)


@pytest.mark.parametrize("argv", [["--v", "-2,1,3"], ["--v=-2,1,3"], ["--v", "-.5,-1e-3,2"], ["--v", "-2", "--w", "-1.5"]])
def test_negative_lists_reach_the_flag(argv):
    p = argparse.ArgumentParser()
    add_float_list(p, "--v", 3, "a vector")
    p.add_argument("--w", type=float)
    p.add_argument("--flag", action="store_true")
    ns = p.parse_args(argv + ["--flag"])
    assert ns.v == argv[0].split("=", 1)[1] if "=" in argv[0] else ns.v == argv[1]
    assert ns.flag


def test_without_the_helper_argparse_takes_a_negative_list_for_a_flag():
    p = argparse.ArgumentParser(exit_on_error=False)
    p.add_argument("--v")
    with pytest.raises((argparse.ArgumentError, SystemExit)):
        p.parse_args(["--v", "-2,1,3"])
    allow_negative_lists(p)
    assert p.parse_args(["--v", "-2,1,3"]).v == "-2,1,3"


def test_builtin_scene_with_negative_target_as_in_the_issue(tmp_path):
    out = tmp_path / "f.npz"
    assert main(["render", "fence", "--eye", "0.7,1,1.4", "--target", "-0.05,0.5,-0.5", "--out", str(out)] + SMALL) == 0
    _, _, _, extras = _world_points(out)
    expected = look_at_matrix((0.7, 1, 1.4), (-0.05, 0.5, -0.5))[0]
    assert torch.allclose(extras["world_to_view"][0].double(), expected, atol=1e-12)


@pytest.mark.parametrize("argv, match", [
    (["--eye", "-2,1"], "--eye: expected 3"),
    (["--target=-1,2,3,4"], "--target: expected 3"),
    (["--up", "-0,1"], "--up: expected 3"),
    (["--eye", "-2,x,1"], "--eye: expected 3"),
])
def test_wrong_lengths_name_the_flag_and_write_nothing(argv, match, tmp_path, capsys, two_node_glb):
    out = tmp_path / "out" / "x.npz"
    assert main(["render", "--mesh", str(two_node_glb), "--out", str(out)] + argv + SMALL) == 2
    err = capsys.readouterr().err
    assert match in err and err.count("\n") == 1
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------ mesh files alone
@pytest.mark.parametrize("spelling", [["--eye", "-2,1.5,3"], ["--eye=-2,1.5,3"]])
def test_obj_alone_with_negative_eye(tmp_path, spelling):
    path = tmp_path / "torus.obj"
    trimesh.creation.torus(1.0, 0.3).export(path)
    out = tmp_path / "t.npz"
    assert main(["render", "--mesh", str(path), "--target", "-0.05,0,-0.1", "--out", str(out)] + spelling + SMALL) == 0
    world, oid, valid, extras = _world_points(out)
    assert torch.allclose(_eye(extras), torch.tensor([-2.0, 1.5, 3.0], dtype=torch.float64), atol=1e-9)
    assert valid.any() and set(oid[valid].tolist()) == {1}
    # every visible point lies on the torus: distance to the core circle = minor radius
    w = world[valid]
    # trimesh's torus has its axis along Z: the core circle of radius 1 is in the XY plane
    ring = torch.sqrt(w[:, 0] ** 2 + w[:, 1] ** 2) - 1.0
    assert float((torch.sqrt(ring ** 2 + w[:, 2] ** 2) - 0.3).abs().max()) < 0.02


def test_gltf_one_id_per_node_ground_plane_and_backface(tmp_path, two_node_glb):
    out = tmp_path / "g.npz"
    assert main(["render", "--mesh", str(two_node_glb), "--eye", "1,2.5,-4", "--target", "1,0.3,0",
                 "--ground-plane", "--backface", "--out", str(out)] + SMALL) == 0
    world, oid, valid, extras = _world_points(out)
    assert set(oid[valid].tolist()) == {1, 2, 3}  # a_box, b_ball, the plane
    assert float(world[oid == 1, 0].abs().max()) <= 0.5 + 1e-4  # the box around x = 0
    assert float((world[oid == 2] - torch.tensor([2.0, 0.5, 0.0], dtype=torch.float64)).norm(dim=1).max()) <= 0.5 + 1e-4
    assert float(world[oid == 3, 1].abs().max()) < 1e-4  # the plane under the lowest vertex: y = 0
    gb, _ = load_gbuffer(out)
    back, depth = gb.backface_depth[0, 0].reshape(-1), gb.depth[0, 0].reshape(-1)
    assert bool(torch.isinf(back[oid == 3]).all()) and bool(torch.isinf(back[~valid]).all())
    meshes = (oid == 1) | (oid == 2)
    assert bool((back[meshes] > depth[meshes]).all())  # closed meshes have thickness
    assert float((back - depth)[oid == 2].max()) <= 1.0 + 1e-3  # at most the ball's diameter


def test_ground_plane_height_may_be_negative(tmp_path, two_node_glb):
    out = tmp_path / "g.npz"
    assert main(["render", "--mesh", str(two_node_glb), "--ground-plane", "-0.25", "--eye", "1,3,5",
                 "--target", "1,0,0", "--out", str(out)] + SMALL) == 0
    world, oid, valid, _ = _world_points(out)
    assert (oid == 3).any() and float((world[oid == 3, 1] + 0.25).abs().max()) < 1e-4


def rewrite_glb_json(src, dst, edit) -> None:
    """Write the GLB ``src`` to ``dst`` with its JSON chunk changed in place by ``edit(header)``."""
    data = src.read_bytes()
    jlen = struct.unpack_from("<I", data, 12)[0]
    header = json.loads(data[20:20 + jlen])
    edit(header)
    text = json.dumps(header).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + data[20 + jlen:]
    dst.write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)


def _with_camera(src, dst):
    """Rewrite the GLB ``src`` with a camera node nested under a translated parent."""
    angle = math.radians(30)

    def edit(header):
        header["cameras"] = [{"type": "perspective", "perspective": {"yfov": math.radians(50), "znear": 0.05}}]
        header["nodes"].append({"name": "rig", "translation": [1.0, 1.0, 0.0], "children": [len(header["nodes"]) + 1]})
        header["nodes"].append({"name": "cam", "camera": 0, "translation": [0.0, 0.0, 4.0],
                                "rotation": [0.0, math.sin(angle / 2), 0.0, math.cos(angle / 2)]})
        header["scenes"][header.get("scene", 0)]["nodes"].append(len(header["nodes"]) - 2)

    rewrite_glb_json(src, dst, edit)
    # expected camera-to-world: T(1,1,0) @ T(0,0,4) @ Ry(30 degrees)
    c, s = math.cos(angle), math.sin(angle)
    R = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)
    return torch.tensor([1.0, 1.0, 4.0], dtype=torch.float64), R


def test_gltf_camera_is_used_without_eye(tmp_path, two_node_glb):
    path = tmp_path / "cam.glb"
    eye, R = _with_camera(two_node_glb, path)
    cam = gltf_camera(path)
    assert cam.fov_y_degrees == pytest.approx(50)
    assert torch.allclose(torch.tensor(cam.eye, dtype=torch.float64), eye, atol=1e-12)
    out = tmp_path / "c.npz"
    assert main(["render", "--mesh", str(path), "--out", str(out)] + SMALL) == 0
    _, _, valid, extras = _world_points(out)
    M = extras["world_to_view"][0].double()
    assert torch.allclose(M[:3, :3], R.T, atol=1e-9) and torch.allclose(_eye(extras), eye, atol=1e-9)
    gb, _ = load_gbuffer(out)  # yfov 50 degrees over 16 rows
    assert float(gb.camera.fy.reshape(-1)[0]) == pytest.approx(8 / math.tan(math.radians(25)), rel=1e-6)
    # with --eye the file's camera is not used: the view looks at the meshes' centre
    out2 = tmp_path / "c2.npz"
    assert main(["render", "--mesh", str(path), "--eye", "-3,2,5", "--out", str(out2)] + SMALL) == 0
    _, _, _, extras2 = _world_points(out2)
    eye2 = torch.tensor([-3.0, 2.0, 5.0], dtype=torch.float64)
    assert torch.allclose(_eye(extras2), eye2, atol=1e-9)
    centre = torch.tensor([1.0, 0.5, 0.0], dtype=torch.float64)  # of the box [-0.5, 2.5] x [0, 1] x [-0.5, 0.5]
    forward = -extras2["world_to_view"][0, 2, :3].double()
    assert torch.allclose(forward, torch.nn.functional.normalize(centre - eye2, dim=0), atol=1e-6)


def test_framed_view_sees_the_meshes(tmp_path, two_node_glb):
    scene = mesh_scene([two_node_glb], ground_plane=None)
    assert "framing" in scene.description and len(scene.objects) == 2
    out = tmp_path / "f.npz"
    assert main(["render", "--mesh", str(two_node_glb), "--out", str(out)] + SMALL) == 0
    _, oid, valid, _ = _world_points(out)
    assert {1, 2} <= set(oid[valid].tolist())


def test_several_files_one_id_each_and_ply(tmp_path, two_node_glb):
    ply = tmp_path / "slab.ply"
    trimesh.creation.box(extents=(4.0, 0.1, 4.0)).export(ply)
    meshes, camera = load_mesh_file(ply)
    assert len(meshes) == 1 and meshes[0].faces.shape == (12, 3) and camera is None
    scene = mesh_scene([ply, two_node_glb])
    assert [o.object_id for o in scene.objects] == [1, 2, 3]
    assert [o.name for o in scene.objects] == ["slab.ply", "two.glb:a_box", "two.glb:b_ball"]


# ------------------------------------------------------------------------------ bad files
def _empty_gltf(path):
    path.write_text(json.dumps({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
                                "nodes": [{"name": "nothing"}]}))


@pytest.mark.parametrize("suffix, make, match", [
    (".gltf", _empty_gltf, "has no meshes"),
    (".obj", None, "no such file"),
    (".xyzw", lambda p: p.write_text("just text"), "cannot read"),
    (".glb", lambda p: p.write_bytes(b"glTF\x02\x00\x00\x00garbage"), "cannot read"),
])
def test_bad_files_one_line_exit_2_nothing_written(suffix, make, match, tmp_path, capsys):
    path = tmp_path / f"in{suffix}"
    if make is not None:
        make(path)
    out = tmp_path / "out" / "x.npz"
    assert main(["render", "--mesh", str(path), "--out", str(out), "--png", str(tmp_path / "out" / "x.png")] + SMALL) == 2
    err = capsys.readouterr().err
    assert match in err and str(path.name) in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_no_scene_and_no_mesh_is_an_error(capsys, tmp_path):
    assert main(["render", "--out", str(tmp_path / "x.npz"), "--no-progress"]) == 2
    assert "--mesh" in capsys.readouterr().err


@pytest.mark.slow
def test_million_triangle_mesh_through_embree(tmp_path):
    """A 1M-triangle closed torus file rendered alone through Embree: every visible point lies on the
    torus within its tessellation error, and the back-face depth is never shorter than the front."""
    pytest.importorskip("embreex", reason="meshes this large need Embree")
    import importlib.util
    import sys
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("bench_tracer", Path(__file__).resolve().parents[1] / "benchmarks" / "bench_tracer.py")
    bench = importlib.util.module_from_spec(spec)
    sys.modules["bench_tracer"] = bench
    spec.loader.exec_module(bench)
    verts, faces = bench.torus_mesh(1_000_000)
    assert faces.shape[0] == 1_000_000
    path = tmp_path / "torus.ply"
    trimesh.Trimesh(verts, faces, process=False).export(path)
    out = tmp_path / "t.npz"
    assert main(["render", "--mesh", str(path), "--eye", "-1.5,1.2,-2.2", "--target", "0,0.2,0", "--backface",
                 "--mesh-backend", "embree", "--out", str(out), "--width", "40", "--height", "24", "--spp", "2",
                 "--no-progress"]) == 0
    world, oid, valid, extras = _world_points(out)
    w = world[valid]
    assert valid.float().mean() > 0.1
    # torus of axis +Y, major radius 1, minor 0.3, centred at y = 0.3
    ring = torch.sqrt(w[:, 0] ** 2 + w[:, 2] ** 2) - 1.0
    assert float((torch.sqrt(ring ** 2 + (w[:, 1] - 0.3) ** 2) - 0.3).abs().max()) < 1e-3
    gb, _ = load_gbuffer(out)
    thickness = (gb.backface_depth - gb.depth)[gb.valid]
    assert bool((thickness > 0).all())


# ------------------------------------------------------------------------------ up axis
def _box_on_floor():
    """A unit box standing on a 2 x 2 floor quad at y = 0 (Y up); float32-exact coordinates."""
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    box.apply_translation([0.25, 0.5, -0.25])
    floor = trimesh.Trimesh(vertices=[[-1, 0, -1], [-1, 0, 1], [1, 0, 1], [1, 0, -1]], faces=[[0, 1, 2], [0, 2, 3]])
    return trimesh.util.concatenate([box, floor])


def test_up_axis_rotations_are_proper_and_lift_their_axis():
    for axis in UP_AXES:
        R = up_axis_rotation(axis)
        sign, i = (-1.0, axis[1]) if axis.startswith("-") else (1.0, axis)
        e = torch.zeros(3, dtype=torch.float64)
        e["xyz".index(i)] = sign
        assert torch.equal(R @ e, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)), axis
        assert torch.equal(R @ R.T, torch.eye(3, dtype=torch.float64)) and float(torch.linalg.det(R)) == 1.0
    z = up_axis_rotation("z")  # Blender's Z up: its front (-Y) faces +Z after the turn
    assert torch.equal(z @ torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"up_axis: expected one of \('y', 'z', 'x', '-y', '-z', '-x'\), got 'w'"):
        up_axis_rotation("w")


@pytest.mark.parametrize("axis", ["z", "x", "-y", "-z", "-x"])
def test_turned_mesh_renders_as_the_y_up_original(tmp_path, axis):
    original = _box_on_floor()
    original.export(tmp_path / "y_up.obj")
    turned = original.copy()
    turned.vertices = turned.vertices @ up_axis_rotation(axis).numpy()  # R^T p: the file as an axis-up tool writes it
    turned.export(tmp_path / f"turned.{'stl' if axis == 'z' else 'obj'}")
    a = mesh_scene([tmp_path / "y_up.obj"])
    b = mesh_scene([next(tmp_path.glob("turned.*"))], up_axis=axis)
    assert b.view.eye == pytest.approx(a.view.eye, abs=1e-9)  # the framing view sees the same bounds
    kw = dict(height=16, width=24, spp=4, max_distance=1.0, seed=1, progress=False)
    ra, rb = render_reference(a, **kw), render_reference(b, **kw)
    assert torch.equal(ra.gbuffer.valid, rb.gbuffer.valid) and float(ra.gbuffer.valid.double().mean()) > 0.1
    v = ra.gbuffer.valid
    assert torch.allclose(ra.gbuffer.depth[v], rb.gbuffer.depth[v], rtol=1e-5)
    assert torch.allclose(ra.gbuffer.normals, rb.gbuffer.normals, atol=1e-5)
    assert torch.allclose(ra.ao, rb.ao, atol=1e-5)
    assert torch.allclose(ra.gbuffer.light, rb.gbuffer.light, atol=1e-5)  # the light comes from above in both


def test_cli_up_axis_z_stl(tmp_path):
    original = _box_on_floor()
    original.export(tmp_path / "y_up.obj")
    turned = original.copy()
    turned.vertices = turned.vertices @ up_axis_rotation("z").numpy()
    turned.export(tmp_path / "z_up.stl")
    outs = {}
    for name, extra in (("y_up.obj", []), ("z_up.stl", ["--up-axis", "z"]), ("lying", [])):
        src = tmp_path / ("z_up.stl" if name == "lying" else name)
        outs[name] = tmp_path / f"{name}.npz"
        assert main(["render", "--mesh", str(src), "--out", str(outs[name])] + extra + SMALL) == 0
    (ga, ea), (gb, eb), (gc, ec) = (load_gbuffer(outs[n]) for n in ("y_up.obj", "z_up.stl", "lying"))
    assert torch.equal(ga.valid, gb.valid)
    assert torch.allclose(ga.depth[ga.valid], gb.depth[gb.valid], rtol=1e-5)
    assert torch.allclose(ea["ao"], eb["ao"], atol=1e-5) and torch.allclose(ga.normals, gb.normals, atol=1e-5)

    def mean_world_up(gbuf, extras):  # mean world-space n_y of the valid pixels
        n = extras["world_to_view"][0, :3, :3].double().T @ gbuf.normals[0].double().reshape(3, -1)
        return float(n[1][gbuf.valid.reshape(-1)].mean())

    # the floor and the box's top face up; without --up-axis the Z-up file lies on its side (they face +Z)
    assert mean_world_up(ga, ea) > 0.5 and mean_world_up(gb, eb) == pytest.approx(mean_world_up(ga, ea), abs=1e-5)
    assert abs(mean_world_up(gc, ec)) < 0.3


def test_up_axis_turns_a_gltf_camera_with_the_meshes(tmp_path, two_node_glb):
    path = tmp_path / "cam.glb"
    eye, R = _with_camera(two_node_glb, path)
    Rz = up_axis_rotation("z")
    (box, ball), cam = load_mesh_file(path, up_axis="z")
    (box0, ball0), _ = load_mesh_file(path)
    assert torch.equal(box.vertices, box0.vertices @ Rz.T) and torch.equal(ball.vertices, ball0.vertices @ Rz.T)
    assert torch.allclose(torch.tensor(cam.eye, dtype=torch.float64), Rz @ eye, atol=1e-12)
    assert torch.allclose(torch.tensor(cam.up, dtype=torch.float64), Rz @ R[:, 1], atol=1e-12)
    forward = torch.tensor(cam.target, dtype=torch.float64) - torch.tensor(cam.eye, dtype=torch.float64)
    assert torch.allclose(forward, Rz @ -R[:, 2], atol=1e-12) and cam.fov_y_degrees == pytest.approx(50)


# ------------------------------------------------------------------------------ orthographic cameras
def _with_cameras(src, dst, kinds):
    """Rewrite the GLB ``src`` with one camera node per kind ("orthographic"/"perspective"), in order."""
    def edit(header):
        header["cameras"] = [{"type": k, "name": f"{k[:5]}_cam", k: {"xmag": 2.0, "ymag": 1.5, "znear": 0.1, "zfar": 50.0}
                              if k == "orthographic" else {"yfov": math.radians(40), "znear": 0.1}} for k in kinds]
        for i in range(len(kinds)):
            header["nodes"].append({"name": f"cam{i}", "camera": i, "translation": [0.0, 1.0, 5.0 + i]})
            header["scenes"][header.get("scene", 0)]["nodes"].append(len(header["nodes"]) - 1)

    rewrite_glb_json(src, dst, edit)


def test_orthographic_only_camera_is_refused_by_name(tmp_path, two_node_glb, capsys):
    path = tmp_path / "ortho.glb"
    _with_cameras(two_node_glb, path, ["orthographic"])
    with pytest.raises(ValueError, match=r"cameras\[0\] 'ortho_cam' \(node 'cam0'\) is an orthographic camera"):
        mesh_scene([path])
    out = tmp_path / "out" / "x.npz"
    assert main(["render", "--mesh", str(path), "--out", str(out)] + SMALL) == 2
    assert capsys.readouterr().err == (
        f"torch-ao render: error: camera: {path}: cameras[0] 'ortho_cam' (node 'cam0') is an orthographic camera, which "
        "torch_ao cannot render; only perspective cameras are supported (add one, or delete the camera to frame the "
        "meshes)\n")
    assert not (tmp_path / "out").exists()


def test_a_perspective_camera_beside_an_orthographic_one_is_used(tmp_path, two_node_glb):
    path = tmp_path / "both.glb"
    _with_cameras(two_node_glb, path, ["orthographic", "perspective"])
    cam = gltf_camera(path)
    assert cam.fov_y_degrees == pytest.approx(40) and cam.eye == pytest.approx((0.0, 1.0, 6.0))
