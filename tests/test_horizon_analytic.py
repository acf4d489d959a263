"""Horizon-family methods against closed forms: planes, a floor next to a wall, a right-angle crease.

Closed form used throughout (DESIGN.md): a point on a floor at distance ``d`` from an infinite wall, with
maximum distance ``R`` and ``k = min(d/R, 1)``, has cosine-weighted visibility
``1 - (acos k - k sqrt(1 - k^2)) / pi`` (project the hemisphere onto the floor's unit disc; the cosine
weighting is uniform over the disc; the wall blocks the directions that reach it within ``R``, the
segment ``x >= k`` of the disc).

The right-angle crease is the same configuration: a point on one half-plane at distance ``d`` from the
crease line sees the other half-plane as a wall rising on its normal side. On the crease line itself
(``d = 0``) the other plane passes through the point and contains the normal, so it cuts the hemisphere
into two mirror halves of equal cosine weight: visibility exactly 1/2, for every ``R``.

Screen-space methods see only what is on screen, so the checks use pixels whose *relevant* wall part,
the half-disc of radius ``sqrt(R^2 - d^2)`` on the wall around the foot point, projects inside the image.
"""
import math

import pytest
import torch

from torch_ao.examples import _rotation_x, crease_gbuffer, floor_wall_gbuffer, plane_gbuffer
from torch_ao.methods.gtao import GTAO, arc_integral, bent_vector, multibounce
from torch_ao.methods.hbao import HBAO
from torch_ao.methods.pssao import PSSAO
from torch_ao.methods.ssao import SSAO
from torch_ao.methods.ue4_ssao import UE4SSAO


@pytest.fixture(autouse=True)
def _no_grad():
    with torch.no_grad():  # forward-only checks: no autograd graph (a dense walk's graph is gigabytes)
        yield


def wall_visibility(d: torch.Tensor, R: float) -> torch.Tensor:
    k = (d / R).clamp(max=1.0)
    return 1 - (torch.acos(k) - k * torch.sqrt(1 - k * k)) / math.pi


def half_disc_on_screen(camera, foot, e_along, e_out, rho, margin=1.0):
    """True where every point ``foot + r rho (cos a e_along + sin a e_out)`` (r in [0,1], a in [0,pi])
    projects inside the image (``margin`` pixels from the border) in front of the camera."""
    a = torch.linspace(0, math.pi, 25, dtype=torch.float64)
    r = torch.linspace(0, 1, 6, dtype=torch.float64)
    ca = (r[:, None] * torch.cos(a)[None]).reshape(-1)
    sa = (r[:, None] * torch.sin(a)[None]).reshape(-1)
    pts = foot[..., None, :] + rho[..., None, None] * (ca[:, None] * e_along[..., None, :] + sa[:, None] * e_out[..., None, :])
    cam = camera.to(dtype=torch.float64)
    u, v, depth = cam.view_to_pixel(pts)
    H, W = cam.height, cam.width
    return ((u >= margin) & (u <= W - 1 - margin) & (v >= margin) & (v <= H - 1 - margin) & (depth > 0)).all(-1)


def floor_wall_case(H, W, R, wall_distance=1.0, camera_height=3.0, pitch=-60.0):
    gb, dist = floor_wall_gbuffer(H, W, wall_distance=wall_distance, camera_height=camera_height,
                                  pitch_degrees=pitch, dtype=torch.float64)
    rot = _rotation_x(math.radians(pitch))  # view = (world - eye) @ rot
    eye = torch.tensor([0.0, camera_height, 0.0], dtype=torch.float64)
    pos = gb.positions()[0].permute(1, 2, 0)
    world = pos @ rot.T + eye
    d = dist[0, 0]
    on = torch.isfinite(d) & (d < R)
    foot = torch.stack((torch.full_like(d, wall_distance), torch.zeros_like(d), world[..., 2]), -1)
    foot_view = (foot - eye) @ rot
    e_along = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) @ rot
    e_out = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64) @ rot
    rho = torch.sqrt((R * R - torch.nan_to_num(d, nan=R) ** 2).clamp_min(0))
    mask = on & half_disc_on_screen(gb.camera, foot_view, e_along.expand_as(foot_view), e_out.expand_as(foot_view), rho)
    return gb, wall_visibility(torch.nan_to_num(d, nan=10 * R), R), mask, d


