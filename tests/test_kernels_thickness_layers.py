"""Thickness models the kernels read as ``ThicknessLayer`` (``t = scale * value + offset`` at a sample, the
value a layer read as depth is, a layer at the first tap, or the sample's depth): a map, the net's map, a
per-object table and the linear model, in the ``"default"`` variant's hard kernel, the exact
union's hard kernel and its kernel with gradients, against the tensor-op walk by the tolerance of
tests/kernel_agreement.py, in SIMD and scalar lanes."""
import math

import pytest
import torch

from kernel_agreement import assert_masks_agree, assert_values_agree
from test_kernels import FRAMES, built, pytestmark  # noqa: F401  (built: the fixture)
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import bitmask_soft, exact_covers, kernel_covers, kernel_forward
import torch_ao.kernels.soft_bitmask as soft_module
from torch_ao.kernels.bitmask import (bitmask_outputs, exact_hard, module_thickness, ssilvb_glsl_hard,
                                      thickness_options)
from torch_ao.kernels.soft_exact import exact_soft_covers
from torch_ao.methods.bitmask import BitmaskAO
from torch_ao.thickness import (BackfaceThickness, LinearThickness, MapThickness, NetThickness, ObjectThickness,
                                ScalarThickness)


def _frame(name: str) -> GBuffer:
    """Frame ``name`` with two objects (left and right of a diagonal) for the per-object table."""
    gb = FRAMES[name]()
    B, _, H, W = gb.depth.shape
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    ids = ((u * H + v * W) > H * W).to(torch.int64).expand(B, 1, H, W).contiguous()
    return GBuffer(depth=gb.depth, camera=gb.camera, normals=gb.normals, object_id=ids)


def _map(gb: GBuffer) -> torch.Tensor:
    """A thickness map that varies over the frame (world units): thin stripes between thick ones."""
    B, _, H, W = gb.depth.shape
    u = torch.linspace(0, 1, W).view(1, 1, 1, W)
    return (0.05 + 0.6 * torch.sin(12 * u) ** 2).expand(B, 1, H, W).contiguous()


MODELS = {
    "map": lambda gb: MapThickness(_map(gb)),
    "net": lambda gb: NetThickness(scale=1.0, init=0.3, thickness=0.05),
    "object": lambda gb: ObjectThickness(torch.tensor([0.05, 0.8])),
    "linear": lambda gb: LinearThickness(0.02, 0.15),
}
FETCH = {"map": "bilinear", "net": "edge_aware", "object": "bilinear", "linear": "edge_aware"}


def _value_map(module, gb) -> torch.Tensor:
    """The thickness a sample on each texel reads (to take its mean as one scalar)."""
    form = module_thickness(module, gb)
    return form.layer if form.read != "depth" else form.scale * gb.depth + form.offset


def _module(model: str, gb: GBuffer, **options) -> BitmaskAO:
    torch.manual_seed(0)  # the net's initial weights
    options.setdefault("fetch", FETCH[model])
    return BitmaskAO(thickness=MODELS[model](gb), backend="torch", trainable=False, **options)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("frame", ["example", "rough", "floor_wall"])
@pytest.mark.parametrize("model", sorted(MODELS))
def test_hard_kernel_reads_the_layer_as_the_tensor_walk(built, model, frame, lanes):
    gb = _frame(frame)
    for weighting in ("uniform", "cosine"):
        module = _module(model, gb, slices=3, steps=4, weighting=weighting)
        with torch.no_grad():
            assert kernel_covers(module, gb) is None
            reference = module(gb).visibility
            if lanes == "simd":
                out = kernel_forward(module, gb, "kernel")["visibility"]
            else:
                out = bitmask_outputs(gb, gb.view_normals(), slices=3, steps=4, radius=float(module.radius),
                                      **thickness_options(module_thickness(module, gb)), fetch=module.fetch,
                                      weighting=weighting, min_step_px=module.min_step_px, lanes="scalar").visibility
            # the layer matters on this frame: its mean as one scalar gives other masks
            mean = float(_value_map(module, gb)[gb.valid].mean())
            scalar = BitmaskAO(slices=3, steps=4, weighting=weighting, fetch=module.fetch, thickness=mean,
                               backend="kernel", trainable=False)(gb).visibility
        assert reference.min() < 0.9 and (scalar - reference).abs().max() > 0.02
        if weighting == "uniform":
            assert_masks_agree(out, reference, gb.valid, slices=3)
        else:
            assert_values_agree(out, reference, gb.valid, bound=1 / (32 * 3) + 1e-6)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("frame", ["example", "rough"])
