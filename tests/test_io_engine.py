"""Engine G-buffers in: OpenEXR files written here with the OpenEXR package (Blender, Unreal and Unity
channel names, world-space normals, DirectX axes, distance depth, far background), 16-bit PNG depth,
and ``torch-ao convert`` end to end."""
import math
import sys

import numpy as np
import pytest
import torch

from torch_ao import GBuffer, PinholeCamera, load_gbuffer, save_npz
from torch_ao.cli import main
from torch_ao.examples import example_gbuffer
from torch_ao.io import read_npz

OpenEXR = pytest.importorskip("OpenEXR", reason="needs the exr extra: pip install -e '.[exr]'")

H, W = 24, 32
K = np.array([[30.0, 0, 14.2], [0, 31.0, 12.9], [0, 0, 1]])


def _scene() -> GBuffer:
    """A floor meeting a wall (exact planes) with light, ids, a background corner and an off-centre camera."""
    gb = example_gbuffer(H, W)
    cam = PinholeCamera(torch.tensor(K, dtype=torch.float32)[None], H, W)
    depth = gb.depth.clone()
    depth[..., :3, :4] = float("inf")
    return GBuffer(depth, cam, normals=gb.normals, light=gb.light, object_id=gb.object_id)


def _hwc(t: torch.Tensor) -> np.ndarray:
    return t[0].permute(1, 2, 0).numpy().astype(np.float32)


def _write_exr(path, channels: dict, header: dict | None = None, parts: dict | None = None):
    base = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    if parts:
        OpenEXR.File([OpenEXR.Part(base | {"name": n}, ch) for n, ch in parts.items()]).write(str(path))
    else:
        OpenEXR.File(base | (header or {}), {k: np.ascontiguousarray(v) for k, v in channels.items()}).write(str(path))


def _vector(prefix: str, x: np.ndarray, letters="XYZ") -> dict:
    return {f"{prefix}.{c}": np.ascontiguousarray(x[..., i]) for i, c in enumerate(letters)}


def _blender_channels(gb: GBuffer, albedo: np.ndarray) -> dict:
    depth = gb.depth[0, 0].numpy().copy()
    depth[~np.isfinite(depth)] = 1e10  # Blender's background depth
    return {"ViewLayer.Depth.Z": depth, **_vector("ViewLayer.Normal", _hwc(gb.normals)),
            **_vector("ViewLayer.DiffCol", albedo, "RGB"), "ViewLayer.IndexOB.X": gb.object_id[0, 0].numpy().astype(np.float32),
            **_vector("ViewLayer.Light", _hwc(gb.light), "RGB")}


def _assert_same(a: GBuffer, b: GBuffer, atol=1e-6, names=("normals",)):
    """``a`` (read) equals ``b`` (expected) on valid pixels: depth, camera and the buffers ``names``."""
    assert torch.equal(a.valid, b.valid)
    v = a.valid
    assert torch.allclose(a.depth[v], b.depth[v], rtol=0, atol=atol)
    for name in names:
        x, y = getattr(a, name), getattr(b, name)
        assert x is not None and y is not None, name
        assert torch.allclose(x[v.expand_as(x)], y[v.expand_as(y)], rtol=0, atol=atol), name
    assert torch.allclose(a.camera.intrinsics, b.camera.intrinsics, atol=1e-6)


@pytest.fixture
def scene():
    gb = _scene()
    albedo = np.random.default_rng(0).uniform(0.1, 0.9, (H, W, 3)).astype(np.float32)
    return gb, albedo


