"""The ``position`` G-buffer key: view-space positions (OpenGL axes), validated, depth derived from them."""
import numpy as np
import pytest
import torch

from torch_ao import GBuffer, PinholeCamera, load_gbuffer, save_npz
from torch_ao.examples import crease_gbuffer
from torch_ao.io import read_npz


@pytest.fixture
def crease():
    gb = crease_gbuffer(12, 16, dtype=torch.float64)
    pos = torch.where(gb.valid, gb.positions(), torch.full_like(gb.positions(), float("nan")))
    return gb, pos


def test_depth_is_derived_from_positions(crease):
    gb, pos = crease
    from_pos = GBuffer(None, gb.camera, position=pos)
    assert torch.equal(from_pos.valid, gb.valid)
    assert torch.equal(from_pos.depth[gb.valid], -pos[:, 2:3][gb.valid])
    assert torch.allclose(from_pos.depth[gb.valid], gb.depth[gb.valid], rtol=1e-12)
    assert torch.equal(from_pos.positions()[gb.valid.expand(-1, 3, -1, -1)], pos[gb.valid.expand(-1, 3, -1, -1)])
    # the background of positions() is finite (depth 1), like the depth path's
    assert bool(torch.isfinite(from_pos.positions()).all())


def test_derived_depth_carries_gradients_to_positions(crease):
    gb, pos = crease
    p = pos.clone().requires_grad_(True)
    GBuffer(None, gb.camera, position=p).safe_depth.sum().backward()
    expected = torch.zeros_like(pos)
    expected[:, 2:3] = -gb.valid.double()
    assert torch.equal(p.grad, expected)


def test_given_positions_replace_unprojected_depth(crease):
    gb, pos = crease
    moved = pos * 1.5  # not what depth says: positions() returns the buffer anyway
    both = GBuffer(gb.depth, gb.camera, position=moved)
    v = gb.valid.expand(-1, 3, -1, -1)
    assert torch.equal(both.positions()[v], moved[v])
    assert torch.equal(both.to(dtype=torch.float32).position, moved.float())


@pytest.mark.parametrize("case, match", [
    ("shape", r"position: expected shape \(B,3,H,W\)"),
    ("nan", "position: non-finite values on valid"),
    ("behind", "position: expected z < 0"),
    ("behind_no_depth", "position: expected z < 0"),
    ("size", "position: batch and image size must match depth"),
])
def test_bad_positions(crease, case, match):
    gb, pos = crease
    bad, depth = pos.clone(), gb.depth
    if case == "shape":
        bad = bad[:, :2]
    elif case == "nan":
        bad[0, 0, 5, 5] = float("nan")
    elif case in ("behind", "behind_no_depth"):
        bad[0, 2, 5, 5] = 0.5
        depth = None if case == "behind_no_depth" else depth
    elif case == "size":
        bad = bad[..., :-1]
    with pytest.raises(ValueError, match=match):
        GBuffer(depth, gb.camera, position=bad)


def test_npz_position_key_round_trips_without_depth(tmp_path, crease):
    gb, pos = crease
    np.savez(tmp_path / "pos.npz", position=pos[0].permute(1, 2, 0).numpy(), intrinsics=gb.camera.intrinsics[0].numpy())
    got, _ = load_gbuffer(tmp_path / "pos.npz")
    assert torch.equal(got.valid, gb.valid)
    assert torch.allclose(got.depth[gb.valid], gb.depth[gb.valid], rtol=1e-12)
    save_npz(tmp_path / "again.npz", got)
    raw = read_npz(tmp_path / "again.npz")
    assert raw["position"].shape == (1, 12, 16, 3) and raw["depth"].shape == (1, 12, 16)
    again, _ = load_gbuffer(tmp_path / "again.npz")
    v = gb.valid.expand(-1, 3, -1, -1)
    assert torch.allclose(again.positions()[v], got.position[v], rtol=1e-12)


def test_reference_files_carry_their_positions(tmp_path):
    from torch_ao.reference import get_scene, render_reference

    ref = render_reference(get_scene("stairs"), height=10, width=14, spp=2, progress=False)
    gb, extras = load_gbuffer(ref.save(tmp_path / "stairs.npz"))
    v = gb.valid.expand(-1, 3, -1, -1)
    # the renderer's positions are its depth unprojected: loaded as depth only (the cheaper fetch), kept as an extra
    assert gb.position is None and "position" in extras
    assert torch.allclose(extras["position"][v], gb.camera.unproject(gb.safe_depth)[v], rtol=1e-6, atol=1e-6)
    moved = extras["position"].clone()
    moved[:, 0] += 1e-3  # positions that are not the unprojected depth stay in the G-buffer
    save_npz(tmp_path / "moved.npz", gb, position=moved)
    assert torch.equal(load_gbuffer(tmp_path / "moved.npz")[0].position[v], moved[v])


# --------------------------------------------------------------------------------------------------
# The walk on a position buffer: where positions and depth agree, every method gives the same result.
WALK_CASES = [
    ("gtao", {}), ("hbao", {}), ("ue4_ssao", {}), ("pssao", {"walk": False}), ("ssao", {}),
    ("bitmask", {"mode": "hard"}), ("bitmask", {"mode": "soft"}), ("ssilvb", {"mode": "hard"}),
    ("bitmask", {"variant": "ssilvb_glsl", "glsl_numerics": "mesa"}),
]


