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


def test_one_model_serves_modules_with_and_without_growth():
    """``thickness_growth=`` does not write into the model it is given: a module built after one with growth reads
    the model without it, and a second module with growth can be built from the same model."""
    gb = _gbuffer()
    model = LinearThickness(0.1, slope=0.02)
    plain = BitmaskAO(thickness=LinearThickness(0.1, slope=0.02), trainable=False, **OPTS)(gb).visibility
    grown = BitmaskAO(thickness=model, thickness_growth=2.0, trainable=False, **OPTS)(gb).visibility
    assert model.growth is None
    again = BitmaskAO(thickness=model, thickness_growth=2.0, trainable=False, **OPTS)(gb).visibility
    after = BitmaskAO(thickness=model, trainable=False, **OPTS)(gb).visibility
    assert torch.equal(again, grown) and torch.equal(after, plain)
    assert not torch.allclose(grown, plain)  # (the growth changes the frame's visibility)
    assert "thickness_growth" not in dict(BitmaskAO(thickness=model, **OPTS).named_parameters())


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


# ---------------------------------------------------------------------------------------------
# The learned per-pixel thickness (NetThickness)
# ---------------------------------------------------------------------------------------------
from torch_ao.fit import FitConfig, fit  # noqa: E402
from torch_ao.thickness import NetThickness  # noqa: E402
from torch_ao.thickness_net import PREFIX, ThicknessCNN, net_features  # noqa: E402
from torch_ao.views import FitView  # noqa: E402


def _net(scale=0.8, init=0.3, seed=0, **kw):
    """A float64 NetThickness whose head is not zero (so gradients reach every layer)."""
    torch.manual_seed(seed)
    cnn = ThicknessCNN(width=4, init=init / scale).double()
    with torch.no_grad():
        cnn.head.weight.normal_(0.0, 0.3)
    return NetThickness(scale, cnn=cnn, **kw)


def test_net_thickness_registers_its_weights_and_predicts_a_nonnegative_map():
    gb = _gbuffer()
    model = _net()
    ao = BitmaskAO(thickness=model, **OPTS).double()
    names = {n for n, _ in ao.named_parameters()}
    cnn_names = {PREFIX + n.replace(".", "_") for n, _ in model.cnn.named_parameters()}
    assert cnn_names | {"thickness", "radius"} == names and len(cnn_names) == 8
    tmap = model.predict(gb, ao)
    assert tmap.shape == gb.depth.shape and tmap.dtype == D
    assert bool((tmap[gb.valid] > 0).all()) and bool((tmap[~gb.valid] == 0).all())
    assert float(tmap[gb.valid].detach().std()) > 1e-4  # a map, not a constant
    # the samples read that map: the same AO as MapThickness with it (the offset added everywhere)
    with torch.no_grad():
        ao.thickness.fill_(0.05)
    ref = BitmaskAO(thickness=model.predict(gb, ao, offset=False).detach() + 0.05, mode="soft", tau=0.4, **OPTS)
    ao.mode, ao.tau = "soft", 0.4
    assert torch.allclose(ao(gb).visibility, ref(gb).visibility, atol=1e-12)
    assert net_features(gb, 0.8).shape == (1, 8, *gb.depth.shape[-2:])


def test_untrained_net_thickness_is_the_scalar_init():
    # head weights zero: softplus(softplus^-1(init / scale)) * scale = init at every pixel
    gb = _gbuffer()
    model = NetThickness(0.8, init=0.3, cnn=ThicknessCNN(4, 0.3 / 0.8).double())
    out = BitmaskAO(thickness=model, mode="soft", tau=0.5, **OPTS).double()(gb).visibility
    ref = BitmaskAO(thickness=0.3, mode="soft", tau=0.5, **OPTS)(gb).visibility
    assert torch.allclose(out, ref, atol=1e-10)
    assert NetThickness(2.0, init=0.3).predict(gb)[gb.valid].detach() == pytest.approx(0.3, rel=1e-6)


@pytest.mark.parametrize("variant", ["default", "exact"])
def test_net_thickness_gradients_match_finite_differences_float64(variant):
    gb = _gbuffer()
    kw = dict(mode="soft", tau=0.5) if variant == "default" else dict(variant="exact")
    module = BitmaskAO(thickness=_net(), **OPTS, **kw).double()
    module(gb).visibility.sum().backward()
    for name, index in (("thickness_net_body_0_weight", (1, 0, 1, 1)), ("thickness_net_body_2_bias", (2,)),
                        ("thickness_net_head_weight", (0, 1, 0, 2)), ("thickness_net_head_bias", (0,)),
                        ("thickness", ())):
        p = getattr(module, name)
        eps = 1e-6
        with torch.no_grad():
            p[index] += eps
            up = module(gb).visibility.sum()
            p[index] -= 2 * eps
            down = module(gb).visibility.sum()
            p[index] += eps
        fd = float((up - down) / (2 * eps))
        assert abs(fd) > 1e-6, f"{name}: vacuous"
        assert float(p.grad[index]) == pytest.approx(fd, rel=1e-4, abs=1e-8), name


