"""Confinement: files a scene names (Mitsuba includes, shape filenames and ``$default`` parameters,
glTF buffer and image URIs, OBJ material libraries) are refused outside the scene's folder, symbolic
links included, before anything reads them; the message names the file and the reference and nothing
of the outside file; ``--allow-outside-paths`` / ``allow_outside_paths=True`` lets them through."""
from __future__ import annotations

import json
import os

import pytest

from torch_ao.cli import main
from torch_ao.reference import load_mesh_file, mesh_scene
from torch_ao.io.confine import OutsidePathError

SMALL = ["--width", "8", "--height", "6", "--spp", "2", "--quiet"]
SECRET = "secret line one\nsecret line two\nsecret line three\n"


@pytest.fixture
def layout(tmp_path):
    """``scene/`` (the scene's folder, with a box OBJ) beside ``outside/`` (a secret file and a box OBJ)."""
    inside, outside = tmp_path / "scene", tmp_path / "outside"
    inside.mkdir()
    outside.mkdir()
    box = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
    (inside / "box.obj").write_text(box)
    (outside / "box.obj").write_text(box)
    (outside / "secret.txt").write_text(SECRET)
    return inside, outside


def _refused(argv, capsys, *fragments):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert "outside the scene's folder" in err and "--allow-outside-paths" in err, err
    assert "secret" not in err.replace("secret.txt", "") and "line" not in err, err  # nothing of the file
    for fragment in fragments:
        assert fragment in err, (fragment, err)
    return err


def _mitsuba_scene(body: str) -> str:
    return f'<scene version="3.0.0">{body}<shape type="sphere"/></scene>'


MITSUBA_CASES = {
    "include absolute": lambda o: f'<include filename="{o}/secret.txt"/>',
    "include dotdot": lambda o: '<include filename="../outside/secret.txt"/>',
    "shape absolute": lambda o: f'<shape type="obj"><string name="filename" value="{o}/box.obj"/></shape>',
    "shape dotdot": lambda o: '<shape type="obj"><string name="filename" value="../outside/box.obj"/></shape>',
    "default": lambda o: f'<default name="f" value="{o}/secret.txt"/><include filename="$f"/>',
    "default prefix": lambda o: f'<default name="f" value="{o}/secret.tx"/><include filename="$ft"/>',
    "search path": lambda o: f'<path value="{o}"/>',
    "spectrum attribute": lambda o: f'<shape type="sphere"><bsdf type="diffuse"><spectrum name="reflectance" '
                                    f'filename="{o}/secret.txt"/></bsdf></shape>',
}


@pytest.mark.parametrize("case", list(MITSUBA_CASES))
def test_mitsuba_references_outside_are_refused(case, layout, capsys):
    inside, outside = layout
    xml = inside / "scene.xml"
    xml.write_text(_mitsuba_scene(MITSUBA_CASES[case](outside)))
    out = inside / "o.npz"
    _refused(["render", str(xml), "--out", str(out)] + SMALL, capsys, str(xml))
    assert not out.exists()
    with pytest.raises(OutsidePathError, match="outside the scene's folder"):
        mesh_scene([xml])


def test_mitsuba_include_inside_is_checked_in_turn(layout, capsys):
    inside, outside = layout
    (inside / "part.xml").write_text(f'<scene version="3.0.0"><include filename="{outside}/secret.txt"/></scene>')
    (inside / "scene.xml").write_text(_mitsuba_scene('<include filename="part.xml"/>'))
    _refused(["render", str(inside / "scene.xml"), "--out", str(inside / "o.npz")] + SMALL, capsys,
             str(inside / "part.xml"), "<include filename>")


def test_mitsuba_symlink_that_leaves_the_folder_is_outside(layout, capsys):
    inside, outside = layout
    os.symlink(outside / "box.obj", inside / "link.obj")
    (inside / "scene.xml").write_text(_mitsuba_scene('<shape type="obj"><string name="filename" value="link.obj"/></shape>'))
    _refused(["render", str(inside / "scene.xml"), "--out", str(inside / "o.npz")] + SMALL, capsys, "'link.obj'")


