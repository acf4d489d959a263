"""The screen-space ground truth against closed forms, and the split of the error.

Closed forms (see tests/test_horizon_analytic.py and docs/reference.md): a point on a floor at distance
``d`` from an infinite wall, ``k = min(d/R, 1)``: cosine-weighted visibility ``1 - (acos k - k sqrt(1-k^2))/pi``,
uniform-weighted ``(1 + k)/2``. Any thickness > 0 gives the same limit (a ray that reaches the wall's front
within ``R`` is inside the slab just behind it); an infinite plane gives 1. Pixels are used only where the
wall's relevant part projects on screen (rays leaving the screen are unoccluded by definition).

A thin slab of known thickness: a floor and a plank (the view-space plane ``z = -D`` for ``x <= 0``, standing on
the floor). With thickness ``T`` the occluder behind the plank is the convex region ``x <= 0``,
``D <= -z <= D + T``, above the floor (as seen from the camera): four half-spaces, so whether a ray meets it
within ``R`` is an exact interval clip, integrated over a fine grid of directions (cosine weighting is uniform
over the unit disc under the hemisphere). For floor pixels beside the plank the visibility depends strongly on
``T`` (rays that pass behind a thin plank are free).
"""
import math

import pytest
import torch
from test_horizon_analytic import floor_wall_case

from torch_ao.camera import PinholeCamera
from torch_ao.examples import _rotation_x, plane_gbuffer, planes_gbuffer
from torch_ao.reference.sampling import frame
from torch_ao.screen_truth import ScreenTruth, screen_space_truth, split_error, thickness_map


def _within_error(estimate, stderr, exact, mask, rays, z=4.0, share=0.97):
    """Most pixels within ``z`` standard errors, and the mean error within ``z`` of its own error. Where fewer
    than about one ray in ``rays`` is blocked, no group sees a blocked ray and the estimated error is 0: those
    pixels get a floor of 2 rays' weight."""
    e = (estimate.double() - exact)[mask]
    se = stderr.double()[mask]
    per_pixel = (e.abs() <= z * se + 2 / rays).double().mean()
    mean_se = float(se.square().sum().sqrt() / se.numel())
    return float(per_pixel) >= share and abs(float(e.mean())) <= z * mean_se, float(per_pixel), float(e.mean()), mean_se


@pytest.mark.parametrize("tilt", [0.0, 45.0, 75.0])
def test_plane_is_unoccluded(tilt):
    gb = plane_gbuffer(24, 32, tilt_degrees=tilt)
    st = screen_space_truth(gb, 1.0, rays=64, uniform=True)
    assert st.visibility.shape == (1, 1, 24, 32)
    assert float(st.visibility.min()) == 1.0 and float(st.uniform.min()) == 1.0
    assert float(st.stderr.max()) == 0.0


@pytest.fixture(scope="module")
def wall():
    R = 1.0
    gb, vis, mask, d = floor_wall_case(48, 64, R)
    return gb.to(dtype=torch.float32), vis, mask, d, R


def test_floor_wall_closed_form_cosine_and_uniform(wall):
    gb, vis, mask, d, R = wall
    assert int(mask.sum()) > 200
    st = screen_space_truth(gb, R, rays=256, uniform=True)
    ok, share, mean, se = _within_error(st.visibility[0, 0], st.stderr[0, 0], vis, mask, 256)
    assert ok, (share, mean, se)
    k = (d / R).clamp(max=1.0)
    ok, share, mean, se = _within_error(st.uniform[0, 0], st.uniform_stderr[0, 0], (1 + k) / 2, mask, 256)
    assert ok, (share, mean, se)


def test_reproducible_whatever_the_chunking(wall):
    gb, vis, mask, d, R = wall
    where = mask[None, None]
    a = screen_space_truth(gb, 1.0, rays=32, seed=3, where=where)
    b = screen_space_truth(gb, 1.0, rays=32, seed=3, chunk_points=5000, where=where)
    c = screen_space_truth(gb, 1.0, rays=32, seed=4, where=where)
    assert torch.equal(a.visibility, b.visibility) and torch.equal(a.stderr, b.stderr)
    assert not torch.equal(a.visibility, c.visibility)


