"""BitmaskAO / SSILVB: analytic cases, thin occluders, gradients, robustness, only-what-is-asked."""
import math

import pytest
import torch

from torch_ao.camera import PinholeCamera
from torch_ao.examples import floor_wall_gbuffer, plane_gbuffer, planes_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.walk import Sample
from torch_ao.methods.bitmask import SSILVB, BitmaskAO, bitmask_ao, ssilvb

D = torch.float64


@pytest.mark.parametrize("weighting", ["uniform", "cosine"])
@pytest.mark.parametrize("rounding", ["ceil", "round", "floor"])
@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_flat_plane_is_unoccluded(weighting, rounding, mode):
    for tilt in (0.0, 60.0):
        gb = plane_gbuffer(16, 20, tilt_degrees=tilt)
        out = BitmaskAO(weighting=weighting, rounding=rounding, mode=mode, tau=0.05, slices=3, steps=4)(gb)
        assert torch.allclose(out.visibility, torch.ones_like(out.visibility), atol=1e-4), out.visibility.min()


def test_hdrp_variant_on_a_plane_with_round():
    # HDRP's fast_acos (error ~1e-2 rad) lifts in-plane samples above the horizon by a fraction of a
    # sector; with ceil that occludes one sector (a property of the seed), with round/floor nothing.
    gb = plane_gbuffer(24, 32, tilt_degrees=60.0)
    out = BitmaskAO(variant="hdrp", rounding="round", slices=3, steps=4)(gb)
    assert torch.equal(out.visibility, torch.ones_like(out.visibility))


