"""The shared slice-marching core: sample placement, slice geometry, angles, chunking, recompute."""
import math

import pytest
import torch

from torch_ao.examples import floor_wall_gbuffer, plane_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.ops import fast_acos
from torch_ao.walk import (Frame, PerspectiveBilinearDepth, SliceAccumulator, SlicePattern, interleaved_gradient_noise,
                           march)


class Recorder(SliceAccumulator):
    """Keeps every sample, and sums the exact unoccluded slice integral |n_p| (cos g + g sin g)."""

    def __init__(self):
        self.samples = []
        self.views = []  # (each sample's queries' V)
        self.geoms = []

    def begin_slice(self, q, geom):
        self.geoms.append(geom)
        return None

    def step(self, state, q, geom, sample):
        self.samples.append((geom, sample))
        self.views.append(q.view)
        return state

    def end_slice(self, state, q, geom):
        g = geom.normal_angle
        full = geom.normal_length * (torch.cos(g) + g * torch.sin(g))
        return {"norm": full[:, None]}

    def finish(self, sums, q, num_slices):
        return {"visibility": sums["norm"] / num_slices}


def test_interleaved_gradient_noise_values():
    u = torch.tensor([0.0, 1.0, 10.0])
    v = torch.tensor([0.0, 2.0, 3.0])
    expected = [math.modf(52.9829189 * math.modf(0.06711056 * x + 0.00583715 * y)[0])[0] for x, y in zip(u.tolist(), v.tolist())]
    assert torch.allclose(interleaved_gradient_noise(u, v), torch.tensor(expected, dtype=torch.float64))
    assert not torch.allclose(interleaved_gradient_noise(u, v, seed=1), interleaved_gradient_noise(u, v))


def test_fast_acos_is_close_to_acos():
    x = torch.linspace(-1, 1, 1001, dtype=torch.float64)
    assert (fast_acos(x) - torch.acos(x)).abs().max().item() < 2e-2  # HDRP's polynomial


def test_background_costs_nothing_and_queries_are_valid_pixels():
    gb = plane_gbuffer(10, 12, tilt_degrees=80)  # the horizon is in view
    frame = Frame(gb)
    assert len(frame.queries) == int(gb.valid.sum()) < 10 * 12


@pytest.mark.parametrize("azimuth", ["view", "screen"])
def test_samples_lie_in_the_slice_plane_within_the_radius(azimuth):
    gb = plane_gbuffer(32, 40, tilt_degrees=50, dtype=torch.float64)
    rec = Recorder()
    pattern = SlicePattern(3, 4, 0.5, fetch="bilinear", border="drop", azimuth=azimuth, step_power=2.0)
    march(Frame(gb), pattern, rec)
    assert len(rec.samples) == 3 * 2 * 4
    for (geom, s), view in zip(rec.samples, rec.views):
        ok = s.valid
        assert ok.float().mean() > 0.5
        axis = torch.cross(geom.tangent, view, dim=-1)  # the slice plane's normal
        off_plane = (s.delta * axis).sum(-1).abs() / s.distance
        assert off_plane[ok].max().item() < 1e-9
        assert s.distance_px[ok].min().item() >= 1.0 - 1e-9
        radius_px = pattern.radius_px(geom)
        assert (s.distance_px[ok] <= torch.maximum(radius_px[ok], torch.ones_like(radius_px[ok])) + 1e-9).all()
        # On a plane every sample lies on the tangent line: at n +- pi/2 in signed slice angles.
        expected = math.pi / 2 + s.side * geom.normal_angle
        assert torch.allclose(s.angle()[ok], expected[ok], atol=1e-9)
        assert torch.allclose(s.cos_view()[ok], torch.cos(s.angle())[ok], atol=1e-9)