def test_blender_multilayer_exr_equals_npz(tmp_path, scene):
    gb, albedo = scene
    save_npz(tmp_path / "ref.npz", gb, albedo=albedo)
    header = {"intrinsics": K.astype(np.float32)}
    _write_exr(tmp_path / "frame.exr", _blender_channels(gb, albedo), header)
    ref, ref_extras = load_gbuffer(tmp_path / "ref.npz")
    got, extras = load_gbuffer(tmp_path / "frame.exr", normal_space="view")  # Blender's names: world unless told
    _assert_same(got, ref, names=("normals", "light"))
    assert torch.equal(got.object_id, ref.object_id) and got.object_id.dtype == torch.int64
    assert torch.allclose(extras["albedo"], ref_extras["albedo"], atol=1e-6)
    assert int((~got.valid).sum()) == 12  # the 1e10 corner is background with the default far


def test_multipart_unreal_names_and_half_channels(tmp_path, scene):
    gb, _ = scene
    depth = gb.depth[0, 0].numpy()
    parts = {"SceneDepth": {"R": np.where(np.isfinite(depth), depth, 65504).astype(np.float32)},
             "WorldNormal": {c: _hwc(gb.normals)[..., i].astype(np.float16) for i, c in enumerate("RGB")}}
    _write_exr(tmp_path / "unreal.exr", None, parts=parts)
    got, _ = load_gbuffer(tmp_path / "unreal.exr", intrinsics=(K[0, 0], K[1, 1], K[0, 2], K[1, 2]), far=65000.0)
    assert torch.equal(got.valid, gb.valid) and torch.equal(got.depth[got.valid], gb.depth[gb.valid])
    v = got.valid.expand(-1, 3, -1, -1)
    assert torch.allclose(got.normals[v], gb.normals[v], rtol=0, atol=1e-3)  # half floats: 11-bit mantissa


def test_world_space_normals_and_positions_with_a_view_matrix(tmp_path, scene):
    gb, _ = scene
    rng = np.random.default_rng(1)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))  # a rotation
    t = np.array([0.3, -1.2, 2.5])
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t  # world -> view: p_view = R p_world + t
    n_view, p_view = _hwc(gb.normals).astype(np.float64), _hwc(gb.positions()).astype(np.float64)
    n_world = n_view @ R  # R^T n for each row
    p_world = (p_view - t) @ R
    depth = gb.depth[0, 0].numpy()
    channels = {"Depth.V": depth, **_vector("Normal", n_world.astype(np.float32)),
                **_vector("Position", p_world.astype(np.float32))}
    # The header attribute follows Imath's row-vector convention: translation in the last row.
    imath = M.T.copy()
    assert np.allclose(imath[3, :3], t)
    _write_exr(tmp_path / "world.exr", channels, {"worldToCamera": imath})
    opts = dict(fov=None, intrinsics=(K[0, 0], K[1, 1], K[0, 2], K[1, 2]), normal_space="world", position_space="world")
    from_header, _ = load_gbuffer(tmp_path / "world.exr", **opts)
    _write_exr(tmp_path / "world_nohdr.exr", channels)
    from_option, _ = load_gbuffer(tmp_path / "world_nohdr.exr", view_matrix=M.reshape(-1).tolist(), **opts)
    for got in (from_header, from_option):
        _assert_same(got, gb, atol=2e-6)
        v = got.valid.expand(-1, 3, -1, -1)
        assert torch.allclose(got.positions()[v], gb.positions()[v], atol=1e-5)
    with pytest.raises(ValueError, match="view_matrix: normal_space='world' needs"):
        load_gbuffer(tmp_path / "world_nohdr.exr", intrinsics=opts["intrinsics"], normal_space="world")


def test_directx_convention_flips_z_of_normals_and_positions(tmp_path, scene):
    gb, _ = scene
    flip = np.array([1, 1, -1], np.float32)
    position = np.where(_hwc(gb.valid.float()) > 0, _hwc(gb.positions()), np.nan)  # NaN on background
    channels = {**_vector("Normal", _hwc(gb.normals) * flip), **_vector("Position", position * flip)}
    _write_exr(tmp_path / "dx.exr", channels, {"intrinsics": K.astype(np.float32)})
    got, _ = load_gbuffer(tmp_path / "dx.exr", convention="directx")
    _assert_same(got, gb)  # depth derived from the positions: -z after the flip
    with pytest.raises(ValueError, match="position: expected z < 0"):
        load_gbuffer(tmp_path / "dx.exr")  # read as OpenGL, the points are behind the camera