@pytest.mark.parametrize("model", sorted(MODELS))
def test_exact_kernel_reads_the_layer_as_the_tensor_walk(built, model, frame, lanes):
    gb = _frame(frame)
    module = _module(model, gb, variant="exact", slices=3, steps=4)
    with torch.no_grad():
        assert exact_covers(module, gb) is None
        reference = module(gb).visibility
        if lanes == "simd":
            out = kernel_forward(module, gb, "kernel")["visibility"]
        else:
            out = exact_hard(gb, gb.view_normals(), slices=3, steps=4, radius=float(module.radius), fetch=module.fetch,
                             **thickness_options(module_thickness(module, gb)), lanes="scalar")
    assert reference.min() < 0.9
    assert_values_agree(out, reference, gb.valid, bound=0.05)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("frame", ["example", "rough"])
@pytest.mark.parametrize("model", sorted(MODELS))
def test_the_glsl_shaders_kernel_reads_the_layer_as_the_tensor_walk(built, model, frame, lanes):
    """The ``"ssilvb_glsl"`` variant's hitThickness read at each sample's texel (the shader fetches the nearest one),
    AO and indirect light, by tests/test_kernels_glsl.py's agreement (its masks are never reset across slices)."""
    from test_kernels_glsl import assert_glsl_agrees, lit

    gb0 = _frame(frame)
    gb = GBuffer(depth=gb0.depth, camera=gb0.camera, normals=gb0.normals, object_id=gb0.object_id, light=lit(gb0).light)
    module = _module(model, gb, variant="ssilvb_glsl", indirect=True, slices=3, steps=4)
    with torch.no_grad():
        assert kernel_covers(module, gb) is None
        reference = module(gb)
        out = ssilvb_glsl_hard(gb, gb.view_normals(), slices=3, steps=4, radius=module.radius, indirect=True,
                               **thickness_options(module_thickness(module, gb)), lanes=lanes)
        # the layer matters on this frame: its mean as one scalar gives other masks
        mean = float(_value_map(module, gb)[gb.valid].mean())
        scalar = BitmaskAO(variant="ssilvb_glsl", slices=3, steps=4, thickness=mean, trainable=False)(gb).visibility
    assert (scalar - reference.visibility).abs().max() > 0.02
    assert_glsl_agrees(out, reference, gb.valid, slices=3)


def test_exact_kernel_differentiates_the_nets_offset(built):
    """The net's map is a layer; its additive ``thickness`` is a scalar parameter the exact union's kernel
    differentiates (the net's weights frozen), as the tensor path's autograd does."""
    gb = _frame("rough")
    grads = {}
    for backend in ("torch", "kernel"):
        torch.manual_seed(0)
        module = BitmaskAO(variant="exact", mode="soft", slices=3, steps=4, fetch="bilinear", backend=backend,
                           thickness=NetThickness(scale=1.0, init=0.3, thickness=0.05))
        for name, p in module.named_parameters():
            p.requires_grad_(name in ("radius", "thickness"))
        if backend == "kernel":
            assert exact_soft_covers(module, gb) is None
        vis = module(gb).visibility
        weights = torch.linspace(0.5, 1.5, vis.numel()).view_as(vis)
        grads[backend] = torch.autograd.grad((vis * weights).sum(), [module.radius, module.thickness])
    for kernel, torch_path in zip(grads["kernel"], grads["torch"]):
        assert torch_path.abs() > 1e-2
        assert kernel.item() == pytest.approx(torch_path.item(), rel=1e-4, abs=1e-6)


