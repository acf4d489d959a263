"""Mitsuba 3 scene files (``torch-ao render scene.xml``, optional ``mitsuba``): shapes, albedo and the
camera as Mitsuba reads them, and the same render as the equivalent native scene within Monte Carlo
noise."""
from __future__ import annotations

import math
import sys

import numpy as np
import pytest
import torch

from test_reference import _judge
from torch_ao.cli import main
from torch_ao.io import load_gbuffer
from torch_ao.reference import Box, LookAt, Mesh, Plane, Scene, Sphere, look_at_matrix, mesh_scene, render_reference

XML = """<scene version="3.0.0">
    <sensor type="perspective">
        <float name="fov" value="50"/>
        <transform name="to_world"><lookat origin="-2, 1.5, 3" target="0, 0.4, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="64"/><integer name="height" value="48"/></film>
    </sensor>
    <shape type="sphere" id="a_ball">
        <point name="center" x="0" y="0.5" z="0"/><float name="radius" value="0.5"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.4, 0.6"/></bsdf>
    </shape>
    <shape type="cube" id="b_crate">
        <transform name="to_world"><scale value="0.3"/><translate x="1" y="0.3" z="0.2"/></transform>
    </shape>
    <shape type="rectangle" id="c_floor">
        <transform name="to_world"><scale value="50"/><rotate x="1" angle="-90"/></transform>
    </shape>
    <shape type="cylinder" id="d_pole">
        <point name="p0" x="-1" y="0" z="-0.5"/><point name="p1" x="-1" y="1.5" z="-0.5"/><float name="radius" value="0.1"/>
    </shape>
</scene>
"""


@pytest.fixture
def xml(tmp_path):
    pytest.importorskip("mitsuba", reason="Mitsuba 3 scene files need mitsuba (pip install -e '.[mitsuba]')")
    path = tmp_path / "scene.xml"
    path.write_text(XML)
    return path


def test_shapes_albedo_and_camera(xml):
    scene = mesh_scene([xml])
    ball, crate, floor, pole = scene.objects
    assert isinstance(ball, Sphere) and ball.center == (0.0, 0.5, 0.0) and ball.radius == pytest.approx(0.5)
    assert ball.albedo == pytest.approx((0.2, 0.4, 0.6), abs=1e-6)
    assert crate.albedo == pytest.approx((0.5, 0.5, 0.5))  # Mitsuba's default diffuse reflectance
    lo, hi = crate.bounds()
    assert torch.allclose(lo, torch.tensor([0.7, 0.0, -0.1], dtype=torch.float64), atol=1e-6)
    assert torch.allclose(hi, torch.tensor([1.3, 0.6, 0.5], dtype=torch.float64), atol=1e-6)
    assert float(floor.vertices[:, 1].abs().max()) < 1e-5 and float(floor.vertices[:, 0].max()) == pytest.approx(50)
    # the open cylinder: every vertex 0.1 from its axis x = -1, z = -0.5, between y = 0 and 1.5, no caps
    v = pole.vertices
    assert torch.allclose(torch.hypot(v[:, 0] + 1, v[:, 2] + 0.5), torch.full((v.shape[0],), 0.1, dtype=torch.float64), atol=1e-6)
    assert set(torch.round(v[:, 1], decimals=6).tolist()) == {0.0, 1.5}
    # camera: Mitsuba's fov is horizontal by default; 64x48 film
    view = scene.view
    assert view.eye == pytest.approx((-2.0, 1.5, 3.0))
    assert view.fov_y_degrees == pytest.approx(math.degrees(2 * math.atan(math.tan(math.radians(25)) * 48 / 64)))
    expected = look_at_matrix((-2, 1.5, 3), (0, 0.4, 0))[0]
    assert torch.allclose(look_at_matrix(view.eye, view.target, view.up)[0], expected, atol=1e-6)