def crease_case(H, W, R):
    gb = crease_gbuffer(H, W, dtype=torch.float64)
    pos = gb.positions()[0].permute(1, 2, 0)
    x, y, z = pos.unbind(-1)
    d = torch.sqrt(x * x + (z + 3) ** 2)
    foot = torch.stack((torch.zeros_like(x), y, torch.full_like(x, -3.0)), -1)
    s = 1 / math.sqrt(2)
    left = (x < 0)[..., None]
    # On the left plane the wall is the right one, which leaves the crease along (1, 0, 1)/sqrt(2).
    e_out = torch.where(left, pos.new_tensor([s, 0.0, s]), pos.new_tensor([-s, 0.0, s])).expand_as(pos)
    e_along = pos.new_tensor([0.0, 1.0, 0.0]).expand_as(pos)
    rho = torch.sqrt((R * R - d * d).clamp_min(0))
    mask = gb.valid[0, 0] & (d < R) & half_disc_on_screen(gb.camera, foot, e_along, e_out, rho)
    return gb, wall_visibility(d, R), mask, d


# ---------------------------------------------------------------------------------------------
# Infinite planes: visibility 1 for every method
# ---------------------------------------------------------------------------------------------
# (constructor, options, tolerance). All with bilinear fetch and border drop: a bilinear depth lies on or
# behind the plane (depth = 1/affine is convex in screen space), so no sample rises above it.
PLANE_CASES = [
    ("gtao-exact", GTAO, dict(variant="exact"), 1e-6),
    # HDRP/UE4 use GTAOFastAcos (error ~1e-2 rad), so a horizon on the plane can poke past the clamp.
    ("gtao-hdrp", GTAO, dict(variant="hdrp", normalize="exact", fetch="bilinear", border="drop"), 1e-4),
    ("gtao-ue4", GTAO, dict(variant="ue4", normalize="exact", fetch="bilinear", border="drop"), 3e-4),
    ("hbao", HBAO, dict(), 0.0),  # default angle bias 10 degrees: exactly 1
    ("hbao-view", HBAO, dict(elevation="view", accumulate="max"), 0.0),
    ("hbao-nobias", HBAO, dict(angle_bias=0.0), 1e-5),
    ("ue4_ssao", UE4SSAO, dict(fetch="bilinear", border="drop"), 0.0),  # the flat-surface test
    ("pssao", PSSAO, dict(), 1e-6),
    ("pssao-directions", PSSAO, dict(normalize="directions"), 1e-6),
    ("ssao", SSAO, dict(), 0.0),  # kernel points above the plane, bias 0.025
]


@pytest.mark.parametrize("name,cls,options,tol", PLANE_CASES, ids=[c[0] for c in PLANE_CASES])
@pytest.mark.parametrize("tilt", [0.0, 45.0, 75.0])
def test_infinite_plane_is_unoccluded(name, cls, options, tol, tilt):
    gb = plane_gbuffer(24, 32, tilt_degrees=tilt)
    vis = cls(**options)(gb).visibility
    assert vis.shape == (1, 1, 24, 32)
    assert bool(torch.isfinite(vis).all())
    assert float((1 - vis.detach()).abs().max()) <= tol


def test_gtao_exact_plane_is_one_with_any_slice_count_and_limit_without_normalisation():
    gb = plane_gbuffer(16, 20, tilt_degrees=60.0)
    for slices in (1, 2, 3):
        vis = GTAO(slices=slices, steps=4)(gb).visibility
        assert float((1 - vis).abs().max()) < 1e-6
    # normalize="none" is the plain slice mean: 1 only in the limit (view-uniform slices), not per slice.
    few = GTAO(slices=2, steps=2, normalize="none", jitter=False)(gb).visibility
    many = GTAO(slices=64, steps=2, normalize="none", jitter=False)(gb).visibility
    assert float((1 - many).abs().max()) < 1e-3 < float((1 - few).abs().max())


def test_gtao_ue4_normalisation_is_two_over_pi_on_a_facing_plane():
    gb = plane_gbuffer(9, 9, tilt_degrees=0.0, fov_y_degrees=1.0)  # nearly parallel rays: n_p = V
    out = GTAO(variant="ue4", fetch="bilinear", border="drop", slices=3, steps=2)(gb).visibility
    assert out[0, 0, 4, 4].item() == pytest.approx(2 / math.pi, abs=1e-5)
    none = GTAO(variant="hdrp", normalize="none", fetch="bilinear", border="drop", slices=3, steps=2)(gb).visibility
    assert none[0, 0, 4, 4].item() == pytest.approx(1.0, abs=1e-5)


# ---------------------------------------------------------------------------------------------
# Floor next to a wall, and the crease: GTAO (exact) converges to the closed form
# ---------------------------------------------------------------------------------------------
def _errors(vis, ref, mask):
    e = (vis[0, 0] - ref)[mask]
    return e.abs().mean().item(), e.mean().item()