def test_thickness_forms_resolve_to_one_map(wall):
    gb, *_ = wall
    B, _, H, W = gb.depth.shape
    assert thickness_map(gb, 0.5) == 0.5 and thickness_map(gb) == math.inf
    table = torch.tensor([9.0, 0.25, 2.0])  # object 1 = floor, 2 = wall
    t = thickness_map(gb, table)
    assert torch.equal(t, table[gb.object_id].float())
    back = gb.depth + 0.75
    assert torch.allclose(thickness_map(gb, backface_depth=back)[gb.valid], torch.full((int(gb.valid.sum()),), 0.75), atol=1e-5)
    assert torch.equal(thickness_map(gb, lambda g: 0.1 * g.safe_depth), 0.1 * gb.safe_depth)
    # Every form gives the same truth as the map it resolves to.
    a = screen_space_truth(gb, 1.0, table, rays=16)
    b = screen_space_truth(gb, 1.0, t, rays=16)
    assert torch.equal(a.visibility, b.visibility)
    for bad, match in ((-1.0, "thickness"), (torch.ones(2, 1, H, W), "thickness"), ("x", "thickness")):
        with pytest.raises((ValueError, TypeError), match=match):
            thickness_map(gb, bad)
    with pytest.raises(ValueError, match="backface_depth"):
        thickness_map(gb, backface_depth=torch.ones(1, 1, 2, 2))


@pytest.mark.parametrize("kwargs,name", [(dict(radius=0.0), "radius"), (dict(rays=1), "rays"), (dict(rays=17), "spp"),
                                         (dict(fetch="cubic"), "fetch"), (dict(min_steps=0), "min_steps"),
                                         (dict(min_steps=8, max_steps=4), "max_steps"), (dict(uniform=1), "uniform")])
def test_bad_arguments_are_named(wall, kwargs, name):
    gb, *_ = wall
    with pytest.raises(ValueError, match=name):
        screen_space_truth(gb, **{"radius": 1.0, **kwargs})


def test_split_error_adds_up_per_view(wall):
    gb, vis, mask, d, R = wall
    ref = torch.where(torch.isfinite(d), torch.nan_to_num(vis.float(), nan=1.0), torch.ones_like(d))[None, None]
    truth = ref + 0.01
    method = ref + 0.03
    ref2, truth2, method2 = (torch.cat((x, x.flip(-1))) for x in (ref, truth, method))
    valid = torch.cat((gb.valid, gb.valid.flip(-1)))
    st = ScreenTruth(truth2, torch.full_like(truth2, 0.002), None, None, torch.zeros_like(truth2, dtype=torch.long), R, 8, 0)
    out = split_error(method2, st, ref2, valid)
    assert len(out) == 2
    for s in out:
        assert s.screen["mae"] == pytest.approx(0.01, abs=1e-6)
        assert s.estimator["mae"] == pytest.approx(0.02, abs=1e-6)
        assert s.total["mae"] == pytest.approx(0.03, abs=1e-6)
        assert s.estimator["bias"] == pytest.approx(0.02, abs=1e-6) and s.screen["bias"] == pytest.approx(0.01, abs=1e-6)
        assert s.total["psnr"] == pytest.approx(-20 * math.log10(0.03), abs=1e-3)
        assert s.truth_stderr == pytest.approx(0.002)
    with pytest.raises(ValueError, match="reference"):
        split_error(method2, st, ref)


# ---------------------------------------------------------------------------------------------- thin slab
PLANK = dict(D=4.0, h=1.5, pitch=-25.0, R=0.6)


def plank_gbuffer(H, W, D, h, pitch):
    rot = _rotation_x(math.radians(pitch))
    nf = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64) @ rot  # the floor's normal in view space
    floor = (tuple(nf.tolist()), -h, None)
    plank = ((0.0, 0.0, 1.0), -D, [((1.0, 0.0, 0.0), 0.0), (tuple((-nf).tolist()), h)])
    return planes_gbuffer([floor, plank], PinholeCamera.from_fov(60.0, H, W)), nf


def ray_meets_region(P, w, A, b, R):
    """``(M,K)`` bool: whether ``P (M,3) + t w (K,3)``, ``0 <= t <= R``, meets ``{x : A x <= b}``."""
    lo = torch.zeros(P.shape[0], w.shape[0], dtype=torch.float64)
    hi = torch.full_like(lo, R)
    for a, c in zip(A, b):
        room = (c - P @ a)[:, None]  # a.(P + t w) <= c  <=>  t (a.w) <= room
        d = (w @ a)[None, :].expand_as(lo)
        t = room / torch.where(d == 0, torch.ones_like(d), d)
        hi = torch.where(d > 0, torch.minimum(hi, t), hi)
        lo = torch.where(d < 0, torch.maximum(lo, t), lo)
        lo = torch.where((d == 0) & (room < 0), torch.full_like(lo, math.inf), lo)
    return lo <= hi