def test_exact_kernel_differentiates_the_linear_models_slope_and_offset(built):
    """``LinearThickness`` reads the sample's depth: its slope and offset are the kernel's scale and offset,
    differentiated as the tensor path's autograd does (the sample's depth moving with the radius too)."""
    gb = _frame("rough")
    grads = {}
    for backend in ("torch", "kernel"):
        module = BitmaskAO(variant="exact", mode="soft", slices=3, steps=4, fetch="bilinear", backend=backend,
                           thickness=LinearThickness(0.02, 0.15))
        if backend == "kernel":
            assert exact_soft_covers(module, gb) is None
        vis = module(gb).visibility
        weights = torch.linspace(0.5, 1.5, vis.numel()).view_as(vis)
        names = ("radius", "thickness", "thickness_slope")
        grads[backend] = torch.autograd.grad((vis * weights).sum(), [getattr(module, n) for n in names])
    for kernel, torch_path in zip(grads["kernel"], grads["torch"]):
        assert torch_path.abs() > 1e-2
        assert kernel.item() == pytest.approx(torch_path.item(), rel=1e-4, abs=1e-6)


def test_every_models_layer_reads_as_it_says(built):
    gb = _frame("example")
    for model in [*(make(gb) for make in MODELS.values()), ScalarThickness(0.3)]:
        module = BitmaskAO(thickness=model, trainable=False)
        assert module_thickness(module, gb).read == model.kernel_read


def test_coverage_reasons(built):
    gb = _frame("example")
    with torch.no_grad():
        assert kernel_covers(BitmaskAO(thickness=0.3, thickness_growth=0.5, trainable=False), gb) is None
        assert exact_covers(BitmaskAO(variant="exact", thickness=0.3, thickness_growth=0.5, trainable=False), gb) is None
        glsl = BitmaskAO(variant="ssilvb_glsl", thickness=MapThickness(_map(gb)), trainable=False)
        assert kernel_covers(glsl, gb) is None  # (the shader's hitThickness read at each sample's texel)
    # a gradient of the map itself: the exact union's backward scatters it to the layer's taps
    trainable = BitmaskAO(variant="exact", mode="soft", thickness=MapThickness(_map(gb)))
    assert exact_soft_covers(trainable, gb) is None
    with torch.no_grad():
        assert exact_soft_covers(trainable, gb) is None


# ------------------------------------------------------------------ the soft / straight-through kernel with a layer
def _backface(gb: GBuffer) -> GBuffer:
    """``gb`` with a back-face layer: occluders from 0.05 to 0.65 thick in stripes, and a band with no exit."""
    back = gb.depth + _map(gb)
    back[..., : gb.depth.shape[-1] // 6] = torch.inf  # (the layer is BACKFACE_CAP thick there)
    return GBuffer(depth=gb.depth, camera=gb.camera, normals=gb.normals, backface_depth=back)


SOFT_LAYERS = {  # model -> (its thickness, the parameters the fit moves)
    "backface": (lambda: BackfaceThickness(0.8, 0.1), ("radius", "thickness_scale", "thickness")),
    "linear": (lambda: LinearThickness(0.02, 0.15), ("radius", "thickness_slope", "thickness")),
}
SOFT_SETTINGS = [
    dict(mode="soft", slices=3, steps=4, weighting="cosine", fetch="edge_aware"),  # the sectors and fetch of torch-ao fit's default pipeline
    dict(mode="soft", slices=2, steps=3, tau=0.1, border="clamp"),
    dict(mode="straight_through", slices=3, steps=3, weighting="cosine", fetch="bilinear"),
    dict(mode="soft", slices=2, steps=4, fetch="nearest", rounding="round"),
]


def _soft_kernel(module, gb: GBuffer, lanes: str, names):
    """The soft walk in ``lanes`` with ``module``'s options and thickness model, and the gradients of a weighted
    sum of its visibility with respect to ``names``."""
    form = module_thickness(module, gb)
    vis = bitmask_soft(gb, gb.view_normals(), slices=module.slices, steps=module.steps, radius=module.radius,
                       thickness=form.offset, layer=form.layer, layer_scale=form.scale, thickness_read=form.read,
                       tau=module.tau, weighting=module.weighting, straight_through=module.mode != "soft",
                       min_step_px=module.min_step_px, fetch=module.fetch, border=module.border,
                       rounding=module.rounding, sector_epsilon=module.sector_epsilon, azimuth=module.azimuth,
                       variant=module.variant, lanes=lanes)
    weights = torch.linspace(0.5, 1.5, vis.numel(), dtype=vis.dtype).view_as(vis)
    grads = torch.autograd.grad((vis * weights).sum(), [getattr(module, n) for n in names], allow_unused=True)
    return vis.detach(), [torch.zeros(()) if g is None else g for g in grads]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(SOFT_SETTINGS)))