def test_distance_depth_is_converted_with_the_camera(tmp_path, scene):
    gb, _ = scene
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    ray = np.sqrt(((u - K[0, 2]) / K[0, 0]) ** 2 + ((v - K[1, 2]) / K[1, 1]) ** 2 + 1)
    depth = gb.depth[0, 0].numpy().astype(np.float64)
    _write_exr(tmp_path / "dist.exr", {"Z": (depth * ray).astype(np.float32)}, {"intrinsics": K.astype(np.float32)})
    got, _ = load_gbuffer(tmp_path / "dist.exr", depth_kind="distance")
    assert torch.equal(got.valid, gb.valid)
    assert torch.allclose(got.depth[got.valid], gb.depth[gb.valid], rtol=1e-6)
    as_z, _ = load_gbuffer(tmp_path / "dist.exr")
    assert float((as_z.depth - gb.depth)[gb.valid].max()) > 0.01  # the conversion matters here


def test_far_marks_background(tmp_path):
    depth = np.full((4, 5), 3.0, np.float32)
    depth[1, 2] = 500.0
    _write_exr(tmp_path / "far.exr", {"depth": depth})
    near, _ = load_gbuffer(tmp_path / "far.exr", fov=60.0, far=100.0)
    everything, _ = load_gbuffer(tmp_path / "far.exr", fov=60.0, far=math.inf)
    default, _ = load_gbuffer(tmp_path / "far.exr", fov=60.0)
    assert not bool(near.valid[0, 0, 1, 2]) and int(near.valid.sum()) == 19
    assert bool(everything.valid.all()) and bool(default.valid.all())
    assert float(near.camera.fov_y_degrees) == pytest.approx(60.0)