def test_view_azimuth_makes_the_unoccluded_slice_integral_exact():
    # With slices uniform around V, mean |n_p| (cos g + g sin g) -> 1 (the cosine-weighted hemisphere);
    # uniform screen angles are biased off-centre (the approximation of XeGTAO/HDRP).
    gb = plane_gbuffer(24, 32, tilt_degrees=65, fov_y_degrees=90, dtype=torch.float64)
    exact = march(Frame(gb), SlicePattern(64, 1, 0.1, jitter=False), Recorder())["visibility"]
    screen = march(Frame(gb), SlicePattern(64, 1, 0.1, jitter=False, azimuth="screen"), Recorder())["visibility"]
    assert (exact - 1).abs().max().item() < 1e-3
    assert (screen - 1).abs().max().item() > 1e-2


def test_chunking_and_recompute_give_identical_values_and_gradients():
    gb, _ = floor_wall_gbuffer(20, 24, dtype=torch.float64)

    # a smooth sum over the steps: a maximum's gradient follows float ties, and chunks of other lengths may
    # round an elementwise op 1 ulp apart (vector body against tail), which moves a tie
    class SumCos(Recorder):
        def begin_slice(self, q, geom):
            return torch.zeros_like(q.u)

        def step(self, total, q, geom, s):
            return torch.where(s.valid, total + torch.cos(s.angle()).square(), total)

        def end_slice(self, best, q, geom):
            return {"visibility": best[:, None]}

        def finish(self, sums, q, num_slices):
            return sums

    results = []
    for chunk, recompute in ((None, False), (37, False), (37, True)):
        depth = gb.depth.clone().requires_grad_(True)
        g = GBuffer(depth, gb.camera, normals=gb.normals)
        frame = Frame(g)
        radius = torch.tensor(0.7, dtype=torch.float64, requires_grad=True)
        out = march(frame, SlicePattern(2, 3, radius, fetch="bilinear"), SumCos(), chunk_size=chunk, recompute=recompute)
        out["visibility"].square().sum().backward()
        results.append((out["visibility"].detach(), depth.grad, radius.grad))
    for other in results[1:]:
        for a, b in zip(results[0], other):
            assert torch.allclose(a, b, rtol=1e-12, atol=1e-12)
    assert results[0][2].abs().item() > 0  # bilinear fetch makes the radius differentiable


def test_jitter_is_seeded_and_can_be_switched_off():
    gb = plane_gbuffer(8, 8)

    def first_slice(**kw):
        rec = Recorder()
        march(Frame(gb), SlicePattern(2, 1, 1.0, azimuth="screen", **kw), rec)
        return rec.geoms[0].pixels_per_unit

    assert torch.equal(first_slice(seed=3), first_slice(seed=3))
    assert not torch.equal(first_slice(seed=3), first_slice(seed=4))
    off = first_slice(jitter=False)
    assert off[:, 1].abs().max().item() < 1e-6 and off[:, 0].min().item() > 0  # the first slice is horizontal


@pytest.mark.parametrize("kwargs, match", [
    (dict(slices=0), "slices"), (dict(steps=1.5), "steps"), (dict(fetch="cubic"), "fetch"),
    (dict(border="wrap"), "border"), (dict(azimuth="x"), "azimuth"), (dict(step_power=0), "step_power"),
])
def test_pattern_rejects_bad_options(kwargs, match):
    args = dict(slices=2, steps=2, radius=1.0) | kwargs
    with pytest.raises(ValueError, match=match):
        SlicePattern(args.pop("slices"), args.pop("steps"), args.pop("radius"), **args)