def _position_twin(gb: GBuffer) -> GBuffer:
    """The same frame given as positions only (NaN on background), depth left to GBuffer."""
    pos = torch.where(gb.valid, gb.positions(), torch.full_like(gb.positions(), float("nan")))
    return GBuffer(None, gb.camera, normals=gb.normals, light=gb.light, position=pos)


@pytest.mark.parametrize("fetch", ["nearest", "bilinear"])
@pytest.mark.parametrize("name, options", WALK_CASES, ids=[f"{n}-{'-'.join(map(str, o.values()))}" for n, o in WALK_CASES])
def test_position_input_matches_depth_input(name, options, fetch):
    from torch_ao import get_method
    from torch_ao.examples import floor_wall_gbuffer

    gb, _ = floor_wall_gbuffer(24, 32, light_direction=(0.3, 0.8, 0.5), dtype=torch.float64)
    cls = get_method(name)
    options = dict(options)
    kwargs = dict(slices=3, steps=4, radius=1.5, jitter=False) if options.pop("walk", True) else {}
    kwargs |= options
    if options.get("variant") == "ssilvb_glsl":
        kwargs.pop("fetch", None)
    elif "fetch" in _init_names(cls):
        kwargs["fetch"] = fetch
    method = cls(**kwargs).double()
    from_depth, from_position = method(gb), method(_position_twin(gb))
    for key in ("visibility", "indirect"):
        a, b = getattr(from_depth, key), getattr(from_position, key)
        if a is not None:
            assert torch.allclose(a, b, rtol=0, atol=1e-9), (key, float((a - b).abs().max()))


def _init_names(cls) -> set[str]:
    import inspect

    names = set()
    for klass in cls.__mro__:
        if "__init__" in klass.__dict__:
            names |= set(inspect.signature(klass.__dict__["__init__"]).parameters)
    return names


def test_soft_bitmask_gradients_flow_to_positions():
    from torch_ao import BitmaskAO
    from torch_ao.examples import floor_wall_gbuffer

    gb, _ = floor_wall_gbuffer(16, 20, dtype=torch.float64)
    twin = _position_twin(gb)
    position = twin.position.clone().requires_grad_(True)
    g = GBuffer(None, gb.camera, normals=gb.normals, position=position)
    BitmaskAO(mode="soft", slices=2, steps=3, radius=1.5, jitter=False).double()(g).visibility.sum().backward()
    grad = position.grad[gb.valid.expand(-1, 3, -1, -1)]
    assert bool(torch.isfinite(grad).all()) and float(grad.abs().max()) > 0
    assert bool((position.grad[~gb.valid.expand(-1, 3, -1, -1)] == 0).all())


def test_bilinear_fetch_interpolates_positions_perspective_correctly():
    from torch_ao.walk import Frame
    from torch_ao.walk.fetch import Footprint

    H, W = 5, 6
    g = torch.Generator().manual_seed(3)
    P = torch.randn(1, 3, H, W, generator=g, dtype=torch.float64)
    P[:, 2] = -(1 + 4 * torch.rand(1, H, W, generator=g, dtype=torch.float64))  # in front, off the pixel rays
    frame = Frame(GBuffer(None, PinholeCamera.from_fov(60.0, H, W, dtype=torch.float64), position=P))
    su = torch.tensor([0.0, 1.25, 3.5, 4.9, -2.0, 7.5], dtype=torch.float64)
    sv = torch.tensor([0.0, 2.75, 1.5, 3.1, 1.2, 4.0], dtype=torch.float64)
    fp, _ = Footprint.at(frame, torch.zeros(6, dtype=torch.long), su, sv, "bilinear")
    got = fp.position(frame)
    grid = P[0].permute(1, 2, 0)
    for i in range(6):  # independent: the four clamped taps by hand
        u, v = float(su[i]), float(sv[i])
        u0, v0 = int(np.floor(u)), int(np.floor(v))
        fu, fv = u - u0, v - v0
        num, den = torch.zeros(3, dtype=torch.float64), 0.0
        for du, dv, w in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
            p = grid[min(max(v0 + dv, 0), H - 1), min(max(u0 + du, 0), W - 1)]
            num += w * p / -p[2]
            den += w / -float(p[2])
        assert torch.allclose(got[i], num / den, rtol=1e-12, atol=1e-12), i


def test_soft_bitmask_on_positions_gradcheck():
    from torch_ao import BitmaskAO
    from torch_ao.examples import crease_gbuffer

    gb = crease_gbuffer(6, 7, dtype=torch.float64)
    g = torch.Generator().manual_seed(1)  # off the pixel rays and off the crease's symmetry (sign flips there)
    position = _position_twin(gb).position + 0.02 * torch.rand(1, 3, 6, 7, generator=g, dtype=torch.float64)
    ao = BitmaskAO(mode="soft", slices=2, steps=2, radius=2.0, jitter=False, fetch="bilinear", tau=0.3).double()

    def f(position):
        return ao(GBuffer(None, gb.camera, normals=gb.normals, position=position)).visibility

    assert torch.autograd.gradcheck(f, (position.requires_grad_(True),), eps=1e-6, atol=1e-5)