def test_mitsuba_inside_references_load_and_the_flag_allows_outside(layout):
    pytest.importorskip("mitsuba")
    inside, outside = layout
    (inside / "sub").mkdir()
    (inside / "sub" / "box.obj").write_text((inside / "box.obj").read_text())
    (inside / "scene.xml").write_text(_mitsuba_scene('<default name="f" value="sub/box.obj"/>'
                                                     '<shape type="obj"><string name="filename" value="$f"/></shape>'))
    assert len(mesh_scene([inside / "scene.xml"]).objects) == 2  # the box and the sphere
    (inside / "out.xml").write_text(_mitsuba_scene(f'<shape type="obj"><string name="filename" value="{outside}/box.obj"/></shape>'))
    with pytest.raises(OutsidePathError):
        mesh_scene([inside / "out.xml"])
    assert len(mesh_scene([inside / "out.xml"], allow_outside_paths=True).objects) == 2
    out = inside / "o.npz"
    assert main(["render", str(inside / "out.xml"), "--allow-outside-paths", "--out", str(out)] + SMALL) == 0
    assert out.is_file()


@pytest.fixture
def gltf(layout):
    """A .gltf in ``scene/`` with its two buffers moved to ``outside/``; returns (gltf path, header)."""
    trimesh = pytest.importorskip("trimesh")
    inside, outside = layout
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(), node_name="box")
    files = scene.export(file_type="gltf")
    header = json.loads(files.pop("model.gltf"))
    for name, data in files.items():
        (inside / name).write_bytes(data)
        (outside / name).write_bytes(data)
    path = inside / "model.gltf"
    path.write_text(json.dumps(header))
    return path, header


@pytest.mark.parametrize("uri", ["{o}/{name}", "../outside/{name}", "..%2Foutside%2F{name}", "file://{o}/{name}"])
def test_gltf_buffer_outside_is_refused(uri, gltf, layout, capsys):
    path, header = gltf
    outside = layout[1]
    name = header["buffers"][0]["uri"]
    header["buffers"][0]["uri"] = uri.format(o=outside, name=name)
    path.write_text(json.dumps(header))
    _refused(["render", "--mesh", str(path), "--out", str(path.parent / "o.npz")] + SMALL, capsys,
             "buffers[0].uri", str(path))
    with pytest.raises(OutsidePathError, match=r"buffers\[0\]\.uri"):
        load_mesh_file(path)
    if "/" in uri and "file:" not in uri:  # (trimesh does not decode %2F itself)
        meshes, _ = load_mesh_file(path, allow_outside_paths=True)
        assert meshes[0].faces.shape == (12, 3)


def test_gltf_image_outside_and_symlinked_buffer_are_refused(gltf, layout):
    path, header = gltf
    outside = layout[1]
    header["images"] = [{"uri": f"{outside}/secret.txt"}]
    path.write_text(json.dumps(header))
    with pytest.raises(OutsidePathError, match=r"images\[0\]\.uri"):
        load_mesh_file(path)
    del header["images"]
    name = header["buffers"][1]["uri"]
    os.symlink(outside / name, path.parent / "link.bin")
    header["buffers"][1]["uri"] = "link.bin"
    path.write_text(json.dumps(header))
    with pytest.raises(OutsidePathError, match=r"buffers\[1\]\.uri 'link.bin'"):
        load_mesh_file(path)


def test_gltf_inside_loads(gltf):
    meshes, _ = load_mesh_file(gltf[0])
    assert meshes[0].faces.shape == (12, 3)


def test_obj_material_library_outside_is_refused(layout, capsys):
    pytest.importorskip("trimesh")
    inside, outside = layout
    (outside / "m.mtl").write_text("newmtl red\nKd 1 0 0\n")
    obj = inside / "mat.obj"
    obj.write_text("mtllib ../outside/m.mtl\nusemtl red\n" + (inside / "box.obj").read_text())
    _refused(["render", "--mesh", str(obj), "--out", str(inside / "o.npz")] + SMALL, capsys, "'../outside/m.mtl'", str(obj))
    (inside / "m.mtl").write_text("newmtl red\nKd 1 0 0\n")
    obj.write_text("mtllib m.mtl\nusemtl red\n" + (inside / "box.obj").read_text())
    assert load_mesh_file(obj)[0][0].faces.shape == (4, 3)