def _plain_perspective_bilinear(safe_depth, index, fu, fv):
    w = torch.stack(((1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv), -1)
    return 1.0 / (w / safe_depth[index]).sum(-1)


def test_perspective_bilinear_depth_matches_autograd_and_finite_differences():
    g = torch.Generator().manual_seed(5)
    depth = (0.5 + 3 * torch.rand(12, generator=g, dtype=torch.float64)).requires_grad_()
    index = torch.randint(0, 12, (7, 4), generator=g)
    index[0] = 3  # all four taps on one texel: the depth itself
    fu = torch.rand(7, generator=g, dtype=torch.float64).requires_grad_()
    fv = torch.rand(7, generator=g, dtype=torch.float64).requires_grad_()
    ours = PerspectiveBilinearDepth.apply(depth, index, fu, fv)
    plain = _plain_perspective_bilinear(depth, index, fu, fv)
    assert torch.allclose(ours, plain, rtol=1e-14) and torch.allclose(ours[0], depth[3])
    weights = torch.randn(7, dtype=torch.float64, generator=g)
    for a, b in zip(torch.autograd.grad((ours * weights).sum(), (depth, fu, fv)),
                    torch.autograd.grad((plain * weights).sum(), (depth, fu, fv))):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-14)
    assert torch.autograd.gradcheck(lambda d, u, v: PerspectiveBilinearDepth.apply(d, index, u, v), (depth, fu, fv))


def test_perspective_bilinear_depth_is_exact_on_a_plane():
    # 1/depth is affine in screen space across a plane, so any interpolation of it between texels
    # is the plane's own depth there.
    a, b, c = 0.3, -0.2, 0.5  # 1/z = a u + b v + c on a 4x4 grid
    u, v = torch.meshgrid(torch.arange(4.0, dtype=torch.float64), torch.arange(4.0, dtype=torch.float64), indexing="xy")
    depth = (1.0 / (a * u + b * v + c + 2.0)).reshape(-1)
    fu, fv = torch.tensor([0.25, 0.7], dtype=torch.float64), torch.tensor([0.5, 0.1], dtype=torch.float64)
    u0, v0 = torch.tensor([1, 2]), torch.tensor([0, 2])
    index = torch.stack((v0 * 4 + u0, v0 * 4 + u0 + 1, (v0 + 1) * 4 + u0, (v0 + 1) * 4 + u0 + 1), -1)
    expected = 1.0 / (a * (u0 + fu) + b * (v0 + fv) + c + 2.0)
    assert torch.allclose(PerspectiveBilinearDepth.apply(depth, index, fu, fv), expected, rtol=1e-13)


class BatchedRecorder(Recorder):
    batch_steps = True


@pytest.mark.parametrize("fetch", ["nearest", "bilinear"])
def test_batched_steps_see_the_same_samples_block_major(fetch):
    gb, _ = floor_wall_gbuffer(12, 16)
    frame = Frame(gb)
    pattern = SlicePattern(2, 3, 0.8, fetch=fetch, border="drop")
    one, batched = Recorder(), BatchedRecorder()
    march(frame, pattern, one)
    march(frame, pattern, batched)
    n = len(frame.queries)
    assert len(one.samples) == 2 * 2 * 3 and len(batched.samples) == 2 * 2
    for k, (_, sample) in enumerate(batched.samples):
        assert sample.steps == 3 and sample.step is None and sample.position.shape == (3 * n, 3)
        for j in range(3):
            ref = one.samples[3 * k + j][1]
            assert ref.side == sample.side and ref.step == j
            rows = slice(j * n, (j + 1) * n)
            for name in ("position", "valid", "along_view", "along_tangent", "distance"):
                assert torch.equal(getattr(sample, name)[rows], getattr(ref, name)), name


