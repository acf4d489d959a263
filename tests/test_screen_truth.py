"""The screen-space ground truth against closed forms, and the split of the error.

Closed forms (see tests/test_horizon_analytic.py and docs/reference.md): a point on a floor at distance
``d`` from an infinite wall, ``k = min(d/R, 1)``: cosine-weighted visibility ``1 - (acos k - k sqrt(1-k^2))/pi``,
uniform-weighted ``(1 + k)/2``. Any thickness > 0 gives the same limit (a ray that reaches the wall's front
within ``R`` is inside the slab just behind it); an infinite plane gives 1. Pixels are used only where the
wall's relevant part projects on screen (rays leaving the screen are unoccluded by definition).
"""
import math

import pytest
import torch
from test_horizon_analytic import floor_wall_case

from torch_ao.examples import plane_gbuffer
from torch_ao.screen_truth import ScreenTruth, screen_space_truth, split_error, thickness_map


def _within_error(estimate, stderr, exact, mask, z=4.0, share=0.97):
    """Most pixels within ``z`` standard errors, and the mean error within ``z`` of its own error."""
    e = (estimate.double() - exact)[mask]
    se = stderr.double()[mask]
    per_pixel = (e.abs() <= z * se + 1e-6).double().mean()
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
    st = screen_space_truth(gb, R, rays=512, uniform=True)
    ok, share, mean, se = _within_error(st.visibility[0, 0], st.stderr[0, 0], vis, mask)
    assert ok, (share, mean, se)
    k = (d / R).clamp(max=1.0)
    ok, share, mean, se = _within_error(st.uniform[0, 0], st.uniform_stderr[0, 0], (1 + k) / 2, mask)
    assert ok, (share, mean, se)


def test_reproducible_whatever_the_chunking(wall):
    gb, *_ = wall
    a = screen_space_truth(gb, 1.0, rays=32, seed=3)
    b = screen_space_truth(gb, 1.0, rays=32, seed=3, chunk_points=5000)
    c = screen_space_truth(gb, 1.0, rays=32, seed=4)
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
        assert s.truth_stderr == pytest.approx(0.002)
    with pytest.raises(ValueError, match="reference"):
        split_error(method2, st, ref)