@pytest.mark.parametrize("model", sorted(SOFT_LAYERS))
def test_soft_kernel_reads_the_layer_and_differentiates_its_scale_as_the_float64_tensor_walk(built, model, setting,
                                                                                              lanes):
    """Values within 1e-5 (a straight-through forward: within one sector of one slice) and the gradients of the
    radius, the model's scale and offset within 1e-4 relative of the float64 tensor walk's autograd."""
    assert_layer_agrees(model, SOFT_SETTINGS[setting], lanes)


def assert_layer_agrees(model: str, settings: dict, lanes: str) -> dict:
    """The soft kernel with thickness model ``model`` (SOFT_LAYERS) in ``lanes``: values and the gradients of the
    model's parameters against the float64 tensor walk's (the tolerances of the test above); the largest errors
    measured (value, relative gradients)."""
    gb = _backface(FRAMES["rough"]())
    make, names = SOFT_LAYERS[model]
    reference = BitmaskAO(thickness=make(), backend="torch", **settings).double()
    g64 = gb.to(dtype=torch.float64)
    want = reference(g64).visibility
    weights = torch.linspace(0.5, 1.5, want.numel(), dtype=want.dtype).view_as(want)
    want_grads = [torch.zeros(()) if g is None else g for g in
                  torch.autograd.grad((want * weights).sum(), [getattr(reference, n) for n in names], allow_unused=True)]
    module = BitmaskAO(thickness=make(), backend="kernel", **settings)
    assert soft_module.kernel_covers(module, gb) is None
    got, got_grads = _soft_kernel(module, gb, lanes, names)
    assert want.min() < 0.9
    if settings["mode"] == "soft":
        assert (got.double() - want.detach()).abs().max() <= 1e-5
    else:
        assert_values_agree(got.double(), want.detach(), gb.valid, bound=math.pi / 2 / (32 * settings["slices"]) + 1e-6)
    for name, g, w in zip(names, got_grads, want_grads):
        assert abs(float(w)) > 1e-3 or (name == "radius" and settings["fetch"] == "nearest"), (name, float(w))
        assert abs(float(g) - float(w)) <= 1e-4 * abs(float(w)) + 1e-6, (name, float(g), float(w))
    return {"value": float((got.double() - want.detach()).abs().max()),
            **{name: abs(float(g) - float(w)) / max(abs(float(w)), 1e-30) for name, g, w in zip(names, got_grads, want_grads)}}


def test_soft_kernel_layer_matters_and_its_scale_gradient_matches_finite_differences(built):
    """The back-face layer changes the soft visibility against its mean as one scalar, and the kernel's
    d loss / d thickness_scale is the central difference of its own loss."""
    gb = _backface(FRAMES["example"]())
    module = BitmaskAO(thickness=BackfaceThickness(0.8, 0.1), mode="soft", slices=3, steps=4, weighting="cosine",
                       fetch="edge_aware", backend="kernel")
    vis = module(gb).visibility
    weights = torch.linspace(0.5, 1.5, vis.numel()).view_as(vis)
    (g,) = torch.autograd.grad((vis * weights).sum(), [module.thickness_scale])
    h = 1e-2
    with torch.no_grad():
        mean = float((module_thickness(module, gb).layer * 0.8 + 0.1)[gb.valid].clamp(max=10).mean())
        scalar = BitmaskAO(thickness=mean, mode="soft", slices=3, steps=4, weighting="cosine", fetch="edge_aware")(gb)
        assert (scalar.visibility - vis).abs().max() > 0.02
        losses = []
        for sign in (1, -1):
            module.thickness_scale.fill_(0.8 + sign * h)
            losses.append(float((module(gb).visibility.double() * weights).sum()))
    assert abs(float(g)) > 1e-2
    assert float(g) == pytest.approx((losses[0] - losses[1]) / (2 * h), rel=2e-2)


