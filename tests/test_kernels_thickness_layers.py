"""Thickness models the kernels read as ``ThicknessLayer`` (``t = scale * value + offset`` at a sample, the
value a layer read as depth is, a layer at the first tap, or the sample's depth): a map, the net's map, a
per-object table and the linear model, in the ``"default"`` variant's hard kernel, the exact
union's hard kernel and its kernel with gradients, against the tensor-op walk by the tolerance of
tests/kernel_agreement.py, in SIMD and scalar lanes."""
import pytest
import torch

from kernel_agreement import assert_masks_agree, assert_values_agree
from test_kernels import FRAMES, built, pytestmark  # noqa: F401  (built: the fixture)
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import exact_covers, kernel_covers, kernel_forward
from torch_ao.kernels.bitmask import bitmask_outputs, exact_hard, module_thickness, thickness_options
from torch_ao.kernels.soft_exact import exact_soft_covers
from torch_ao.methods.bitmask import BitmaskAO
from torch_ao.thickness import LinearThickness, MapThickness, NetThickness, ObjectThickness, ScalarThickness


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
        assert "growth" in kernel_covers(BitmaskAO(thickness=0.3, thickness_growth=0.5, trainable=False), gb)
        glsl = BitmaskAO(variant="ssilvb_glsl", thickness=MapThickness(_map(gb)), trainable=False)
        assert "reads one scalar thickness" in kernel_covers(glsl, gb)
    # a gradient of the map itself: the exact union's backward scatters it to the layer's taps
    trainable = BitmaskAO(variant="exact", mode="soft", thickness=MapThickness(_map(gb)))
    assert exact_soft_covers(trainable, gb) is None
    with torch.no_grad():
        assert exact_soft_covers(trainable, gb) is None
