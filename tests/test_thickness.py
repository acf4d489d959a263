"""Thickness models: each one against the scalar it reduces to, the G-buffer field it reads, and
finite differences of its fitted parameters (float64)."""
import math

import numpy as np
import pytest
import torch

from torch_ao.examples import floor_wall_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.io import load_gbuffer, save_npz
from torch_ao.methods.bitmask import BitmaskAO
from torch_ao.thickness import (BackfaceThickness, LinearThickness, MapThickness, ObjectThickness, ScalarThickness,
                                as_thickness)

D = torch.float64


def _gbuffer(**extra):
    gb, _ = floor_wall_gbuffer(12, 14, wall_distance=0.6, camera_height=1.5, pitch_degrees=-40.0, dtype=D)
    return GBuffer(gb.depth, gb.camera, normals=gb.normals, object_id=gb.object_id, **extra)


OPTS = dict(slices=2, steps=3, jitter=False, radius=0.8)


@pytest.mark.parametrize("kw", [dict(mode="soft", tau=0.5), dict(mode="hard"), dict(variant="exact")])
def test_models_reduce_to_the_scalar(kw):
    gb = _gbuffer()
    back = GBuffer(gb.depth, gb.camera, normals=gb.normals, backface_depth=gb.depth + 0.3)
    scalar = BitmaskAO(thickness=0.3, **OPTS, **kw)(gb).visibility
    for model, g in ((LinearThickness(0.3, slope=0.0), gb), (BackfaceThickness(), back),
                     (BackfaceThickness(scale=0.5, thickness=0.15), back)):  # 0.5 * 0.3 + 0.15
        out = BitmaskAO(thickness=model, **OPTS, **kw)(g).visibility
        assert torch.allclose(out, scalar, atol=1e-12), type(model).__name__


def test_linear_thickness_is_the_map_of_the_sample_depth():
    # With nearest fetch the sample is a texel, so a + b * depth at the sample equals the map a + b * depth
    # read at that texel: the occluder's own depth is used, not the pixel's.
    gb = _gbuffer()
    a, b = 0.05, 0.2
    tmap = (a + b * gb.safe_depth).to(D)
    ref = BitmaskAO(thickness=tmap, fetch="nearest", mode="soft", tau=0.3, **OPTS)(gb).visibility
    out = BitmaskAO(thickness=LinearThickness(a, slope=b), fetch="nearest", mode="soft", tau=0.3, **OPTS)(gb).visibility
    assert torch.allclose(out, ref, atol=1e-12)
    assert not torch.allclose(out, BitmaskAO(thickness=a + b * 2.0, fetch="nearest", mode="soft", tau=0.3, **OPTS)(gb).visibility)


def test_backface_layer_is_each_occluders_own_thickness():
    # Back faces 0.1 behind the floor (object 1) and 2.0 behind the wall (object 2): the same as a
    # per-object table (0.1, 2.0) read at the sample (nearest fetch: ids are read at the nearest texel,
    # a bilinear fetch of the layer would blend the two across the crease).
    gb = _gbuffer()
    table = torch.tensor([0.0, 0.1, 2.0], dtype=D)
    back = gb.depth + table[gb.object_id]
    g = GBuffer(gb.depth, gb.camera, normals=gb.normals, object_id=gb.object_id, backface_depth=back)
    ref = BitmaskAO(thickness=table, mode="soft", tau=0.3, fetch="nearest", **OPTS)(g).visibility
    out = BitmaskAO(thickness=BackfaceThickness(), mode="soft", tau=0.3, fetch="nearest", **OPTS)(g).visibility
    assert torch.allclose(out, ref, atol=1e-12)


@pytest.mark.parametrize("variant", ["default", "exact"])
def test_fitted_parameters_match_finite_differences_float64(variant):
    gb = _gbuffer()
    back = GBuffer(gb.depth, gb.camera, normals=gb.normals, backface_depth=gb.depth + 0.25 + 0.1 * gb.safe_depth)
    kw = dict(mode="soft", tau=0.5) if variant == "default" else dict(variant="exact")
    cases = [(LinearThickness(0.1, slope=0.1), gb, ("thickness", "thickness_slope")),
             (BackfaceThickness(scale=1.2, thickness=0.05), back, ("thickness_scale", "thickness")),
             (ScalarThickness(0.3, growth=0.5), gb, ("thickness", "thickness_growth"))]
    for model, g, names in cases:
        module = BitmaskAO(thickness=model, **OPTS, **kw).double()
        module(g).visibility.sum().backward()
        for name in names:
            p = getattr(module, name)
            eps = 1e-6
            with torch.no_grad():
                p += eps
                up = module(g).visibility.sum()
                p -= 2 * eps
                down = module(g).visibility.sum()
                p += eps
            fd = float((up - down) / (2 * eps))
            assert abs(fd) > 1e-6, f"{type(model).__name__}.{name}: vacuous"
            assert float(p.grad) == pytest.approx(fd, rel=1e-4, abs=1e-8), f"{type(model).__name__}.{name}"


def test_legacy_forms_map_onto_the_classes():
    assert type(as_thickness(0.5)) is ScalarThickness
    assert type(as_thickness(torch.ones(3))) is ObjectThickness
    assert type(as_thickness(torch.ones(1, 1, 4, 4))) is MapThickness
    assert as_thickness(0.5, growth=0.2).growth == 0.2
    m = BitmaskAO(thickness=LinearThickness(0.1, slope=0.02), thickness_growth=0.3)
    assert {n for n, _ in m.named_parameters()} == {"radius", "thickness", "thickness_slope", "thickness_growth"}
    # a map set per frame on a module built with a scalar switches the model
    gb = _gbuffer()
    ao = BitmaskAO(thickness=0.3, trainable=False, **OPTS)
    ref = ao(gb).visibility
    ao.thickness = torch.full_like(gb.depth, 0.3)
    assert torch.allclose(ao(gb).visibility, ref)


def test_bad_thickness_inputs_are_named():
    gb = _gbuffer()
    with pytest.raises(ValueError, match="backface_depth"):
        BitmaskAO(thickness=BackfaceThickness(), **OPTS)(gb)
    with pytest.raises(ValueError, match="backface_depth"):
        GBuffer(gb.depth, gb.camera, backface_depth=gb.depth - 0.1)
    with pytest.raises(ValueError, match="thickness_growth"):
        BitmaskAO(thickness=ScalarThickness(0.2, growth=0.1), thickness_growth=0.2)
    with pytest.raises(ValueError, match="thickness"):
        BitmaskAO(thickness="thick")


def test_backface_depth_round_trips_through_npz(tmp_path):
    gb = _gbuffer()
    back = torch.where(gb.valid, gb.depth + 0.2, torch.full_like(gb.depth, math.inf))
    g = GBuffer(gb.depth, gb.camera, normals=gb.normals, backface_depth=back)
    path = save_npz(tmp_path / "frame.npz", g)
    loaded, extras = load_gbuffer(path)
    assert "backface_depth" not in extras
    assert torch.allclose(loaded.backface_depth[g.valid].double(), back[g.valid])
    assert np.load(path)["backface_depth"].shape == (12, 14) or np.load(path)["backface_depth"].shape == (1, 12, 14)