def test_unity_one_file_per_buffer_through_channels(tmp_path, scene):
    gb, _ = scene
    _write_exr(tmp_path / "depth.exr", {"R": gb.depth[0, 0].numpy().copy()})
    _write_exr(tmp_path / "normal.exr", {c: _hwc(gb.normals)[..., i].copy() for i, c in enumerate("RGB")})
    got, _ = load_gbuffer(tmp_path / "depth.exr", channels={"normal": "normal.exr"},
                          intrinsics=(K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    _assert_same(got, gb)


def test_sixteen_bit_png_depth(tmp_path):
    Image = pytest.importorskip("PIL.Image")
    mm = np.array([[0, 1000, 2500], [65535, 1234, 1]], dtype=np.uint16)
    Image.fromarray(mm).save(tmp_path / "depth.png")
    got, _ = load_gbuffer(tmp_path / "depth.png", depth_scale=0.001, fov=50.0)
    expected = torch.tensor(mm, dtype=torch.float64) * 0.001
    assert torch.equal(got.valid[0, 0], torch.tensor(mm != 0))
    assert torch.allclose(got.depth[0, 0][got.valid[0, 0]].double(), expected[mm != 0], rtol=1e-7)
    Image.fromarray(np.zeros((2, 3), np.uint8)).save(tmp_path / "eight.png")
    with pytest.raises(ValueError, match="16-bit"):
        load_gbuffer(tmp_path / "eight.png", fov=50.0)


def test_options_apply_to_npz_files_too(tmp_path, scene):
    gb, _ = scene
    depth = gb.depth.clone()
    depth[~gb.valid] = 1e10
    save_npz(tmp_path / "engine.npz", GBuffer(depth, gb.camera))
    got, _ = load_gbuffer(tmp_path / "engine.npz", far=1e6)
    assert torch.equal(got.valid, gb.valid)
    with pytest.raises(ValueError, match="channels: .npz files"):
        load_gbuffer(tmp_path / "engine.npz", channels={"depth": "Z"})


def test_missing_openexr_names_the_extra(tmp_path, monkeypatch):
    _write_exr(tmp_path / "a.exr", {"Z": np.ones((2, 2), np.float32)})
    monkeypatch.setitem(sys.modules, "OpenEXR", None)
    with pytest.raises(ImportError, match=r'pip install -e "\.\[exr\]" \(in the torch_ao checkout\) or pip install openexr'):
        load_gbuffer(tmp_path / "a.exr", fov=60.0)


# ------------------------------------------------------------------------------------------- the CLI
@pytest.fixture
def exr_files(tmp_path, scene):
    gb, albedo = scene
    _write_exr(tmp_path / "good.exr", _blender_channels(gb, albedo), {"intrinsics": K.astype(np.float32)})
    ch = _blender_channels(gb, albedo)
    del ch["ViewLayer.Depth.Z"]
    _write_exr(tmp_path / "nodepth.exr", ch)
    _write_exr(tmp_path / "sizes.exr", {"Z": np.ones((4, 5), np.float32)})
    _write_exr(tmp_path / "small_normals.exr", _vector("N", np.ones((3, 5, 3), np.float32)))
    pos = _hwc(gb.positions())
    pos[10, 10, 0] = np.nan
    _write_exr(tmp_path / "nanpos.exr", {"Depth.Z": gb.depth[0, 0].numpy().copy(), **_vector("P", pos)})
    ids = gb.object_id[0, 0].numpy().astype(np.float32) + 0.5
    _write_exr(tmp_path / "badids.exr", {"Z": gb.depth[0, 0].numpy().copy(), "IndexOB.X": ids})
    (tmp_path / "junk.exr").write_bytes(b"not an exr at all")
    return tmp_path


BAD = [
    (["{d}/nodepth.exr"], "no depth or position channel"),
    (["{d}/sizes.exr", "--fov", "60", "--channels", "normal=small_normals.exr:N"], "normal: 5x3 pixels, but depth is 5x4"),
    (["{d}/nanpos.exr", "--fov", "60"], "position: non-finite values on valid"),
    (["{d}/badids.exr", "--fov", "60"], "object_id: expected non-negative whole numbers"),
    (["{d}/junk.exr", "--fov", "60"], "not a readable OpenEXR file"),
    (["{d}/missing.exr"], "no such file"),
    (["{d}/good.exr", "--channels", "depth=ViewLayer.Nope"], "--channels: depth='ViewLayer.Nope' not found"),
    (["{d}/good.exr", "--channels", "colour=X"], "channels"),
    (["{d}/good.exr", "--view-matrix", "1,2,3"], "--view-matrix: expected 16"),
    (["{d}/good.exr", "--intrinsics", "-1,1,0,0"], "--intrinsics: expected four"),
    (["{d}/good.exr", "--fov", "200"], "--fov"),
    (["{d}/good.exr", "--far", "-1"], "--far"),
    (["{d}/good.exr", "--normal-space", "world"], "--view-matrix"),
    (["{d}/nodepth.exr", "--channels", "depth=ViewLayer.Normal.X", "--depth-kind", "distance"], "camera"),
]


@pytest.mark.parametrize("argv, message", BAD, ids=[f"{i}-" + c[1][:20] for i, c in enumerate(BAD)])
def test_convert_refuses_bad_files(exr_files, capsys, argv, message):
    out = exr_files / "out.npz"
    code = main(["convert", *[a.format(d=exr_files) for a in argv], "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "Traceback" not in err[0], err
    assert message in err[0], err[0]
    assert not out.exists()


def test_convert_end_to_end(exr_files, capsys, scene):
    gb, albedo = scene
    out = exr_files / "frame.npz"
    assert main(["convert", str(exr_files / "good.exr"), "--out", str(out), "--png", str(exr_files / "p.png"),
                 "--normal-space", "view"]) == 0  # view-space normals under Blender's names
    printed = capsys.readouterr().out
    assert "32x24, 756 valid pixels" in printed and "normals" in printed
    raw = read_npz(out)
    assert raw["depth"].shape == (1, H, W) and raw["normal"].shape == (1, H, W, 3) and raw["albedo"].shape == (1, H, W, 3)
    assert np.allclose(raw["intrinsics"], K)
    back, _ = load_gbuffer(out)
    _assert_same(back, gb, names=("normals", "light"))
    assert (exr_files / "p.png").stat().st_size > 0
    # the converted file is an ordinary input of the other commands
    assert main(["ao", str(out), "--method", "gtao", "--preset", "low", "--out", str(exr_files / "ao.npz")]) == 0
    assert main(["convert", str(exr_files / "good.exr"), "--list-channels"]) == 0
    assert "ViewLayer.Depth.Z  float32  32x24" in capsys.readouterr().out


@pytest.mark.parametrize("style", ["separate", "equals"])
def test_convert_view_matrix_accepts_negative_numbers(exr_files, style):
    M = "-1,0,0,0,0,1,0,0,0,0,-1,0,0,0,0,1"  # a half turn about +Y
    flags = ["--view-matrix", M] if style == "separate" else [f"--view-matrix={M}"]
    out = exr_files / f"{style}.npz"
    assert main(["convert", str(exr_files / "good.exr"), "--normal-space", "world", *flags, "--out", str(out)]) == 0
    gb = _scene()
    n = read_npz(out)["normal"][0]
    expected = _hwc(gb.normals) * np.array([-1, 1, -1])
    valid = gb.valid[0, 0].numpy()
    assert np.allclose(n[valid], expected[valid], atol=1e-6)


def test_a_backface_pass_reads_as_depth_does_and_feeds_the_backface_model(tmp_path, scene):
    """A front-face-culled depth pass (``BackfaceDepth``), stored as distance from the eye like the depth, with
    the background's far value where the ray never leaves: view-axis depth, ``inf`` there, and the back-face
    thickness model reads it as it reads the same layer from an ``.npz``."""
    from torch_ao import BitmaskAO
    from torch_ao.thickness import BackfaceThickness

    gb, _ = scene
    back = gb.depth + 0.3
    back[..., :, W // 2:] = float("inf")  # the floor's right half: no exit
    expected = GBuffer(gb.depth, gb.camera, normals=gb.normals, backface_depth=back)
    save_npz(tmp_path / "ref.npz", expected)
    lengths = expected.camera.unproject(torch.ones_like(gb.depth)).norm(dim=1, keepdim=True)[0, 0].numpy()
    as_distance = {k: np.where(np.isfinite(x), x * lengths, 1e10).astype(np.float32)
                   for k, x in (("Depth.V", gb.depth[0, 0].numpy()), ("BackfaceDepth.V", back[0, 0].numpy()))}
    _write_exr(tmp_path / "frame.exr", {**as_distance, **_vector("Normal", _hwc(gb.normals))})
    got, _ = load_gbuffer(tmp_path / "frame.exr", intrinsics=(K[0, 0], K[1, 1], K[0, 2], K[1, 2]),
                          depth_kind="distance", normal_space="view")
    ref, _ = load_gbuffer(tmp_path / "ref.npz")
    v = ref.valid
    assert torch.equal(got.valid, v)
    assert torch.equal(torch.isinf(got.backface_depth[v]), torch.isinf(ref.backface_depth[v]))
    finite = v & torch.isfinite(ref.backface_depth)
    assert torch.allclose(got.backface_depth[finite], ref.backface_depth[finite], rtol=1e-5, atol=0)
    module = BitmaskAO(thickness=BackfaceThickness(), trainable=False)
    with torch.no_grad():
        assert (module(got).visibility - module(ref).visibility).abs().max() <= 1e-4