def test_gtao_exact_converges_on_floor_next_to_wall():
    R = 1.0
    gb, ref, mask, d = floor_wall_case(48, 48, R)
    assert int(mask.sum()) > 100
    coarse = GTAO(slices=4, steps=8, radius=R, jitter=False, search_scale=1.5)(gb).visibility
    fine = GTAO(slices=24, steps=32, radius=R, jitter=False, search_scale=1.5)(gb).visibility
    mae_c, _ = _errors(coarse, ref, mask)
    mae_f, bias_f = _errors(fine, ref, mask)
    assert mae_f < 0.6 * mae_c
    assert mae_f < 0.006 and abs(bias_f) < 0.006
    # Pixels farther than R from the wall see no occluder within R: exactly 1.
    far = torch.isfinite(d) & (d > R)  # floor pixels only (nan elsewhere)
    assert float((1 - fine[0, 0][far]).abs().max()) < 1e-4


@pytest.mark.slow
def test_gtao_exact_converges_on_floor_next_to_wall_dense():
    R = 1.0
    gb, ref, mask, _ = floor_wall_case(64, 64, R)
    vis = GTAO(slices=64, steps=128, radius=R, jitter=False, search_scale=1.5)(gb).visibility
    mae, bias = _errors(vis, ref, mask)
    assert mae < 0.002 and abs(bias) < 0.002


def test_gtao_exact_on_right_angle_crease():
    R = 0.6
    gb, ref, mask, d = crease_case(40, 41, R)  # odd width: column 20 lies exactly on the crease line
    assert int(mask.sum()) > 50
    vis = GTAO(slices=24, steps=32, radius=R, jitter=False, search_scale=1.5)(gb).visibility[0, 0].detach()
    e = (vis - ref)[mask]
    assert e.abs().mean().item() < 0.006
    on_line = mask & (d < 1e-9)
    assert int(on_line.sum()) > 5
    assert float((vis[on_line] - 0.5).abs().max()) < 0.01  # the crease value 1/2
    near = mask & (d > 1e-9) & (d < 0.2 * R)
    assert float((vis[near] - ref[near]).abs().max()) < 0.01


@pytest.mark.parametrize("cls,options", [(GTAO, dict(variant="hdrp")), (GTAO, dict(variant="ue4")),
                                         (HBAO, {}), (UE4SSAO, {}), (PSSAO, {}), (SSAO, {})])
def test_every_method_darkens_the_crease_and_stays_in_range(cls, options):
    gb = crease_gbuffer(24, 24)
    vis = cls(radius=0.8, **options)(gb).visibility[0, 0] if cls is not PSSAO else cls(**options)(gb).visibility[0, 0]
    assert bool(((vis >= 0) & (vis <= 1)).all())
    centre, edge = vis[6:18, 11:13].mean(), vis[6:18, [1, 22]].mean()
    assert centre < edge - 1e-3


# ---------------------------------------------------------------------------------------------
# Closed-form pieces
# ---------------------------------------------------------------------------------------------
def _quad(f, a, b, n=4001):
    t = torch.linspace(0, 1, n, dtype=torch.float64)
    x = a[:, None] + (b - a)[:, None] * t[None]
    w = torch.full((n,), 1.0, dtype=torch.float64)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0  # Simpson
    return (f(x) * w).sum(-1) * (b - a) / (3 * (n - 1))


def test_arc_integral_and_bent_vector_match_quadrature():
    g = torch.Generator().manual_seed(3)
    n = (torch.rand(64, generator=g, dtype=torch.float64) - 0.5) * 2.4
    h1 = -torch.rand(64, generator=g, dtype=torch.float64) * (math.pi / 2 - n)
    h2 = torch.rand(64, generator=g, dtype=torch.float64) * (math.pi / 2 + n)
    w = lambda t: torch.cos(t - n[:, None]) * torch.sin(t).abs()
    ref = _quad(w, h1, h2)
    assert torch.allclose(arc_integral(h1, h2, n, torch.cos(n), torch.sin(n)), ref, atol=1e-9)
    bv, bt = bent_vector(h1, h2, n)
    assert torch.allclose(bv, _quad(lambda t: torch.cos(t) * w(t), h1, h2), atol=1e-9)
    assert torch.allclose(bt, _quad(lambda t: torch.sin(t) * w(t), h1, h2), atol=1e-9)


def test_gtao_power_multibounce_and_bent_normals():
    gb, _, _, _ = floor_wall_case(24, 24, 1.0)
    base = GTAO(slices=4, steps=6, jitter=False)(gb).visibility
    powered = GTAO(slices=4, steps=6, jitter=False, final_power=2.0)(gb).visibility
    assert torch.allclose(powered, base.clamp_min(1e-12) ** 2, atol=1e-9)
    bounced = GTAO(slices=4, steps=6, jitter=False, multibounce=True, albedo=0.7)(gb).visibility
    assert torch.allclose(bounced, multibounce(base, torch.tensor(0.7, dtype=base.dtype)).clamp(0, 1), atol=1e-9)
    assert bool((bounced >= base - 1e-12).all())
    out = GTAO(slices=16, steps=6, jitter=False, bent_normals=True)(gb)
    assert out.bent_normal.shape == (1, 3, 24, 24)
    assert torch.allclose(out.bent_normal.norm(dim=1), torch.ones(1, 24, 24, dtype=torch.float64), atol=1e-9)
    assert GTAO(slices=2, steps=2)(gb).bent_normal is None  # opt-in


