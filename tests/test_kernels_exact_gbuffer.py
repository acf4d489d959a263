"""The exact union's G-buffer gradients (walk_grad.h's exact_grad_block: ``torch_ao_kernels::exact_backward``, the
union's adjoint by hand and the intervals replayed in dual lanes) against the tensor-op walk's autograd: values
within 1e-5 of the float64 walk, gradients of depth, normals, the back-face depth, a position buffer, a thickness
map and the scalars within 1e-4 relative, in SIMD and scalar lanes; directional derivatives against central
differences of the float64 walk; what it covers.

The comparisons run on the rough frame. On the planar frames (a floor, a crease) with ``sector_epsilon=0`` most
samples lie on the pixel's own plane, where an interval's width is zero give or take rounding: there the float32
tensor walk itself is 2-60 % (relative) off the float64 walk's depth gradient, and the kernel as far."""
import pytest
import torch

from kernel_agreement import position_gradients, relative_error, use_scalar_lanes
from kernel_calls import on_threads
from test_kernels import FRAMES, built, pytestmark, rough_gbuffer  # noqa: F401 (the fixture, the skip)
from test_kernels_soft_exact import SETTINGS
from torch_ao.camera import PinholeCamera
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import dispatch
from torch_ao.kernels.soft_exact import exact_soft_covers
from torch_ao.methods.bitmask import BitmaskAO
from torch_ao.thickness import BackfaceThickness, LinearThickness


def _weights(vis: torch.Tensor) -> torch.Tensor:
    """Upstream weights that differ per pixel, so that every pixel's gradient counts differently."""
    return torch.linspace(0.5, 1.5, vis.numel(), dtype=vis.dtype).view_as(vis)


def _scalar_names(module: BitmaskAO) -> list[str]:
    return ["radius", "thickness"] + [n for n in ("thickness_scale", "thickness_growth")
                                      if isinstance(getattr(module, n, None), torch.Tensor)]


def values_and_grads(gb0: GBuffer, dtype: torch.dtype, backend: str, setting: dict):
    """Visibility, and the gradients of a weighted sum of it with respect to depth, normals, the back-face depth
    (``None`` where the model reads no layer) and the module's scalars (by name)."""
    gb0 = gb0.to(dtype=dtype)
    depth = gb0.depth.detach().clone().requires_grad_()
    normals = gb0.view_normals().detach().clone().requires_grad_()
    back = (gb0.depth.detach() * 1.3).requires_grad_()
    gb = GBuffer(depth=depth, normals=normals, camera=gb0.camera, backface_depth=back)
    module = BitmaskAO(variant="exact", backend=backend, **{"mode": "soft", **setting}).to(dtype)
    if backend == "kernel":
        assert exact_soft_covers(module, gb) is None
    vis = module(gb).visibility
    names = _scalar_names(module)
    grads = torch.autograd.grad((vis * _weights(vis)).sum(), [depth, normals, back, *(getattr(module, n) for n in names)],
                                allow_unused=True)
    grads = [None if g is None else g.double() for g in grads]
    return vis.detach().double(), grads[:3], dict(zip(names, grads[3:]))


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_gbuffer_gradients_equal_the_float64_tensor_walk(built, setting, lanes, monkeypatch):
    """The settings of test_kernels_soft_exact: the variant's defaults (cosine, along the ray, clipped, sphere
    extent, edge-aware), the back-face model, uniform sectors along the view without clipping (bilinear, clamped
    border), the nearest fetch without jitter, the Hilbert-indexed R2 noise with staggered steps and a sector
    margin (straight-through mode). Measured: up to 1.1e-5 relative (depth), 5e-6 (values)."""
    if lanes == "scalar":  # the CUDA thread's walk (what tao_exact_backward compiles), on the CPU
        import torch_ao.kernels.soft_exact as soft_exact
        use_scalar_lanes(monkeypatch, soft_exact)
    gb = FRAMES["rough"]()
    settings = SETTINGS[setting]
    ref, (ref_depth, ref_normals, ref_back), ref_scalars = values_and_grads(gb, torch.float64, "torch", settings)
    out, (depth, normals, back), scalars = values_and_grads(gb, torch.float32, "kernel", settings)
    assert ref.min() < 0.9 and ref_depth.abs().sum() > 0 and ref_normals.abs().sum() > 0
    assert (out - ref).abs().max() <= 1e-5
    assert relative_error(depth, ref_depth) <= 1e-4
    assert relative_error(normals, ref_normals) <= 1e-4
    if isinstance(settings.get("thickness"), BackfaceThickness):  # the layer back - depth reaches both
        assert ref_back.abs().sum() > 0 and relative_error(back, ref_back) <= 1e-4
    else:
        assert back is None and ref_back is None
    for name, want in ref_scalars.items():
        assert abs(float(scalars[name] - want)) <= 1e-4 * abs(float(want)) + 1e-6, (name, scalars[name], want)