def plank_visibility(P, nf, D, h, T, R, N=250):
    """Exact cosine-weighted visibility ``(M,)`` of floor points ``P`` beside the plank of thickness ``T``."""
    g = (torch.arange(N, dtype=torch.float64) + 0.5) / N * 2 - 1
    a, b = (x.reshape(-1) for x in torch.meshgrid(g, g, indexing="ij"))
    disc = a * a + b * b < 1
    a, b = a[disc], b[disc]
    t, bt = frame(nf)
    w = a[:, None] * t + b[:, None] * bt + (1 - a * a - b * b).sqrt()[:, None] * nf
    ez = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    # x <= 0; -z >= D; -z <= D + T; the camera ray through the point meets the plank above the floor.
    A = torch.stack((torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), ez, -ez, -D * nf + h * ez))
    bounds = torch.tensor([0.0, -D, D + min(T, 1e30), 0.0], dtype=torch.float64)
    return 1 - ray_meets_region(P, w, A, bounds, R).double().mean(1)


def ball_on_screen(camera, P, R, margin=1.0):
    """Whether the cube of half-size ``R`` around each ``P (...,3)`` (so its ball) projects inside the image."""
    corners = torch.tensor([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=torch.float64) * R
    u, v, d = camera.to(dtype=torch.float64).view_to_pixel(P[..., None, :] + corners)
    H, W = camera.height, camera.width
    return ((u >= margin) & (u <= W - 1 - margin) & (v >= margin) & (v <= H - 1 - margin) & (d > 0)).all(-1)


@pytest.fixture(scope="module")
def plank():
    D, h, R = PLANK["D"], PLANK["h"], PLANK["R"]
    gb, nf = plank_gbuffer(192, 256, D, h, PLANK["pitch"])
    pos = gb.positions().double()[0].permute(1, 2, 0)
    x, depth = pos[..., 0], -pos[..., 2]
    sel = (gb.object_id[0, 0] == 1) & (x > 0) & (x < 0.5) & (depth > D - 0.3) & (depth < D + 0.25)
    sel &= ball_on_screen(gb.camera, pos, R)
    sparse = torch.zeros_like(sel)
    sparse[::2, ::2] = True
    sel &= sparse
    exact = {T: plank_visibility(pos[sel], nf, D, h, T, R) for T in (0.05, math.inf)}
    return gb, sel, exact, R


def _plank_error(plank, T, **kwargs):
    gb, sel, exact, R = plank
    st = screen_space_truth(gb, R, T, rays=1024, min_steps=64, where=sel[None, None], **kwargs)
    e = st.visibility[0, 0][sel].double() - exact[T]
    se = st.stderr[0, 0][sel].double()
    return e, se, st


def test_plank_thickness_matters_and_the_truth_follows_it(plank):
    gb, sel, exact, R = plank
    assert int(sel.sum()) >= 40
    assert float((exact[0.05] - exact[math.inf]).max()) > 0.1  # a thin plank lets many rays pass behind it
    for T in (0.05, math.inf):
        e, se, st = _plank_error(plank, T, fetch="edge_aware", edge_ratio=1.02)
        assert abs(float(e.mean())) <= 4 * float(se.square().sum().sqrt()) / se.numel() + 1e-3, (T, float(e.mean()))
        assert float((e.abs() <= 4 * se + 0.01).double().mean()) >= 0.95
        assert st.visibility[~sel[None, None]].eq(1).all()  # pixels outside ``where`` are not estimated


def test_bilinear_skirts_occlude_behind_a_thin_plank(plank):
    # Bilinear fetch joins the plank's edge to the floor behind it by an interpolated surface, which blocks the
    # rays passing behind the plank: the depth buffer as the methods' default fetch reads it.
    e, se, _ = _plank_error(plank, 0.05, fetch="bilinear")
    assert float(e.mean()) < -0.01
    e, se, _ = _plank_error(plank, math.inf, fetch="bilinear")  # no rays pass behind an infinite plank
    assert abs(float(e.mean())) < 0.005


def test_too_few_steps_miss_a_thin_slab(plank):
    gb, sel, exact, R = plank
    coarse = screen_space_truth(gb, R, 0.05, rays=256, min_steps=2, max_steps=2, where=sel[None, None],
                                fetch="edge_aware", edge_ratio=1.02)
    e = coarse.visibility[0, 0][sel].double() - exact[0.05]
    assert float(e.mean()) > 0.01  # points 0.3 apart step over a slab 0.05 thick


# ---------------------------------------------------------------------------------------------- limits
def test_standard_error_shrinks_at_least_as_one_over_sqrt_rays(wall):
    gb, vis, mask, d, R = wall
    errs, ses = [], []
    for rays in (16, 256):
        st = screen_space_truth(gb, R, rays=rays)
        errs.append(float((st.visibility[0, 0].double() - vis)[mask].square().mean().sqrt()))
        ses.append(float(st.stderr[0, 0][mask].square().mean().sqrt()))
    # At least sqrt(16) = 4: stratification does better than independent rays (16^0.75 = 8 for a sharp edge).
    assert 3.5 < ses[0] / ses[1] < 10.0
    assert 3.0 < errs[0] / errs[1] < 12.0
    assert 0.6 < errs[1] / ses[1] < 1.6  # the reported error is the actual one


def test_zero_thickness_occludes_nothing(wall):
    gb, vis, mask, d, R = wall
    assert float(screen_space_truth(gb, R, 0.0, rays=64).visibility.min()) == 1.0
    thin = screen_space_truth(gb, R, 1e-4, rays=64).visibility
    assert float((1 - thin).mean()) < 2e-3


def test_screen_bound_counts_occluders_beyond_the_radius(plank):
    # Floor pixels 0.85-1 behind the plank's plane, just right of its edge: the plank (thickness 0.3) is farther
    # than R = 0.5, but within the radius projected on screen.
    gb, _, _, R = plank
    D = PLANK["D"]
    pos = gb.positions().double()[0].permute(1, 2, 0)
    far = (gb.object_id[0, 0] == 1) & (pos[..., 0] > 0) & (pos[..., 0] < 0.3) & (-pos[..., 2] > D + 0.85) & (-pos[..., 2] < D + 1.0)
    assert int(far.sum()) >= 8
    where = far[None, None]
    kwargs = dict(rays=256, where=where, fetch="edge_aware", edge_ratio=1.02)  # no skirt at the plank's edge
    sphere = screen_space_truth(gb, 0.5, 0.3, **kwargs)
    screen = screen_space_truth(gb, 0.5, 0.3, bound="screen", **kwargs)
    assert float(sphere.visibility[0, 0][far].mean()) > 0.99
    assert float(screen.visibility[0, 0][far].mean()) < 0.98
    assert float(screen_space_truth(plane_gbuffer(16, 20), 0.5, rays=16, bound="screen").visibility.min()) == 1.0


def test_report_rows_split_each_pipeline_error(wall):
    import importlib.util
    import sys
    from pathlib import Path

    from torch_ao import Denoiser, GTAO, BitmaskAO, error_metrics
    from torch_ao.fit import FitView

    spec = importlib.util.spec_from_file_location("accuracy_report", Path(__file__).parents[1] / "benchmarks" / "accuracy_report.py")
    report = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("accuracy_report", report)  # dataclasses look their module up there
    spec.loader.exec_module(report)
    gb, vis, mask, d, R = wall
    reference = torch.where(gb.valid, torch.nan_to_num(vis.float(), nan=1.0)[None, None], torch.ones_like(gb.depth))
    view = FitView(gb, reference, name="wall")
    truths = report.Truths(R, 16, log=lambda *_: None)
    gtao = GTAO(preset="low", radius=R)
    pipes = [report.Pipeline("gtao", gtao, None, "low"), report.Pipeline("gtao", gtao, Denoiser(), "low"),
             report.Pipeline("bitmask", BitmaskAO(preset="low", radius=R, thickness=0.25), None, "low")]
    rows = report.pipeline_rows(pipes, [view], truths, log=lambda *_: None)
    assert [r["thickness"] for r in rows] == ["inf", "inf", "0.25"]
    with torch.no_grad():
        out = gtao(gb).visibility
    truth = truths.get(view, math.inf)
    assert rows[0]["ref_mae"] == pytest.approx(error_metrics(out, reference, gb.valid)["mae"])
    assert rows[0]["truth_mae"] == pytest.approx(error_metrics(out, truth.visibility, gb.valid)["mae"])
    assert rows[0]["screen_mae"] == pytest.approx(error_metrics(truth.visibility, reference, gb.valid)["mae"])
    assert rows[1]["ref_mae"] != rows[0]["ref_mae"]  # the denoised row
