"""Camera geometry, G-buffer validation, normals from depth, and the file format."""
import math

import numpy as np
import pytest
import torch

from torch_ao.camera import PinholeCamera
from torch_ao.examples import crease_gbuffer, example_gbuffer, plane_gbuffer
from torch_ao.gbuffer import GBuffer, normals_from_depth
from torch_ao.io import load_gbuffer, save_npz


def test_unproject_matches_closed_form_and_projects_back():
    cam = PinholeCamera.from_fov(50.0, 5, 7)
    depth = torch.rand(1, 1, 5, 7, dtype=torch.float64) + 0.5
    cam = cam.to(dtype=torch.float64)
    pos = cam.unproject(depth)[0]
    f = 0.5 * 5 / math.tan(math.radians(25))
    v, u = torch.meshgrid(torch.arange(5.0, dtype=torch.float64), torch.arange(7.0, dtype=torch.float64), indexing="ij")
    assert torch.allclose(pos[0], (u - 3) / f * depth[0, 0])
    assert torch.allclose(pos[1], -(v - 2) / f * depth[0, 0])  # +Y up, row 0 at the top
    assert torch.allclose(pos[2], -depth[0, 0])  # camera looks down -Z
    uu, vv, dd = cam.view_to_pixel(pos.permute(1, 2, 0))
    assert torch.allclose(uu, u) and torch.allclose(vv, v) and torch.allclose(dd, depth[0, 0])