SOFT_GBUFFER_MODELS = {  # model -> (its thickness for a frame, the parameters the fit moves)
    **{model: (lambda gb, make=make: make(), names) for model, (make, names) in SOFT_LAYERS.items()},
    "net": (lambda gb: NetThickness(scale=1.0, init=0.3, thickness=0.05), ("radius", "thickness")),
    "map": (lambda gb: MapThickness(_map(gb)), ("radius", "thickness")),
    "object": (lambda gb: ObjectThickness(torch.tensor([0.05, 0.8])), ("radius", "thickness")),
}


def _soft_gbuffer_grads(model: str, settings: dict, dtype: torch.dtype, lanes: str | None):
    """The visibility and the gradients of a weighted sum of it with respect to depth, normals, the back-face depth,
    the model's parameters and (the net) its weights: the tensor walk in ``dtype`` (``lanes=None``) or the soft
    kernel (float32) in ``lanes``."""
    gb0 = _backface(_frame("rough")).to(dtype=dtype)
    depth = gb0.depth.detach().clone().requires_grad_()
    normals = gb0.view_normals().detach().clone().requires_grad_()
    back = gb0.backface_depth.detach().clone().requires_grad_()
    gb = GBuffer(depth=depth, normals=normals, camera=gb0.camera, backface_depth=back, object_id=_frame("rough").object_id)
    make, names = SOFT_GBUFFER_MODELS[model]
    torch.manual_seed(0)  # (the net's initial weights)
    module = BitmaskAO(thickness=make(gb0), backend="torch", **settings).to(dtype)
    if lanes is None:
        vis = module(gb).visibility
    else:
        assert soft_module.kernel_covers(module, gb) is None
        form = module_thickness(module, gb)
        vis = bitmask_soft(gb, normals, slices=module.slices, steps=module.steps, radius=module.radius,
                           thickness=form.offset, layer=form.layer, layer_scale=form.scale, thickness_read=form.read,
                           tau=module.tau, weighting=module.weighting, straight_through=module.mode != "soft",
                           min_step_px=module.min_step_px, fetch=module.fetch, border=module.border,
                           rounding=module.rounding, sector_epsilon=module.sector_epsilon, azimuth=module.azimuth,
                           variant=module.variant, lanes=lanes)
    weights = torch.linspace(0.5, 1.5, vis.numel(), dtype=dtype).view_as(vis)
    leaves = {"depth": depth, "normals": normals, "backface_depth": back,
              **{n: getattr(module, n) for n in names},
              **{n: p for n, p in module.named_parameters() if n.startswith("thickness_net")}}
    grads = torch.autograd.grad((vis * weights).sum(), list(leaves.values()), allow_unused=True)
    return vis.detach().double(), {n: torch.zeros(()) if g is None else g.double() for n, g in zip(leaves, grads)}


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", [0, 2])
@pytest.mark.parametrize("model", sorted(SOFT_GBUFFER_MODELS))
def test_soft_kernel_differentiates_the_gbuffer_and_the_layer_as_the_float64_tensor_walk(built, model, setting,
                                                                                          lanes):
    """With a thickness model that reads a layer (the back-face depth's, the net's map, a map, a per-object table
    at the first tap) or the sample's depth, the soft kernel's G-buffer backward: d / d depth, normals and the
    back-face depth, the model's parameters (the map and the table themselves) and the net's weights within 1e-4
    relative of the float64 tensor walk's autograd (soft, and straight-through: the soft union's gradients)."""
    assert_layer_gbuffer_gradients_agree(model, SOFT_SETTINGS[setting], lanes)