def _wall_case(size: int):
    """A floor at distance ``d`` from an infinite wall: the cosine-weighted closed form within ``R`` and the
    floor pixels near the wall whose radius-R neighbourhood is on screen."""
    gb, dist = floor_wall_gbuffer(size, size, wall_distance=1.0, camera_height=3.0, pitch_degrees=-50.0,
                                  fov_y_degrees=70)
    R = 1.5
    d = dist[0, 0]
    k = (d / R).clamp(max=1)
    ref = 1 - (torch.acos(k) - k * torch.sqrt(1 - k * k)) / math.pi
    H, W = d.shape
    rows = torch.arange(H)[:, None].expand(H, W)
    cols = torch.arange(W)[None].expand(H, W)
    sel = torch.isfinite(d) & (d > 0.05) & (d < 1.2) & (rows > H * 30 // 96) & (rows < H * 80 // 96) & (cols > W * 10 // 96)
    return gb, R, ref, sel


@pytest.mark.parametrize("size,slices,steps", [(48, 6, 10), pytest.param(96, 8, 16, marks=pytest.mark.slow)])
def test_wall_cosine_weighting_converges_to_the_closed_form(size, slices, steps):
    gb, R, ref, sel = _wall_case(size)
    errors = {}
    for weighting in ("cosine", "uniform"):
        out = BitmaskAO(weighting=weighting, slices=slices, steps=steps, radius=R, thickness=1e3, jitter=False)(gb)
        errors[weighting] = float((out.visibility[0, 0] - ref)[sel].abs().mean())
    print(f"\nwall at distance d, R={R}: mean |visibility - closed form| cosine={errors['cosine']:.4f} "
          f"uniform={errors['uniform']:.4f} over {int(sel.sum())} pixels")
    assert errors["cosine"] < 0.025
    assert errors["cosine"] < errors["uniform"]


def test_clipping_and_the_sphere_extent_converge_to_the_wall_closed_form():
    """The same wall (thickness 1e3). Counting occluders whole beyond R over-occludes at many steps
    (bias < 0); clipping each segment to R alone under-occludes (the walk does not reach the wall points
    within R nearer the camera than the pixel); the sphere's screen extent removes most of that."""
    gb, R, ref, sel = _wall_case(48)
    bias = {}
    for name, kw in {"sectors": dict(), "clip": dict(union="exact", clip_to_radius=True),
                     "sphere": dict(union="exact", clip_to_radius=True, sample_extent="sphere")}.items():
        with torch.no_grad():
            vis = BitmaskAO(weighting="cosine", slices=16, steps=16, radius=R, thickness=1e3, **kw)(gb).visibility[0, 0]
        bias[name] = float((vis - ref)[sel].mean())
    print("\nwall: mean signed error at 16 x 16 by option", bias)
    assert bias["sectors"] < -0.005
    assert bias["clip"] > 0.008 and 0 < bias["sphere"] < 0.6 * bias["clip"]


def _slat_scene(gap: float):
    """A wall at z=-6 facing the camera and a vertical slat (x in [-0.1, 0.1]) at z = -6 + gap."""
    cam = PinholeCamera.from_fov(50.0, 24, 40)
    wall = ((0.0, 0.0, 1.0), -6.0, None)
    slat = ((0.0, 0.0, 1.0), -6.0 + gap, [((1.0, 0.0, 0.0), 0.1), ((-1.0, 0.0, 0.0), 0.1)])
    return planes_gbuffer([wall, slat], cam, dtype=D)


def test_thin_slat_lets_light_pass_behind_when_thinner_than_the_gap():
    gap = 1.0
    gb = _slat_scene(gap)
    on_wall = gb.object_id[0, 0] == 1
    # wall pixels within a small distance of the slat, on both sides of it
    H, W = on_wall.shape
    cols = torch.arange(W)[None].expand(H, W)
    slat_cols = (gb.object_id[0, 0] == 2).any(0).nonzero()[:, 0]
    near = on_wall & ((cols - slat_cols.min()).abs() <= 3) | on_wall & ((cols - slat_cols.max()).abs() <= 3)
    vis = {}
    for t in (0.25 * gap, 0.5 * gap, 0.9 * gap, 1.5 * gap, 4 * gap):
        out = BitmaskAO(thickness=t, slices=4, steps=8, radius=2.0, jitter=False)(gb)
        vis[t] = float(out.visibility[0, 0][near].mean())
    print("\nslat in front of a wall (gap 1): mean visibility next to the slat by thickness", vis)
    # Thinner than the gap: the directions passing behind the slat stay open, and more so for thinner slats.
    assert vis[0.25] > vis[0.5] > vis[0.9] > vis[1.5]
    assert vis[0.5] - vis[1.5] > 0.03
    # Thicker than the gap: the back face reaches the wall, every direction behind the slat is occluded;
    # thickening further changes nothing (nothing lies behind the wall).
    assert abs(vis[1.5] - vis[4.0]) < 1e-6


def _small_gbuffer(light=True):
    gb, _ = floor_wall_gbuffer(12, 14, wall_distance=0.6, camera_height=1.5, pitch_degrees=-40.0, dtype=D,
                               light_direction=(0.3, 0.8, 0.5) if light else None)
    return gb


def _dir_check(f, x, eps=1e-6, seed=0):
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(x.shape, generator=g, dtype=x.dtype)
    x0 = x.detach().clone().requires_grad_(True)
    y = f(x0)
    (grad,) = torch.autograd.grad(y, x0)
    analytic = float((grad * v).sum())
    with torch.no_grad():
        numeric = float((f(x0 + eps * v) - f(x0 - eps * v)) / (2 * eps))
    return analytic, numeric


def _check(analytic, numeric, name):
    assert math.isfinite(analytic)
    assert abs(analytic - numeric) <= 1e-4 * max(1.0, abs(numeric)), f"{name}: autograd {analytic} vs FD {numeric}"
    assert abs(numeric) > 1e-8, f"{name}: the check is vacuous (zero derivative)"


OPTS = dict(mode="soft", tau=0.5, slices=2, steps=3, radius=0.8, jitter=False, fetch="bilinear", indirect=True,
            weighting="cosine")


def _loss(out):
    return out.visibility.sum() + 0.3 * out.indirect.sum()


def test_gradients_match_finite_differences_float64():
    gb = _small_gbuffer()
    valid = gb.valid

    def with_(depth=gb.depth, normals=gb.normals, light=gb.light):
        return GBuffer(depth, gb.camera, normals=normals, light=light, object_id=gb.object_id)

    cases = {
        "thickness": lambda t: _loss(ssilvb(gb, thickness=t, **{k: v for k, v in OPTS.items() if k != "indirect"})),
        "radius": lambda r: _loss(ssilvb(gb, radius=r, **{k: v for k, v in OPTS.items() if k not in ("indirect", "radius")})),
        "depth": lambda d: _loss(SSILVB(**OPTS)(with_(depth=torch.where(valid, d, gb.depth)))),
        "normals": lambda n: _loss(SSILVB(**OPTS)(with_(normals=n))),
        "light": lambda l: _loss(SSILVB(**OPTS)(with_(light=l))),
    }
    inputs = {"thickness": torch.tensor(0.3, dtype=D), "radius": torch.tensor(0.8, dtype=D), "depth": gb.depth,
              "normals": gb.normals, "light": gb.light}
    for name, f in cases.items():
        a, n = _dir_check(f, inputs[name])
        _check(a, n, name)


def test_thickness_forms_are_fittable_and_read_at_the_sample():
    gb = _small_gbuffer(light=False)
    B, _, H, W = gb.depth.shape
    scalar = BitmaskAO(mode="soft", tau=0.5, thickness=0.3, slices=2, steps=3, jitter=False)
    tmap = BitmaskAO(mode="soft", tau=0.5, thickness=torch.full((1, 1, H, W), 0.3), slices=2, steps=3, jitter=False)
    table = BitmaskAO(mode="soft", tau=0.5, thickness=torch.tensor([0.3, 0.3, 0.3]), slices=2, steps=3, jitter=False)
    grow = BitmaskAO(mode="soft", tau=0.5, thickness=0.3, thickness_growth=0.0, slices=2, steps=3, jitter=False)
    outs = [m(gb).visibility for m in (scalar, tmap, table, grow)]
    for o in outs[1:]:
        assert torch.allclose(o, outs[0], atol=1e-12)
    for m, o in zip((scalar, tmap, table, grow), outs):
        o.sum().backward()
        assert m.thickness.grad is not None and bool(torch.isfinite(m.thickness.grad).all())
        assert float(m.thickness.grad.abs().sum()) > 0
    assert grow.thickness_growth.grad is not None and float(grow.thickness_growth.grad.abs()) > 0
    # The map is the *occluder's* thickness: only entries at sampled pixels get gradient, and changing
    # the thickness of a pixel that is never sampled changes nothing.
    assert tmap.thickness.grad.shape == (1, 1, H, W)
    # per-object: the wall (id 2) and floor (id 1) both occlude something here
    assert float(table.thickness.grad[1:].abs().min()) > 0


@pytest.mark.parametrize("variant", ["default", "hdrp", "ssilvb_glsl"])
def test_no_nan_in_stiff_and_extreme_cases(variant):
    gb, _ = floor_wall_gbuffer(16, 20, wall_distance=0.5, camera_height=1.0, pitch_degrees=-5.0,
                               light_direction=(0.3, 0.8, 0.5))  # grazing floor, background sky
    assert not bool(gb.valid.all())
    for tau, thickness, mode in [(1e-1, 0.0, "soft"), (1e-6, 0.0, "soft"), (1e-1, 1e6, "soft"), (1e-6, 1e6, "soft"),
                                 (1e-6, 0.5, "straight_through")]:
        if True:
            if True:
                depth = gb.depth.clone().requires_grad_(True)
                normals = gb.normals.clone().requires_grad_(True)
                light = gb.light.clone().requires_grad_(True)
                g = GBuffer(depth, gb.camera, normals=normals, light=light)
                m = SSILVB(variant=variant, mode=mode, tau=tau, thickness=thickness, slices=2, steps=3)
                out = m(g)
                assert torch.isfinite(out.visibility).all() and torch.isfinite(out.indirect).all()
                (out.visibility.sum() + out.indirect.sum()).backward()
                # (the GLSL walk fetches whole texels, so its radius has no gradient: a buffer there)
                assert ("radius" in dict(m.named_parameters())) == (variant != "ssilvb_glsl")
                for t in (depth.grad, normals.grad, light.grad, *(p.grad for p in m.parameters())):
                    assert bool(torch.isfinite(t).all())
                bg = ~g.valid
                assert torch.equal(out.visibility[bg], torch.ones_like(out.visibility[bg]))
                assert torch.equal(depth.grad[bg], torch.zeros_like(depth.grad[bg]))


def test_straight_through_forward_equals_hard():
    gb = _small_gbuffer()
    hard = SSILVB(mode="hard", slices=3, steps=4)(gb)
    st = SSILVB(mode="straight_through", tau=0.3, slices=3, steps=4)(gb)
    assert torch.equal(hard.visibility, st.visibility)
    assert torch.allclose(hard.indirect, st.indirect, atol=1e-6)


def test_soft_converges_to_hard_on_a_frame():
    gb = _small_gbuffer()
    hard = BitmaskAO(mode="hard", slices=3, steps=4, weighting="cosine")(gb).visibility
    diffs = []
    for tau in (1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6):
        soft = BitmaskAO(mode="soft", tau=tau, slices=3, steps=4, weighting="cosine")(gb).visibility
        diffs.append(float((soft - hard).abs().mean().detach()))
    print("\nframe: mean |soft - hard| visibility for tau 1e-1..1e-6:", ["%.2e" % d for d in diffs])
    assert diffs[-1] < 1e-5 and diffs[-1] <= diffs[0]


def test_ao_only_never_gathers_light_or_normals(monkeypatch):
    gathered = []
    original = Sample.gather

    def spy(self, name):
        gathered.append(name)
        return original(self, name)

    monkeypatch.setattr(Sample, "gather", spy)
    gb = _small_gbuffer()
    out = BitmaskAO(slices=2, steps=3)(gb)
    assert out.indirect is None and out.bent_normal is None and out.ambient is None
    assert gathered == []
    out = SSILVB(slices=2, steps=3)(gb)
    assert "light" in gathered and "normals" in gathered and out.indirect.shape == (1, 3, 12, 14)


def test_bent_normals_and_ambient():
    gb = plane_gbuffer(16, 20, tilt_degrees=30.0)
    out = BitmaskAO(slices=8, steps=3, bent_normals=True, ambient=(0.2, 0.4, 0.6), weighting="cosine")(gb)
    n = gb.view_normals()
    cos = (out.bent_normal * n).sum(1)
    assert float(cos.min()) > 0.99  # unoccluded: bent normal = normal
    assert torch.allclose(out.ambient, torch.tensor([0.2, 0.4, 0.6]).view(1, 3, 1, 1).expand_as(out.ambient), atol=1e-5)
    sky = lambda d: d[:, 1:2].clamp_min(0).expand(-1, 3)  # noqa: E731  (brighter toward +Y)
    out = BitmaskAO(slices=4, steps=3, ambient=sky, ambient_directions=4)(gb)
    assert out.ambient.shape == (1, 3, 16, 20) and bool(torch.isfinite(out.ambient).all())


def test_glsl_variant_quirks():
    gb = _small_gbuffer()
    out = SSILVB(variant="ssilvb_glsl", slices=2, steps=2, radius=1.0, thickness=0.0)(gb)
    # nothing occludes with zero thickness: (sliceCount + 1) slices / sliceCount = 1.5
    assert torch.allclose(out.visibility[gb.valid], torch.full_like(out.visibility[gb.valid], 1.5))
    with pytest.raises(ValueError, match="sliceCount"):
        BitmaskAO(variant="ssilvb_glsl", slices=1)
    with pytest.raises(ValueError, match="weighting"):
        BitmaskAO(variant="ssilvb_glsl", weighting="cosine")


def test_bad_arguments_are_named():
    for kwargs, word in [({"variant": "x"}, "variant"), ({"mode": "x"}, "mode"), ({"rounding": "x"}, "rounding"),
                         ({"weighting": "x"}, "weighting"), ({"tau": 0.0}, "tau"), ({"thickness": -1.0}, "thickness"),
                         ({"thickness": torch.zeros(2, 2)}, "thickness"), ({"ambient_directions": 5}, "ambient_directions")]:
        with pytest.raises(ValueError, match=word):
            BitmaskAO(**kwargs)
    gb = plane_gbuffer(8, 8)
    with pytest.raises(ValueError, match="light"):
        SSILVB()(GBuffer(gb.depth, gb.camera))
    with pytest.raises(ValueError, match="object_id"):
        BitmaskAO(thickness=torch.tensor([0.1, 0.2]))(GBuffer(gb.depth, gb.camera))


def test_functional_twin_keeps_the_graph():
    gb = _small_gbuffer()
    t = torch.tensor(0.3, dtype=D, requires_grad=True)
    out = bitmask_ao(gb, thickness=t, mode="soft", tau=0.5, slices=2, steps=3)
    out.visibility.sum().backward()
    assert t.grad is not None and float(t.grad.abs()) > 0