def test_opengl_projection_round_trip_and_ndc_of_pixel_centres():
    K = torch.tensor([[[300.0, 0, 150.3], [0, 280.0, 90.7], [0, 0, 1]]], dtype=torch.float64)
    cam = PinholeCamera(K, 180, 320)
    P = cam.opengl_projection(0.1, 100.0)
    back = PinholeCamera.from_opengl_projection(P, 180, 320)
    assert torch.allclose(back.intrinsics, K)
    # The top-left pixel centre (0, 0) maps to NDC (-1 + 1/W, 1 - 1/H).
    point = cam.pixel_to_view(torch.tensor(0.0, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64), torch.tensor(3.0, dtype=torch.float64))
    clip = P[0] @ torch.cat((point, point.new_ones(1)))
    ndc = clip[:3] / clip[3]
    assert ndc[0].item() == pytest.approx(-1 + 1 / 320)
    assert ndc[1].item() == pytest.approx(1 - 1 / 180)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(intrinsics=torch.eye(3)[None] * torch.tensor([-1.0, 1, 1])), "focal"),
        (dict(intrinsics=torch.full((1, 3, 3), float("nan"))), "finite"),
        (dict(intrinsics=torch.eye(4)), "shape"),
        (dict(intrinsics=torch.eye(3, dtype=torch.long)), "floating"),
    ],
)
def test_bad_intrinsics(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        PinholeCamera(kwargs["intrinsics"], 4, 4)


def test_bad_fov_and_size():
    with pytest.raises(ValueError, match="fov_y_degrees"):
        PinholeCamera.from_fov(180.0, 4, 4)
    with pytest.raises(ValueError, match="height"):
        PinholeCamera.from_fov(60.0, 0, 4)


def _cam(h=4, w=5):
    return PinholeCamera.from_fov(60.0, h, w)


@pytest.mark.parametrize(
    "make, err, match",
    [
        (lambda: GBuffer(torch.ones(1, 4, 5), _cam()), ValueError, "depth: expected shape"),
        (lambda: GBuffer(torch.ones(1, 1, 4, 5, dtype=torch.long), _cam()), TypeError, "depth: expected a floating"),
        (lambda: GBuffer(-torch.ones(1, 1, 4, 5), _cam()), ValueError, "depth: negative"),
        (lambda: GBuffer(torch.ones(1, 1, 4, 5), _cam(4, 6)), ValueError, "camera: image size"),
        (lambda: GBuffer(torch.ones(1, 1, 4, 5), "camera"), TypeError, "camera: expected"),
        (lambda: GBuffer(torch.ones(1, 1, 4, 5), _cam(), normals=torch.ones(1, 2, 4, 5)), ValueError, "normals: expected shape"),
        (lambda: GBuffer(torch.ones(2, 1, 4, 5), _cam(), normals=torch.ones(1, 3, 4, 5)), ValueError, "normals: batch"),
        (lambda: GBuffer(torch.ones(1, 1, 4, 5), _cam(), normals=torch.full((1, 3, 4, 5), float("nan"))), ValueError, "normals: non-finite"),
        (lambda: GBuffer(torch.ones(1, 1, 4, 5), _cam(), normals=torch.zeros(1, 3, 4, 5)), ValueError, "normals: zero-length"),
        (lambda: GBuffer(torch.ones(1, 1, 4, 5), _cam(), light=torch.ones(1, 3, 4, 5, dtype=torch.long)), TypeError, "light: expected a floating"),
        (lambda: GBuffer(torch.ones(1, 1, 4, 5), _cam(), mask=torch.full((1, 1, 4, 5), 2.0)), ValueError, "mask"),
        (lambda: GBuffer(torch.ones(1, 1, 4, 5), _cam(), object_id=torch.ones(1, 1, 4, 5)), TypeError, "object_id"),
        (lambda: GBuffer(torch.ones(1, 1, 4, 5), _cam(), object_id=-torch.ones(1, 1, 4, 5, dtype=torch.long)), ValueError, "object_id"),
        (lambda: GBuffer(torch.ones(3, 1, 4, 5), PinholeCamera.from_fov(torch.tensor([50.0, 60.0]), 4, 5, 2)), ValueError, "camera: batch"),
    ],
)
def test_gbuffer_rejects_bad_input(make, err, match):
    with pytest.raises(err, match=match):
        make()


def test_gbuffer_background_kinds_and_safe_depth():
    depth = torch.tensor([[[[1.0, float("inf"), 0.0, float("nan"), 2.0]]]])
    mask = torch.tensor([[[[True, True, True, True, False]]]])
    gb = GBuffer(depth, PinholeCamera.from_fov(60.0, 1, 5), mask=mask)
    assert gb.valid.flatten().tolist() == [True, False, False, False, False]
    assert torch.isfinite(gb.safe_depth).all() and torch.isfinite(gb.positions()).all()
    assert torch.isfinite(gb.view_normals()).all()


def test_half_precision_depth_is_computed_in_float32():
    gb = GBuffer(torch.ones(1, 1, 4, 5, dtype=torch.float16), _cam())
    assert gb.depth.dtype == torch.float32 and gb.camera.intrinsics.dtype == torch.float32


@pytest.mark.parametrize("method", ["improved", "kornia"])
@pytest.mark.parametrize("tilt", [0.0, 40.0, 75.0])
def test_normals_from_depth_on_a_plane(method, tilt):
    gb = plane_gbuffer(24, 32, tilt_degrees=tilt, dtype=torch.float64)
    n = normals_from_depth(gb.depth, gb.camera, method=method)
    # kornia's central differences need the 3x3 neighbourhood on the plane; ours only one side.
    inside = gb.valid if method == "improved" else ~torch.nn.functional.max_pool2d((~gb.valid).double(), 3, 1, 1).bool()
    cos = torch.where(inside[:, 0], (n * gb.normals).sum(1), torch.ones_like(gb.depth[:, 0]))
    inner = cos[:, 2:-2, 2:-2] if method == "kornia" else cos
    assert gb.valid.sum() > 100
    assert inner.min().item() > 1 - 1e-9


def test_improved_normals_keep_the_crease_sharp_where_kornia_smears_it():
    gb = crease_gbuffer(24, 24, dtype=torch.float64)
    truth = gb.normals
    improved = (normals_from_depth(gb.depth, gb.camera, "improved") * truth).sum(1)
    kornia = (normals_from_depth(gb.depth, gb.camera, "kornia") * truth).sum(1)
    # Every pixel of the improved reconstruction is exact, including the two columns at the crease.
    assert improved.min().item() > 1 - 1e-9
    assert kornia[:, 2:-2, 2:-2].min().item() < 0.99


@pytest.mark.parametrize("scale", [1e-12, 1e-6, 1e6, 1e14])
def test_improved_normals_do_not_depend_on_the_depth_scale(scale):
    """A plane scaled about the camera keeps its normals: in float32 at depth 1e14 the world-unit cross
    product's squared length overflows (zero normals), at 1e-12 it falls below the degeneracy threshold
    (normals toward the camera)."""
    gb = plane_gbuffer(24, 32, tilt_degrees=40.0)
    reference = normals_from_depth(gb.depth, gb.camera)
    scaled = normals_from_depth(gb.depth * scale, gb.camera)
    assert torch.isfinite(scaled).all()
    assert (scaled * reference).sum(1).min().item() > 1 - 1e-5
    assert (reference * gb.normals).sum(1)[gb.valid[:, 0]].min().item() > 1 - 1e-5


@pytest.mark.parametrize("scale", [1e-3, 1e20])
def test_given_normals_of_any_length_are_made_unit(scale):
    gb = plane_gbuffer(8, 8, tilt_degrees=30)
    n = GBuffer(gb.depth, gb.camera, normals=gb.normals * scale).view_normals()
    assert (n * gb.normals).sum(1)[gb.valid[:, 0]].min().item() > 1 - 1e-6


def test_normals_from_depth_handle_background_and_gradients():
    gb = plane_gbuffer(8, 8, tilt_degrees=30, dtype=torch.float64)
    depth = gb.depth.clone()
    depth[..., 3, 3] = float("inf")
    depth.requires_grad_(True)
    n = normals_from_depth(depth, gb.camera)
    assert torch.isfinite(n).all()
    n.sum().backward()
    assert torch.isfinite(depth.grad).all() and depth.grad[..., 3, 3].item() == 0.0


def test_npz_round_trip(tmp_path):
    gb = plane_gbuffer(6, 7, tilt_degrees=20)
    mask = torch.ones(1, 1, 6, 7, dtype=torch.bool)
    mask[..., 0, 0] = False
    gb = GBuffer(gb.depth, gb.camera, normals=gb.normals, light=torch.rand(1, 3, 6, 7), mask=mask, object_id=gb.object_id)
    ao = torch.rand(1, 1, 6, 7)
    path = save_npz(tmp_path / "g.npz", gb, ao=ao, max_distance=np.inf)
    raw = np.load(path, allow_pickle=False)
    assert raw["depth"].shape == (1, 6, 7) and raw["normal"].shape == (1, 6, 7, 3)
    assert np.isinf(raw["depth"][0, 0, 0])  # background is stored as inf
    back, extras = load_gbuffer(path)
    assert torch.equal(back.valid, gb.valid)
    assert torch.allclose(back.depth[back.valid], gb.depth[gb.valid])
    assert torch.allclose(back.normals, gb.normals) and torch.allclose(back.light, gb.light)
    assert torch.equal(back.object_id, gb.object_id)
    assert torch.allclose(back.camera.intrinsics, gb.camera.intrinsics)
    assert torch.allclose(extras["ao"], ao) and math.isinf(float(extras["max_distance"]))


def test_npz_top_down_orientation_and_fov_camera(tmp_path):
    depth = np.ones((4, 6), dtype=np.float32)
    depth[0] = 2.0  # top row farther
    np.savez(tmp_path / "d.npz", depth=depth, fov_y_degrees=np.float32(60.0))
    gb, _ = load_gbuffer(tmp_path / "d.npz")
    pos = gb.positions()
    assert pos[0, 1, 0, 0] > 0 and pos[0, 1, -1, 0] < 0  # row 0 is above the view axis (+Y)
    assert gb.depth[0, 0, 0, 0] == 2.0


def test_npz_bad_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="path"):
        load_gbuffer(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a valid"):
        load_gbuffer(tmp_path / "junk.npz")
    np.savez(tmp_path / "pickled.npz", depth=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="pickled"):
        load_gbuffer(tmp_path / "pickled.npz")
    np.savez(tmp_path / "nocam.npz", depth=np.ones((3, 3), np.float32))
    with pytest.raises(ValueError, match="camera"):
        load_gbuffer(tmp_path / "nocam.npz")
    np.savez(tmp_path / "nodepth.npz", normal=np.ones((3, 3, 3), np.float32))
    with pytest.raises(ValueError, match="depth"):
        load_gbuffer(tmp_path / "nodepth.npz")
    ao = np.ones((3, 3), np.float32)
    ao[1, 1] = np.nan
    np.savez(tmp_path / "nanref.npz", depth=np.ones((3, 3), np.float32), fov_y_degrees=60.0, ao=ao)
    with pytest.raises(ValueError, match="ao: 1 non-finite"):
        load_gbuffer(tmp_path / "nanref.npz")


def test_to_takes_a_dtype_as_tensor_to_does():
    gb = example_gbuffer(6, 8)
    wide = gb.to(torch.float64)
    assert wide.depth.dtype == torch.float64 and wide.camera.intrinsics.dtype == torch.float64
    assert wide.depth.device == gb.depth.device
    assert torch.equal(wide.depth.float(), gb.depth)
    with pytest.raises(TypeError, match="two dtypes"):
        gb.to(torch.float64, torch.float32)
    camera = gb.camera.to(torch.float64)  # the camera alone, the same way
    assert camera.intrinsics.dtype == torch.float64 and camera.intrinsics.device == gb.camera.intrinsics.device
    assert torch.equal(camera.intrinsics.float(), gb.camera.intrinsics)
    with pytest.raises(TypeError, match="two dtypes"):
        gb.camera.to(torch.float64, torch.float32)