def _walk_gradients(monkeypatch, fused: bool, fetch: str, border: str, batch: int, sparse: bool = False):
    """Gradients of a weighted sum of every sample's along_view/along_tangent (batched steps) to the
    depth and the radius, with the fused :class:`SampleAlong` or plain autograd."""
    import torch_ao.walk as walk

    monkeypatch.setattr(walk.Footprint, "fusable", lambda self, frame: fused)
    gb, _ = floor_wall_gbuffer(10, 14, dtype=torch.float64)
    torch.manual_seed(3)
    depth = torch.cat([gb.depth * (1 + 0.02 * torch.rand_like(gb.depth)) for _ in range(batch)]).requires_grad_(True)
    radius = torch.tensor(0.9, dtype=torch.float64, requires_grad=True)
    frame = Frame(GBuffer(depth, gb.camera, normals=torch.cat([gb.normals] * batch)))
    rec = BatchedRecorder()
    march(frame, SlicePattern(2, 3, radius, fetch=fetch, border=border, step_power=1.5), rec)
    loss = 0
    for k, (_, sample) in enumerate(rec.samples):
        w = torch.linspace(-1, 1, sample.along_view.shape[0], dtype=torch.float64)
        if sparse:  # most samples without a gradient: the backward works on the others only
            w = w * (torch.arange(w.shape[0]) % 7 == 3)
        loss = loss + (w * sample.along_view).sum() + ((k + 1) * w.flip(0) * sample.along_tangent).sum()
    assert all((type(s.along_view.grad_fn).__name__ == "SampleAlongBackward") == fused for _, s in rec.samples)
    g_depth, g_radius = torch.autograd.grad(loss, (depth, radius), allow_unused=True)
    return g_depth, torch.zeros(()) if g_radius is None else g_radius  # nearest texels do not move with the radius


@pytest.mark.parametrize("fetch,border,batch", [("bilinear", "drop", 1), ("bilinear", "clamp", 2),
                                                ("nearest", "clamp", 1), ("nearest", "drop", 2)])
@pytest.mark.parametrize("sparse", [False, True])
def test_fused_sample_gradients_match_plain_autograd(monkeypatch, fetch, border, batch, sparse):
    fused = _walk_gradients(monkeypatch, True, fetch, border, batch, sparse)
    plain = _walk_gradients(monkeypatch, False, fetch, border, batch, sparse)
    assert fused[0].abs().max() > 0 and (fetch == "nearest" or fused[1] != 0)
    for a, b in zip(fused, plain):
        assert torch.allclose(a.double(), b.double(), rtol=1e-10, atol=1e-12)


class PairRecorder(SliceAccumulator):
    """Keeps the samples of each paired step and counts the walks begun."""

    paired_sides = True

    def __init__(self):
        self.pairs, self.walks = [], []

    def begin_walk(self, q):
        self.walks.append(len(q))

    def begin_slice(self, q, geom):
        return None

    def step_pair(self, state, q, geom, plus, minus):
        self.pairs.append((plus, minus))
        return state

    def end_slice(self, state, q, geom):
        return {"one": torch.ones_like(q.depth)[:, None]}

    def finish(self, sums, q, num_slices):
        return {"visibility": sums["one"] / num_slices}