def test_render_matches_the_native_scene_within_noise(xml, tmp_path):
    """The same geometry written natively: a Sphere, a Box, a Plane for the 100x100 floor (the view
    is judged only nearer than its edge) and the same tessellated pole; same seed, same rays."""
    mine = mesh_scene([xml])
    native = Scene([Sphere(center=(0, 0.5, 0), radius=0.5, albedo=(0.2, 0.4, 0.6)),
                    Box(center=(1, 0.3, 0.2), half_extents=(0.3, 0.3, 0.3), albedo=0.5),
                    Plane(albedo=0.5), Mesh(vertices=mine.objects[3].vertices, faces=mine.objects[3].faces, albedo=0.5)],
                   view=mine.view)
    spp = 32
    kw = dict(height=36, width=48, spp=spp, max_distance=0.6, seed=3, progress=False, backface=True)
    a, b = render_reference(mine, **kw), render_reference(native, **kw)
    same = a.gbuffer.object_id == b.gbuffer.object_id
    inside = b.gbuffer.depth < 30  # nearer than the floor's edge (the Plane goes on to the horizon)
    assert same[inside].double().mean() > 0.995 and set(a.gbuffer.object_id.unique().tolist()) == {0, 1, 2, 3, 4}
    v = inside & same
    assert torch.allclose(a.gbuffer.depth[v], b.gbuffer.depth[v], rtol=1e-4)
    assert torch.allclose(a.gbuffer.light[v.expand_as(a.gbuffer.light)], b.gbuffer.light[v.expand_as(b.gbuffer.light)], atol=1e-4)
    se = (a.ao_stderr.pow(2) + b.ao_stderr.pow(2)).sqrt()
    _judge(a.ao[v], se[v], b.ao[v].double(), spp)
    crate = (a.gbuffer.object_id == 2) & v
    assert torch.allclose(a.backface_depth[crate], b.backface_depth[crate], rtol=1e-4)


def test_cli_renders_the_file_with_its_camera(xml, tmp_path):
    out = tmp_path / "m.npz"
    assert main(["render", str(xml), "--width", "32", "--height", "24", "--spp", "2", "--no-progress", "--out", str(out)]) == 0
    gb, extras = load_gbuffer(out)
    expected = look_at_matrix((-2, 1.5, 3), (0, 0.4, 0))[0]
    assert torch.allclose(extras["world_to_view"][0].double(), expected, atol=1e-6)
    assert set(gb.object_id.unique().tolist()) <= {0, 1, 2, 3, 4} and gb.valid.double().mean() > 0.5