def test_gtao_bent_normal_is_the_normal_on_a_plane_and_leans_away_from_a_wall():
    gb = plane_gbuffer(12, 12, tilt_degrees=40.0, dtype=torch.float64)
    out = GTAO(slices=32, steps=4, jitter=False, bent_normals=True)(gb)
    cos = (out.bent_normal * gb.view_normals()).sum(1)
    assert float(cos.min()) > math.cos(math.radians(1.0))
    gb, _, mask, _ = floor_wall_case(32, 32, 1.0)
    out = GTAO(slices=16, steps=16, jitter=False, bent_normals=True, search_scale=1.5)(gb)
    rot = _rotation_x(math.radians(-60.0))
    world = out.bent_normal[0].permute(1, 2, 0) @ rot.T  # directions: view -> world
    assert float(world[..., 0][mask].max()) < 0  # leans away from the wall at x = +1


# ---------------------------------------------------------------------------------------------
# Method-specific formulas
# ---------------------------------------------------------------------------------------------
def _gist_pssao(gb, slices, steps, normalize):
    """The gist's loops, written out per pixel (with the G-buffer's positions and normals)."""
    P = gb.positions()[0].permute(1, 2, 0)
    N = gb.view_normals()[0].permute(1, 2, 0)
    H, W = gb.depth.shape[-2:]
    out = torch.ones(H, W, dtype=torch.float64)
    for y in range(H):
        for x in range(W):
            total, include = 0.0, 0.0
            for i in range(slices):
                ang = i / slices * 2 * math.pi
                best = -100000.0
                for k in range(steps):
                    dx, dy = math.floor(math.cos(ang) * k), math.floor(math.sin(ang) * k)
                    u, v = x + dx, y - dy  # GL y up -> rows down
                    if not (0 <= u < W and 0 <= v < H):
                        continue
                    include += 1
                    a = float(N[y, x] @ (P[v, u] - P[y, x]))
                    occ = 0.0
                    if a > 0:
                        a /= 1.0 + float((P[v, u] - P[y, x]).norm())
                        occ = 1 - 1 / (1 + a)
                    best = max(best, occ)
                total += best
            out[y, x] = 1 - total / (include if normalize == "samples" else slices)
    return out


@pytest.mark.parametrize("normalize", ["samples", "directions"])
def test_pssao_matches_the_gist_loops(normalize):
    gb = crease_gbuffer(9, 11, dtype=torch.float64)
    vis = PSSAO(slices=6, steps=5, normalize=normalize)(gb).visibility[0, 0]
    assert torch.allclose(vis, _gist_pssao(gb, 6, 5, normalize), atol=1e-12)


def test_hbao_incremental_equals_max_with_one_step_and_quadratic_falloff_darkens():
    gb = crease_gbuffer(20, 20)
    one_inc = HBAO(steps=1, slices=6, jitter=False)(gb).visibility
    one_max = HBAO(steps=1, slices=6, jitter=False, accumulate="max")(gb).visibility
    assert torch.allclose(one_inc, one_max, atol=1e-6)
    lin = HBAO(jitter=False, radius=1.0)(gb).visibility
    quad = HBAO(jitter=False, radius=1.0, falloff="quadratic")(gb).visibility
    assert bool((quad <= lin + 1e-6).all()) and float((lin - quad).max()) > 1e-3


def test_ue4_ssao_options_and_user_adjustment():
    gb = crease_gbuffer(20, 20)
    raw = UE4SSAO(jitter=False)(gb).visibility
    adjusted = UE4SSAO(jitter=False, final_power=2.0, intensity=0.5)(gb).visibility
    assert torch.allclose(adjusted, 1 - (1 - raw.clamp_min(1e-12) ** 2) * 0.5, atol=1e-6)
    accurate = UE4SSAO(jitter=False, accurate_angle=True)(gb).visibility
    assert bool(((accurate >= 0) & (accurate <= 1)).all()) and not torch.allclose(accurate, raw)
    six = UE4SSAO(sample_set="ue4_6")
    assert six.slices == 6


def test_ssao_tiny_radius_sees_nothing():
    gb = crease_gbuffer(16, 16)
    vis = SSAO(radius=1e-3)(gb).visibility
    assert float((1 - vis).abs().max()) == 0.0