def test_paired_sides_see_step_j_of_both_sides_and_begin_walk_runs_once_per_chunk():
    gb, _ = floor_wall_gbuffer(12, 16, dtype=torch.float64)
    frame = Frame(gb)
    n = len(frame.queries)
    pattern = SlicePattern(2, 3, 0.8, fetch="bilinear", border="drop")
    rec, one = PairRecorder(), Recorder()
    march(frame, pattern, rec, chunk_size=50)
    march(frame, pattern, one)
    chunks = [min(50, n - s) for s in range(0, n, 50)]
    assert rec.walks == chunks
    assert len(rec.pairs) == len(chunks) * 2 * 3
    first = rec.pairs[: 2 * 3]  # the first chunk: slices x steps pairs
    for k, (plus, minus) in enumerate(first):
        assert (plus.side, minus.side) == (1, -1) and plus.step == minus.step == k % 3
        assert torch.equal(plus.offset, -minus.offset)  # the two sides are mirror images on screen
        ref = one.samples[(k // 3) * 6 + k % 3][1]  # slice k // 3, side +1, step k % 3 of the unpaired walk
        assert torch.equal(plus.position, ref.position[:50])


def test_sample_offset_and_inside_are_the_screen_position():
    gb = plane_gbuffer(10, 12, tilt_degrees=30, dtype=torch.float64)
    rec = Recorder()
    march(Frame(gb), SlicePattern(2, 2, 3.0, fetch="nearest", border="clamp", jitter=False), rec)
    _, H, W = Frame(gb).shape
    q = Frame(gb).queries
    for geom, s in rec.samples:
        u, v = q.u + s.offset[:, 0], q.v + s.offset[:, 1]
        expected = (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        assert torch.equal(s.inside, expected)
        assert torch.allclose(s.distance_px, s.offset.norm(dim=-1))
    assert any(not bool(s.inside.all()) for _, s in rec.samples)  # a radius of 3 leaves the image somewhere


def test_an_accumulator_without_single_steps_is_refused_by_name():
    class OnlyPairs(PairRecorder):
        paired_sides = False

    with pytest.raises(TypeError, match="OnlyPairs"):
        march(Frame(plane_gbuffer(6, 6)), SlicePattern(1, 1, 1.0), OnlyPairs())


def test_clamped_gradient_keeps_values_and_bounds_the_slope_at_one():
    from torch_ao.ops import safe_acos, safe_fast_acos

    x = torch.tensor([1.0, -1.0, 1 - 1e-7, 0.3], dtype=torch.float64, requires_grad=True)
    y = safe_fast_acos(x)
    assert torch.equal(y.detach(), fast_acos(x.detach()))
    (g,) = torch.autograd.grad(y.sum(), x)
    plain = x.detach().clone().requires_grad_(True)
    (g_plain,) = torch.autograd.grad(fast_acos(plain).sum(), plain)
    assert g_plain[2] < -2000  # fast_acos' own slope near 1 is huge (infinite at 1, where it is taken as 0)
    assert g[:3].tolist() == [0.0, 0.0, 0.0] and g[3] == g_plain[3]  # beyond 1 - eps: none; inside: the same
    x2 = x.detach().clone().requires_grad_(True)
    (ga,) = torch.autograd.grad(safe_acos(x2)[3], x2)
    assert math.isclose(float(ga[3]), -1 / math.sqrt(1 - 0.09), rel_tol=1e-12)  # d acos = -1/sqrt(1-x^2)


def test_projection_round_trips_through_the_camera_formulas():
    from torch_ao.camera import pixels_to_view, view_to_pixels

    u, v, d = torch.tensor([0.0, 7.5]), torch.tensor([3.0, 1.25]), torch.tensor([2.0, 0.5])
    p = pixels_to_view(u, v, d, 50.0, 40.0, 8.0, 6.0)
    assert torch.allclose(p[0], torch.tensor([(0 - 8) / 50 * 2, -(3 - 6) / 40 * 2, -2.0]))
    uu, vv = view_to_pixels(p, -p[:, 2], 50.0, 40.0, 8.0, 6.0)
    assert torch.allclose(uu, u) and torch.allclose(vv, v)


def test_a_footprint_clamped_onto_the_pixel_is_not_an_occluder():
    """A corner pixel's sample beyond the image, read with the clamped border, is the pixel's own texel: its
    position comes back through the inverse depth, 1/(1/d), a few float32 ulp off the pixel's. That offset is
    rounding, not an occluder (the offset's direction would be noise): the sample is invalid at every depth."""
    from torch_ao.walk.sample import fetch_sample

    valid = 0
    for distance in torch.linspace(1.0, 20.0, 40).tolist():  # (depths whose 1/(1/d) rounds off d among them)
        frame = Frame(plane_gbuffer(8, 10, tilt_degrees=35.0, distance=distance))
        q = frame.queries
        rows = (((q.u == 0) | (q.u == 9)) & ((q.v == 0) | (q.v == 7))).nonzero()[:, 0]
        corners = q.map_rows(lambda x: x[rows])
        away = torch.stack((torch.where(corners.u == 0, -3.3, 3.3), torch.where(corners.v == 0, -2.7, 2.7)), -1)
        sample = fetch_sample(frame, corners, None, 1, 0, away, fetch="bilinear", border="clamp")
        valid += int(sample.valid.sum())
    assert valid == 0