@pytest.mark.parametrize("text, match", [
    ("<scene version='3.0.0'><shape type='nonsense'/></scene>", "cannot read"),
    ("<scene version='3.0.0'><shape", "cannot read"),
    ("<scene version='3.0.0'></scene>", "has no shapes"),
])
def test_bad_scene_files_one_line_exit_2(xml, text, match, tmp_path, capsys):
    bad = tmp_path / "bad.xml"
    bad.write_text(text)
    out = tmp_path / "out" / "x.npz"
    assert main(["render", str(bad), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert match in err and "bad.xml" in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_missing_mitsuba_names_the_extra(tmp_path, monkeypatch, capsys):
    path = tmp_path / "scene.xml"
    path.write_text(XML)
    monkeypatch.setitem(sys.modules, "mitsuba", None)
    assert main(["render", str(path), "--out", str(tmp_path / "x.npz"), "--no-progress"]) == 2
    assert 'pip install -e ".[mitsuba]" (in the torch_ao checkout) or pip install mitsuba' in capsys.readouterr().err


def test_up_axis_is_refused_for_a_mitsuba_file(xml, tmp_path, capsys):
    out = tmp_path / "out" / "x.npz"
    assert main(["render", str(xml), "--up-axis", "z", "--out", str(out), "--no-progress"]) == 2
    assert capsys.readouterr().err == ("torch-ao render: error: --up-axis: not for Mitsuba scene files (scene.xml); "
                                       "it turns mesh files only\n")
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------ film size, principal point
FILM_XML = """<scene version="3.0.0">
    <sensor type="perspective">
        <float name="fov" value="60"/>{axis}
        <float name="principal_point_offset_x" value="0.1"/><float name="principal_point_offset_y" value="-0.05"/>
        <transform name="to_world"><lookat origin="-2, 1.5, 3" target="0, 0.4, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="{width}"/><integer name="height" value="{height}"/></film>
    </sensor>
    <shape type="sphere" id="a_ball"><point name="center" x="0" y="0.5" z="0"/><float name="radius" value="0.5"/></shape>
    <shape type="cube" id="b_crate">
        <transform name="to_world"><scale value="0.3"/><translate x="1" y="0.3" z="0.2"/></transform>
    </shape>
    <shape type="rectangle" id="c_floor"><transform name="to_world"><scale value="2"/><rotate x="1" angle="-90"/></transform></shape>
</scene>
"""


def _film_xml(path, width=160, height=96, fov_axis=None):
    axis = "" if fov_axis is None else f'<string name="fov_axis" value="{fov_axis}"/>'
    path.write_text(FILM_XML.format(axis=axis, width=width, height=height))
    return path


def _mitsuba_depth(path):
    """``(H, W)`` float64 view-axis depth of Mitsuba's own camera rays through the pixel centres of the
    file's film (``inf`` where the ray hits nothing): ``(hit - eye) . forward``, with the eye and the
    forward axis (``+Z``) of the sensor's ``to_world``."""
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    scene = mi.load_file(str(path))
    sensor = scene.sensors()[0]
    W, H = (int(x) for x in sensor.film().size())
    M = np.asarray(sensor.world_transform().matrix, dtype=np.float64)
    depth = np.full((H, W), np.inf)
    for j in range(H):
        for i in range(W):
            ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f((i + 0.5) / W, (j + 0.5) / H), mi.Point2f(0.5, 0.5))
            hit = scene.ray_intersect(ray)
            if hit.is_valid():
                depth[j, i] = float(np.dot(np.asarray(hit.p, dtype=np.float64) - M[:3, 3], M[:3, 2]))
    return torch.from_numpy(depth)


def _assert_same_as_mitsuba(out, expected):
    gb, _ = load_gbuffer(out)
    depth = gb.depth[0, 0].double()
    assert depth.shape == expected.shape
    mine, theirs = torch.isfinite(depth), torch.isfinite(expected)
    assert torch.equal(mine, theirs) and 0.2 < float(mine.double().mean()) < 0.8  # identical coverage, sky and floor
    assert float((depth[mine] - expected[mine]).abs().max()) < 1e-4


def test_film_size_and_principal_point_match_mitsubas_rays(xml, tmp_path):
    path = _film_xml(tmp_path / "film.xml")
    view = mesh_scene([path]).view
    assert view.film == (160, 96) and view.fov_axis == "x"
    assert view.principal_offset == pytest.approx((-0.1, 0.05))
    assert view.fov_y_degrees == pytest.approx(math.degrees(2 * math.atan(math.tan(math.radians(30)) * 96 / 160)))
    out = tmp_path / "film.npz"
    assert main(["render", str(path), "--spp", "2", "--no-progress", "--out", str(out)]) == 0  # no --width/--height
    gb, _ = load_gbuffer(out)
    assert gb.depth.shape[-2:] == (96, 160)
    K = gb.camera.intrinsics[0].double()  # horizontal FOV 60 degrees over 160 columns, the axis at film (0.4, 0.55)
    assert float(K[0, 0]) == pytest.approx(80 / math.tan(math.radians(30)), rel=1e-6)
    assert (float(K[0, 2]), float(K[1, 2])) == pytest.approx((0.4 * 160 - 0.5, 0.55 * 96 - 0.5), abs=1e-4)
    _assert_same_as_mitsuba(out, _mitsuba_depth(path))
    ref = render_reference(mesh_scene([path]), spp=2, progress=False)  # Python: the film's size too
    assert torch.equal(ref.gbuffer.depth, gb.depth) and torch.equal(ref.gbuffer.camera.intrinsics, gb.camera.intrinsics)


@pytest.mark.parametrize("fov_axis", [None, "y", "diagonal", "smaller", "larger"])
def test_width_height_override_keeps_the_fov_on_its_axis_as_mitsuba(xml, tmp_path, fov_axis):
    """--width/--height render what Mitsuba renders when the film itself has that size."""
    out = tmp_path / "o.npz"
    path = _film_xml(tmp_path / "film.xml", fov_axis=fov_axis)
    assert main(["render", str(path), "--width", "48", "--height", "80", "--spp", "2", "--no-progress",
                 "--out", str(out)]) == 0
    _assert_same_as_mitsuba(out, _mitsuba_depth(_film_xml(tmp_path / "resized.xml", 48, 80, fov_axis)))


@pytest.mark.parametrize("fov_axis", ["x", "y", "diagonal", "smaller", "larger"])
def test_fov_y_at_is_mitsubas_parse_fov(xml, fov_axis):
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    props = mi.Properties("perspective")
    props["fov"], props["fov_axis"] = 50.0, fov_axis

    def vertical(width, height):  # Mitsuba's horizontal FOV for the film, made vertical
        x_fov = math.radians(mi.parse_fov(props, width / height))
        return math.degrees(2 * math.atan(math.tan(x_fov / 2) * height / width))

    view = LookAt(fov_y_degrees=vertical(160, 96), film=(160, 96), fov_axis=fov_axis)
    for width, height in ((160, 96), (96, 160), (64, 64), (300, 100), (10, 90)):
        assert view.fov_y_at(width, height) == pytest.approx(vertical(width, height), rel=1e-9), (width, height)


def test_crop_window_is_refused(xml, tmp_path, capsys):
    path = tmp_path / "crop.xml"
    path.write_text(FILM_XML.format(axis="", width=160, height=96).replace(
        '<integer name="height" value="96"/>', '<integer name="height" value="96"/><integer name="crop_width" value="80"/>'))
    assert main(["render", str(path), "--out", str(tmp_path / "out" / "x.npz"), "--no-progress"]) == 2
    assert capsys.readouterr().err == (f"torch-ao render: error: scene: {path}: the film's crop window (80x96 of "
                                       "160x96) is not supported; render the whole film (its width and height)\n")
    assert not (tmp_path / "out").exists()