def assert_layer_gbuffer_gradients_agree(model: str, settings: dict, lanes: str) -> dict:
    """The soft kernel's G-buffer backward with thickness model ``model`` (SOFT_GBUFFER_MODELS) in ``lanes`` against
    the float64 tensor walk's autograd (the tolerances of the test above); the largest relative errors measured."""
    want_vis, want = _soft_gbuffer_grads(model, settings, torch.float64, None)
    got_vis, got = _soft_gbuffer_grads(model, settings, torch.float32, lanes)
    if settings["mode"] == "soft":
        assert (got_vis - want_vis).abs().max() <= 1e-5
    errors = {"value": float((got_vis - want_vis).abs().max())}
    for name, w in want.items():
        g = got[name]
        finite = torch.isfinite(w)
        if w[finite].abs().max() == 0:  # only the back-face model reads the back-face depth; the untrained net's
            # hidden layers feed a head whose weights start at 0
            assert (name == "backface_depth" and model != "backface") or name.startswith("thickness_net_body"), name
            assert g.abs().max() == 0, name
            continue
        assert w[finite].abs().max() > 1e-4, name  # (each gradient means something)
        error = float((g - w)[finite].norm() / w[finite].norm())
        assert error <= 1e-4, (name, error)
        errors[name] = error
    return errors


def test_soft_kernel_gbuffer_gradients_with_a_layer_match_finite_differences(built):
    """The back-face model's soft kernel: d loss / d the back-face depth along a random direction against the
    central difference of the kernel's own loss (float64 sums of a float32 walk; h = 1e-3 world units)."""
    gb = _backface(FRAMES["example"]())
    finite = torch.isfinite(gb.backface_depth)
    direction = torch.where(finite, torch.rand(gb.depth.shape, generator=torch.Generator().manual_seed(5)), 0.0)
    module = BitmaskAO(thickness=BackfaceThickness(0.8, 0.1), mode="soft", slices=3, steps=4, weighting="cosine",
                       fetch="edge_aware", backend="kernel")

    def loss(back):
        vis = module(GBuffer(depth=gb.depth, camera=gb.camera, backface_depth=back)).visibility
        return (vis.double() * torch.linspace(0.5, 1.5, vis.numel(), dtype=torch.float64).view_as(vis)).sum()

    back = gb.backface_depth.clone().requires_grad_()
    (g,) = torch.autograd.grad(loss(back), [back])
    h = 1e-3
    with torch.no_grad():
        difference = (loss(gb.backface_depth + h * direction) - loss(gb.backface_depth - h * direction)) / (2 * h)
    along = float((torch.where(finite, g, 0.0).double() * direction).sum())
    assert abs(along) > 1e-2
    assert along == pytest.approx(float(difference), rel=2e-2)


@pytest.mark.parametrize("variant, mode", [("default", "hard"), ("exact", "hard"), ("default", "soft")])
def test_a_batch_with_a_layer_and_edge_aware_fetch_is_its_images_walked_one_by_one(built, variant, mode):
    """The CPU operators prepare one image of every batch element's inverse depth, layer and cell flags
    (frame_cpu.h's fetch_texels); the second element's walk reads its own part of it."""
    from torch_ao.examples import example_gbuffer

    gb = example_gbuffer(40, 64)
    other = gb.depth * 1.07 + 0.05 * torch.sin(torch.arange(64.0)).view(1, 1, 1, 64)
    one = [GBuffer(depth=d, camera=gb.camera, normals=gb.normals, backface_depth=d + t)
           for d, t in ((gb.depth, 0.3), (other, 0.2))]
    both = GBuffer(depth=torch.cat([gb.depth, other]), camera=gb.camera, normals=torch.cat([gb.normals] * 2),
                   backface_depth=torch.cat([gb.depth + 0.3, other + 0.2]))
    module = BitmaskAO(variant=variant, mode=mode, thickness=BackfaceThickness(), fetch="edge_aware",
                       backend="kernel", slices=3, steps=4)
    with torch.no_grad():
        separate = torch.cat([module(g).visibility for g in one])
        batched = module(both).visibility
    assert batched.shape == (2, 1, 40, 64)
    # the two images differ, so a batch element reading another's texels would be far off
    assert (separate[0] - separate[1]).abs().max() > 0.05
    assert (batched - separate).abs().max() <= 1e-6