@pytest.mark.parametrize("thickness", ["map", "linear"])
def test_a_thickness_map_and_the_linear_models_slope_get_their_gradients(built, thickness):
    """A per-pixel map (a parameter read as a layer: its gradient is the taps' scatter) and LinearThickness (the
    sample's depth, times the slope) with depth gradients, against the float64 tensor walk."""
    gb0 = FRAMES["rough"]()
    values = 0.1 + 0.4 * torch.rand(gb0.depth.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    results = []
    for dtype, backend in ((torch.float64, "torch"), (torch.float32, "kernel")):
        gb = gb0.to(dtype=dtype)
        depth = gb.depth.detach().clone().requires_grad_()
        model = values.to(dtype) if thickness == "map" else LinearThickness(0.1, 0.2)
        module = BitmaskAO(variant="exact", mode="soft", slices=3, steps=4, thickness=model, backend=backend).to(dtype)
        frame = GBuffer(depth=depth, camera=gb.camera)
        vis = module(frame).visibility
        leaves = [depth, module.thickness] + ([module.thickness_slope] if thickness == "linear" else [])
        results.append([g.double() for g in torch.autograd.grad((vis * _weights(vis)).sum(), leaves)])
    ref, got = results
    for g, r in zip(got, ref):
        assert r.abs().sum() > 0
        assert relative_error(g, r) <= 1e-4


def test_position_buffer_gradient_equals_the_tensor_walk(built):
    """A position buffer read by the nearest fetch: its gradient reaches the buffer (the pixels' own positions and
    the taps')."""
    def loss(gb, dtype, backend):
        module = BitmaskAO(variant="exact", mode="soft", slices=3, steps=4, fetch="nearest", border="clamp",
                           backend=backend).to(dtype)
        vis = module(gb).visibility
        return (vis * _weights(vis)).sum()

    grads = position_gradients(FRAMES["rough"](), loss)
    assert grads[0].abs().sum() > 0
    assert relative_error(grads[1], grads[0]) <= 1e-4


def test_gradients_match_central_differences(built):
    """gradcheck's fast mode by hand: the kernel's derivative along random directions of depth, normals and the
    back-face depth against central differences (eps = 1e-6) of the float64 tensor-op forward, on a small rough
    frame (clamped borders and the bilinear fetch: a dropped sample or an edge-aware switch is a step in the
    forward). The exact union is piecewise smooth: the directions stay within one piece at this eps."""
    gb0 = rough_gbuffer(28, 40, seed=4)
    settings = dict(slices=2, steps=4, radius=0.8, border="clamp", fetch="bilinear", thickness=BackfaceThickness(0.9))
    back0 = gb0.depth * 1.25

    def tensor_walk(depth, normals, back):
        gb = GBuffer(depth=depth, normals=normals, camera=gb0.camera.to(dtype=torch.float64), backface_depth=back)
        return BitmaskAO(variant="exact", mode="soft", backend="torch", **settings).double()(gb).visibility

    leaves = [gb0.depth.detach().clone().requires_grad_(), gb0.view_normals().detach().clone().requires_grad_(),
              back0.detach().clone().requires_grad_()]
    module = BitmaskAO(variant="exact", mode="soft", backend="kernel", **settings)
    vis = module(GBuffer(depth=leaves[0], normals=leaves[1], camera=gb0.camera, backface_depth=leaves[2])).visibility
    weights = _weights(vis).double()
    grads = torch.autograd.grad((vis * weights.float()).sum(), leaves)
    g = torch.Generator().manual_seed(1)
    eps = 1e-6
    surface = torch.isfinite(gb0.depth) & (gb0.depth > 0)  # (background stays background)
    for _ in range(4):
        directions = [torch.where(surface, torch.randn(x.shape, generator=g, dtype=torch.float64), 0.0) for x in leaves]
        with torch.no_grad():
            base = [x.detach().double() for x in leaves]
            loss = lambda t: float((tensor_walk(*(b + t * u for b, u in zip(base, directions))) * weights).sum())  # noqa: E731
            numerical = (loss(eps) - loss(-eps)) / (2 * eps)
        terms = torch.cat([(gr.double() * u)[torch.isfinite(gr)].flatten() for gr, u in zip(grads, directions)])
        analytical, scale = float(terms.sum()), float(terms.abs().sum())  # (the sum cancels: relative to its terms)
        assert abs(numerical) > 1e-2
        assert abs(analytical - numerical) <= 1e-4 * scale, (analytical, numerical, scale)


def _intrinsics_grads(dtype: torch.dtype, backend: str, setting: dict):
    """d(weighted visibility)/d(depth, the intrinsics (B, 3, 3), radius) on the rough frame in ``dtype``."""
    gb0 = FRAMES["rough"]().to(dtype=dtype)
    depth = gb0.depth.detach().clone().requires_grad_()
    intrinsics = gb0.camera.intrinsics.detach().clone().requires_grad_()
    gb = GBuffer(depth=depth, normals=gb0.view_normals().detach(), backface_depth=gb0.depth.detach() * 1.3,
                 camera=PinholeCamera(intrinsics, gb0.camera.height, gb0.camera.width))
    module = BitmaskAO(variant="exact", backend=backend, **{"mode": "soft", **setting}).to(dtype)
    if backend == "kernel":
        assert exact_soft_covers(module, gb) is None
    vis = module(gb).visibility
    grads = torch.autograd.grad((vis * _weights(vis)).sum(), [depth, intrinsics, module.radius])
    return [g.double() for g in grads]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", [0, 1, 2])
def test_intrinsics_gradients_equal_the_float64_tensor_walk(built, setting, lanes, monkeypatch):
    """The intrinsics reach the walk through the positions (autograd of walk_inputs) and in the kernel: each
    replayed sample's place on screen (the slice's screen motion: walk.h's PlacementAdjoint) and a bilinear fetch's
    unprojection (unprojection_camera), chained by hand. Their sum per image and the depth's and radius' gradients
    beside it, within 1e-4 relative of the float64 tensor walk (the variant's defaults; the back-face model; uniform
    sectors along the view without clipping, bilinear, clamped border)."""
    if lanes == "scalar":
        import torch_ao.kernels.soft_exact as soft_exact
        use_scalar_lanes(monkeypatch, soft_exact)
    ref_depth, ref_intrinsics, ref_radius = _intrinsics_grads(torch.float64, "torch", SETTINGS[setting])
    depth, intrinsics, radius = _intrinsics_grads(torch.float32, "kernel", SETTINGS[setting])
    assert ref_intrinsics.abs().max() > 1e-3
    assert relative_error(intrinsics, ref_intrinsics) <= 1e-4
    assert relative_error(depth, ref_depth) <= 1e-4
    assert abs(float(radius - ref_radius)) <= 1e-4 * abs(float(ref_radius))


# ------------------------------------------------------------------------------- what it covers
def test_the_auto_backend_takes_the_kernel_for_gbuffer_and_intrinsics_gradients(built, monkeypatch):
    gb = FRAMES["rough"]()
    depth = gb.depth.clone().requires_grad_()
    graph = GBuffer(depth=depth, camera=gb.camera, backface_depth=gb.depth * 1.3)
    calls = []
    entries = list(dispatch.KERNELS["bitmask"])
    index = next(i for i, (covers, _) in enumerate(entries) if covers is exact_soft_covers)
    run = entries[index][1]
    entries[index] = (exact_soft_covers, lambda *a: calls.append(1) or run(*a))
    monkeypatch.setitem(dispatch.KERNELS, "bitmask", tuple(entries))
    module = BitmaskAO(variant="exact", thickness=BackfaceThickness(), slices=2, steps=3)  # (hard mode: the default)
    (g_depth,) = torch.autograd.grad(module(graph).visibility.sum(), [depth])
    assert calls == [1] and g_depth[torch.isfinite(g_depth)].abs().sum() > 0
    intrinsics = gb.camera.intrinsics.clone().requires_grad_()
    moving = GBuffer(depth=gb.depth, camera=PinholeCamera(intrinsics, gb.camera.height, gb.camera.width),
                     backface_depth=gb.depth * 1.3)
    assert exact_soft_covers(module, moving) is None
    (g_fx,) = torch.autograd.grad(module(moving).visibility.sum(), [intrinsics])  # (the kernel)
    assert calls == [1, 1] and g_fx.abs().sum() > 0


def test_gbuffer_gradients_on_two_threads_equal_one_thread(built):
    """The taps' gradients go to per-thread images summed after the rows: the same gradients on any number of
    threads, up to the order of the float32 sums."""
    gb = FRAMES["rough"]()
    (vis1, grads1, _), (vis2, grads2, _) = on_threads(lambda: values_and_grads(gb, torch.float32, "kernel", SETTINGS[1]))
    assert torch.equal(vis1, vis2)
    for a, b in zip(grads1, grads2):
        assert relative_error(b, a) <= 1e-6