def test_net_thickness_learns_the_thickness_of_two_slabs():
    # A floor slab 0.2 thick and a wall 1.0 thick (the back-face layer of the two): supervised on that
    # layer from the front G-buffer alone, the net must tell them apart (by their normals).
    gb = _gbuffer()
    target = torch.tensor([0.0, 0.2, 1.0], dtype=D)[gb.object_id]
    torch.manual_seed(0)
    model = NetThickness(1.0, width=8, init=0.5)
    opt = torch.optim.Adam(model.cnn.parameters(), lr=0.02)
    losses = []
    for _ in range(120):
        opt.zero_grad()
        loss = (model.predict(gb) - target)[gb.valid].abs().mean()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    start = float((torch.full_like(target, 0.5) - target)[gb.valid].abs().mean())
    assert losses[0] == pytest.approx(start, rel=1e-5)
    assert losses[-1] < 0.15 * start, losses[::20]


def test_net_thickness_is_fitted_end_to_end_through_fit():
    # The reference is bitmask AO itself with a 0.15 slab everywhere; the net starts at 0.6. fit()
    # sees its weights by name and lowers the loss in hard mode on the view (kept only if it improves).
    gb = _gbuffer()
    opts = dict(OPTS, steps=4)
    reference = BitmaskAO(thickness=0.15, mode="hard", **opts)(gb).visibility.detach()
    torch.manual_seed(0)
    model = NetThickness(0.8, width=4, init=0.6)
    ao = BitmaskAO(thickness=model, mode="soft", **opts)
    names = tuple(n for n, _ in ao.named_parameters() if n.startswith(PREFIX))
    result = fit(ao, [FitView(gb, reference)], FitConfig(params=names, steps=30, lr=0.02, hard_every=5), progress=False)
    hard = [h["loss"] for h in result.hard_history]
    ao.mode = "hard"
    after = float((ao(gb).visibility - reference)[gb.valid].abs().mean())
    before = float((BitmaskAO(thickness=0.6, mode="hard", **opts)(gb).visibility - reference)[gb.valid].abs().mean())
    assert before > 0.01 and after < 0.5 * before, (before, after, hard)
    assert float(model.predict(gb, ao)[gb.valid].detach().median()) < 0.45


def test_net_thickness_save_load_round_trip(tmp_path):
    gb = _gbuffer()
    ao = BitmaskAO(thickness=_net(), mode="soft", tau=0.3, **OPTS).double()
    with torch.no_grad():  # weights that differ from the model's start
        ao.thickness_net_body_0_bias.add_(0.1)
        ao.thickness.fill_(0.02)
    path = ao.thickness_model.save(tmp_path / "net.pt", ao)
    loaded = NetThickness.load(path)
    assert loaded.scale == 0.8 and float(loaded.initial) == pytest.approx(0.02)
    again = BitmaskAO(thickness=loaded, mode="soft", tau=0.3, **OPTS).double()
    assert torch.equal(again(gb).visibility, ao(gb).visibility)
    assert torch.equal(loaded.predict(gb, again), ao.thickness_model.predict(gb, ao))
    torch.save({"weights": 1}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="path"):
        NetThickness.load(tmp_path / "other.pt")


def test_net_thickness_bad_inputs_are_named():
    with pytest.raises(ValueError, match="scale"):
        NetThickness(0.0)
    with pytest.raises(ValueError, match="width"):
        NetThickness(1.0, width=0)
    with pytest.raises(ValueError, match="cnn"):
        NetThickness(1.0, cnn=torch.nn.Conv2d(8, 1, 3))
    with pytest.raises(ValueError, match="thickness_net_head_bias"):
        NetThickness(1.0).check("thickness_net_head_bias", torch.zeros(2))


def test_net_thickness_offset_is_added_to_its_own_map():
    gb = _gbuffer()
    plain, shifted = NetThickness(1.0, init=0.4), NetThickness(1.0, init=0.4, thickness=0.1)
    shifted.cnn.load_state_dict(plain.cnn.state_dict())
    diff = (shifted.predict(gb) - plain.predict(gb))[gb.valid].detach()
    assert diff.numpy() == pytest.approx(0.1, abs=1e-6)
