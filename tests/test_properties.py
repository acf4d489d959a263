"""Property-based checks (hypothesis): random plane scenes, cameras and parameters within the
documented ranges keep every method finite, in [0, 1] and at 1 on background; and the hard bitmask's
monotonicity, where the published rule guarantees it."""
from __future__ import annotations

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torch_ao.camera import PinholeCamera
from torch_ao.examples import planes_gbuffer
from torch_ao.methods import get_method
from torch_ao.sectors import hard_count, hard_mask, popcount32

METHODS = ("ssao", "hbao", "ue4_ssao", "gtao", "pssao", "bitmask", "ssilvb")


@st.composite
def scenes(draw):
    """A floor, a wall and a slab at random poses, seen by a random camera (8..14 x 8..14 pixels)."""
    h, w = draw(st.integers(8, 14)), draw(st.integers(8, 14))
    fov = draw(st.floats(5.0, 150.0))
    f = 0.5 * h / math.tan(math.radians(fov) / 2)
    cx = draw(st.floats(-0.5, 1.5)) * (w - 1)
    cy = draw(st.floats(-0.5, 1.5)) * (h - 1)
    K = torch.tensor([[[f, 0, cx], [0, f, cy], [0, 0, 1.0]]], dtype=torch.float64)
    planes = []
    for _ in range(draw(st.integers(1, 3))):
        n = [draw(st.floats(-1, 1)) for _ in range(3)]
        if sum(x * x for x in n) < 1e-3:
            n = [0.0, 1.0, 0.2]
        planes.append((tuple(n), draw(st.floats(-5.0, -0.05)) if n[2] > 0 else draw(st.floats(0.05, 5.0)), None))
    light = tuple(draw(st.floats(-1, 1)) for _ in range(2)) + (1.0,)
    return planes_gbuffer(planes, PinholeCamera(K, h, w), dtype=torch.float64, light_direction=light)


@settings(max_examples=80, deadline=None)
@given(gb=scenes(), method=st.sampled_from(METHODS), radius=st.floats(0.01, 10.0),
       slices=st.integers(1, 4), steps=st.integers(1, 4), seed=st.integers(0, 1000), soft=st.booleans(),
       thickness=st.floats(0.0, 5.0), tau=st.floats(1e-4, 1.0))
def test_random_scenes_stay_finite_and_bounded(gb, method, radius, slices, steps, seed, soft, thickness, tau):
    cls = get_method(method)
    kwargs = {k: v for k, v in dict(radius=radius, slices=slices, steps=steps, seed=seed).items()
              if k in cls.options()}  # (PSSAO has no radius or seed)
    if method in ("bitmask", "ssilvb"):
        kwargs |= dict(thickness=thickness, mode="soft" if soft else "hard", tau=tau)
    module = cls(**kwargs)
    depth = gb.depth.clone().requires_grad_(True)
    g = type(gb)(depth, gb.camera, normals=gb.normals, light=gb.light)
    out = module(g)
    vis = out.visibility
    assert torch.isfinite(vis).all() and vis.min() >= 0 and vis.max() <= 1
    assert torch.all(vis[~g.valid] == 1)
    if out.indirect is not None:
        assert torch.isfinite(out.indirect).all() and out.indirect.min() >= 0
    loss = vis.sum() + (out.indirect.sum() if out.indirect is not None else 0)
    if loss.requires_grad:
        (grad,) = torch.autograd.grad(loss, depth, allow_unused=True)
        assert grad is None or torch.isfinite(grad).all()


@settings(max_examples=200, deadline=None)
@given(s=st.floats(0.0, 32.0), w=st.floats(0.0, 32.0), dw=st.floats(0.0, 8.0),
       rounding=st.sampled_from(("ceil", "round", "floor")))
def test_hard_sector_count_never_shrinks_when_the_interval_grows_upward(s, w, dw, rounding):
    # More thickness moves the back angle away from the front: for the side where the interval grows
    # at its upper end the start sector is fixed, so the mask only gains bits.
    a = hard_mask(torch.tensor([s]), torch.tensor([w]), rounding)
    b = hard_mask(torch.tensor([s]), torch.tensor([w + dw]), rounding)
    assert int(a & ~b) == 0
    assert int(hard_count(torch.tensor([w + dw]), rounding)) >= int(hard_count(torch.tensor([w]), rounding))


def test_published_rule_is_not_monotone_when_the_interval_grows_downward():
    """The documented limitation: ``start = floor(min * 32)`` anchors the run at the sector holding the
    lower end, so lowering that end by 0.01 sector (what more thickness does on one side of a slice)
    can move a one-sector run to the sector below: the union with other steps may then lose a sector,
    and visibility can *rise* with thickness by one sector of one slice."""
    before = hard_mask(torch.tensor([1.00]), torch.tensor([0.10]))
    after = hard_mask(torch.tensor([0.99]), torch.tensor([0.11]))
    assert int(before) == 0b10 and int(after) == 0b01
    other_step = torch.tensor(0b01)
    assert int(popcount32(before | other_step)) == 2 and int(popcount32(after | other_step)) == 1


@settings(max_examples=25, deadline=None)
@given(gb=scenes(), radius=st.floats(0.01, 10.0), slices=st.integers(1, 4), steps=st.integers(1, 6),
       seed=st.integers(0, 1000), thickness=st.floats(0.0, 5.0), slope=st.floats(0.0, 1.0),
       linear=st.booleans(), weighting=st.sampled_from(("uniform", "cosine")))
def test_exact_variant_stays_finite_and_bounded(gb, radius, slices, steps, seed, thickness, slope, linear, weighting):
    from torch_ao.methods.bitmask import BitmaskAO
    from torch_ao.thickness import LinearThickness

    model = LinearThickness(thickness, slope=slope) if linear else thickness
    module = BitmaskAO(variant="exact", weighting=weighting, radius=radius, slices=slices, steps=steps, seed=seed,
                       thickness=model)
    depth = gb.depth.clone().requires_grad_(True)
    g = type(gb)(depth, gb.camera, normals=gb.normals)
    vis = module(g).visibility
    assert torch.isfinite(vis).all() and vis.min() >= 0 and vis.max() <= 1 + 1e-6
    assert torch.all(vis[~g.valid] == 1)
    grads = torch.autograd.grad(vis.sum(), [depth, module.thickness, module.radius], allow_unused=True)
    assert all(x is None or bool(torch.isfinite(x).all()) for x in grads)
