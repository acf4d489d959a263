"""The soft / straight-through kernel's G-buffer gradients (walk_grad_cpu.cpp's soft_backward: the walk with
soft.h's end_slice_adjoint) against the tensor-op walk's autograd in float64: values within 1e-5, gradients of
depth, normals, a position buffer, radius and thickness within 1e-4 relative, in SIMD and scalar lanes; directional
derivatives against central differences (gradcheck's fast mode); what it covers."""
import pytest
import torch

from kernel_agreement import position_gradients, relative_error, use_scalar_lanes
from kernel_calls import count_kernel_calls, on_threads
from test_kernels import FRAMES, built, pytestmark  # noqa: F401 (the fixture, the skip)
from test_kernels_soft import SETTINGS, _loss_weights
from torch_ao.camera import PinholeCamera
from torch_ao.examples import example_gbuffer, floor_wall_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import bitmask_soft
import torch_ao.kernels.soft_bitmask as soft_module
from torch_ao.methods.bitmask import BitmaskAO


def _soft(gb: GBuffer, normals: torch.Tensor, m: BitmaskAO, lanes: str) -> torch.Tensor:
    """The kernel's visibility with ``m``'s options (its radius and thickness parameters)."""
    return bitmask_soft(gb, normals, slices=m.slices, steps=m.steps, radius=m.radius, thickness=m.thickness,
                        tau=m.tau, weighting=m.weighting, straight_through=m.mode != "soft", step_power=m.step_power,
                        min_step_px=m.min_step_px, jitter=m.jitter, seed=m.seed, noise=m.noise, stagger=m.stagger,
                        fetch=m.fetch, border=m.border, rounding=m.rounding, sector_epsilon=m.sector_epsilon, azimuth=m.azimuth,
                        variant=m.variant, lanes=lanes)


def _values_and_grads(gb0: GBuffer, dtype: torch.dtype, lanes: str | None, settings: dict):
    """Visibility and d(weighted visibility)/d(depth, normals, radius, thickness): the tensor path in
    ``dtype`` (``lanes=None``) or the kernel (float32) in ``lanes``."""
    gb0 = gb0.to(dtype=dtype)
    depth = gb0.depth.detach().clone().requires_grad_()
    normals = gb0.view_normals().detach().clone().requires_grad_()
    gb = GBuffer(depth=depth, normals=normals, camera=gb0.camera)
    module = BitmaskAO(backend="torch", **settings).to(dtype)
    vis = module(gb).visibility if lanes is None else _soft(gb, normals, module, lanes)
    grads = torch.autograd.grad((vis * _loss_weights(vis).to(dtype)).sum(),
                                [depth, normals, module.radius, module.thickness], allow_unused=True)
    return vis.detach().double(), [None if g is None else g.double() for g in grads]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", [0, 1, 2, 4, 5, 6, 7, 10])
def test_gbuffer_gradients_equal_the_float64_tensor_walk(built, lanes, setting):
    """Soft and straight-through, uniform and cosine, every fetch (the edge-aware one's taps switch to the nearest
    texel's across depth edges: most of the rough frame's cells are one surface, about a fifth are not),
    dropped and clamped borders, the Hilbert-indexed R2 noise with staggered steps (the settings of test_kernels_soft; setting 3, without jitter, puts steps on texel boundaries, where float32
    and float64 floor differently: the float32 test below covers it). Measured: up to 9e-5 relative in the
    depth's gradient at tau = 0.1 (float32 against float64; 1/tau^2 terms)."""
    assert_gbuffer_gradients_agree(FRAMES["rough"](), SETTINGS[setting], lanes)


def assert_gbuffer_gradients_agree(gb: GBuffer, settings: dict, lanes: str) -> dict:
    """The kernel's values and gradients of depth, normals, radius and thickness in ``lanes`` against the float64
    tensor walk's (the tolerances of the test above); the largest errors measured (value, relative gradients)."""
    reference, (ref_depth, ref_normals, ref_radius, ref_thickness) = _values_and_grads(gb, torch.float64, None,
                                                                                       settings)
    out, (depth, normals, radius, thickness) = _values_and_grads(gb, torch.float32, lanes, settings)
    assert reference.min() < 1 and ref_depth.abs().sum() > 0 and ref_normals.abs().sum() > 0
    assert (out - reference).abs().max() <= 1e-5
    assert relative_error(depth, ref_depth) <= 1e-4
    assert relative_error(normals, ref_normals) <= 1e-4
    assert abs(float(thickness - ref_thickness)) <= 1e-4 * abs(float(ref_thickness))
    if ref_radius is None:  # a nearest fetch does not move with the radius: Euler's identity gives ~0
        assert settings.get("fetch") == "nearest"
        assert abs(float(radius)) <= 1e-4 * abs(float(ref_thickness))
    else:
        assert ref_radius != 0
        assert abs(float(radius - ref_radius)) <= 1e-4 * abs(float(ref_radius))
    return {"value": float((out - reference).abs().max()), "depth": relative_error(depth, ref_depth),
            "normals": relative_error(normals, ref_normals),
            "thickness": abs(float(thickness - ref_thickness)) / abs(float(ref_thickness)),
            "radius": 0.0 if ref_radius is None else abs(float(radius - ref_radius)) / abs(float(ref_radius))}


@pytest.mark.parametrize("setting", [3, 8])
def test_gbuffer_gradients_equal_the_float32_tensor_walk(built, setting):
    gb = FRAMES["rough"]()
    settings = SETTINGS[setting]
    reference, ref = _values_and_grads(gb, torch.float32, None, settings)
    out, got = _values_and_grads(gb, torch.float32, "simd", settings)
    assert (out - reference).abs().max() <= 1e-5
    for g, r in zip(got[:2], ref[:2]):
        assert relative_error(g, r) <= 1e-4
    for g, r in zip(got[2:], ref[2:]):
        assert abs(float(g - r)) <= 1e-4 * abs(float(r))


def test_position_buffer_gradient_equals_the_tensor_walk(built):
    """A position buffer read by the nearest fetch: its gradient reaches the buffer (the pixels' own and
    the taps' positions)."""
    settings = dict(mode="soft", slices=3, steps=4, fetch="nearest", border="clamp", tau=0.3)

    def loss(gb, dtype, backend):
        module = BitmaskAO(backend="torch", **settings).to(dtype)
        vis = module(gb).visibility if backend == "torch" else _soft(gb, gb.normals, module, "simd")
        return (vis * _loss_weights(vis).to(dtype)).sum()

    grads = position_gradients(FRAMES["rough"](), loss)
    assert grads[0].abs().sum() > 0
    assert relative_error(grads[1], grads[0]) <= 1e-4


@pytest.mark.parametrize("mode", ["soft", "straight_through"])
def test_gradients_match_central_differences_on_a_small_frame(built, mode):
    """gradcheck's fast mode by hand: the kernel's derivative along random directions of depth and normals
    against central differences (eps = 1e-6) of the float64 tensor-op forward, on an 8x10 frame (a floor
    meeting a wall, clamped borders: a dropped sample is a step in the forward). The float32 kernel's own
    differences cannot be taken that close, and farther out (eps >= 1e-4) the bilinear fetch's kinks at
    texel edges (its slope jumps there) enter them. Straight-through: the soft union's gradient, so the
    differences are those of the soft forward."""
    assert_central_differences(floor_wall_gbuffer(8, 10, wall_distance=1.0)[0], mode, {})


def assert_central_differences(gb0: GBuffer, mode: str, options: dict) -> None:
    """The check of the test above on frame ``gb0`` for ``BitmaskAO(mode=mode, **options)`` (its settings beside
    them)."""
    settings = dict(slices=2, steps=3, tau=0.5, border="clamp", radius=0.8, thickness=0.4, **options)

    def tensor_walk(depth, normals):
        gb = GBuffer(depth=depth, normals=normals, camera=gb0.camera.to(dtype=torch.float64))
        return BitmaskAO(backend="torch", mode="soft", **settings).double()(gb).visibility

    depth = gb0.depth.detach().clone().requires_grad_()
    normals = gb0.view_normals().detach().clone().requires_grad_()
    module = BitmaskAO(mode=mode, **settings)
    vis = _soft(GBuffer(depth=depth, normals=normals, camera=gb0.camera), normals, module, "simd")
    weights = _loss_weights(vis).double()
    g_depth, g_normals = torch.autograd.grad((vis * weights.float()).sum(), [depth, normals])
    eps = 1e-6
    g = torch.Generator().manual_seed(1)
    for _ in range(4):
        u_depth = torch.randn(depth.shape, generator=g, dtype=torch.float64)
        u_normals = torch.randn(normals.shape, generator=g, dtype=torch.float64)
        with torch.no_grad():
            d64, n64 = depth.double(), normals.double()
            loss = lambda t: float((tensor_walk(d64 + t * u_depth, n64 + t * u_normals) * weights).sum())  # noqa: E731
            numerical = (loss(eps) - loss(-eps)) / (2 * eps)
        terms = torch.cat(((g_depth.double() * u_depth).flatten(), (g_normals.double() * u_normals).flatten()))
        terms = terms[torch.isfinite(terms)]  # (a frame's background: no gradient)
        analytical, scale = float(terms.sum()), float(terms.abs().sum())  # (the sum cancels: relative to its terms)
        assert abs(numerical) > 1e-2
        assert abs(analytical - numerical) <= 1e-4 * scale, (analytical, numerical, scale)


def _intrinsics_grads(gb0: GBuffer, dtype: torch.dtype, lanes: str | None, settings: dict):
    """d(weighted visibility)/d(depth, the intrinsics (B, 4), radius): the tensor path in ``dtype``
    (``lanes=None``) or the kernel (float32) in ``lanes``."""
    gb0 = gb0.to(dtype=dtype)
    depth = gb0.depth.detach().clone().requires_grad_()
    intrinsics = gb0.camera.intrinsics.detach().clone().requires_grad_()
    gb = GBuffer(depth=depth, normals=gb0.view_normals().detach(),
                 camera=PinholeCamera(intrinsics, gb0.camera.height, gb0.camera.width))
    module = BitmaskAO(backend="torch", **settings).to(dtype)
    vis = module(gb).visibility if lanes is None else _soft(gb, gb.normals, module, lanes)
    grads = torch.autograd.grad((vis * _loss_weights(vis).to(dtype)).sum(), [depth, intrinsics, module.radius],
                                allow_unused=True)  # (a nearest fetch does not move with the radius)
    return [torch.zeros((), dtype=torch.float64) if g is None else g.double() for g in grads]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", [0, 2, 4, 5, 7])
def test_intrinsics_gradients_equal_the_float64_tensor_walk(built, lanes, setting):
    """The intrinsics reach the walk through the positions (autograd of walk_inputs) and in the kernel: the
    slice's screen motion (its direction places the steps, its length the span) and a bilinear fetch's
    unprojection (soft.h's end_slice_adjoint chains both by hand). Their sum per image, the depth's gradient and
    the radius' beside it, within 1e-4 relative of the float64 tensor walk's autograd (soft and
    straight-through, bilinear, nearest and edge-aware fetches, dropped and clamped borders)."""
    gb = FRAMES["rough"]()
    ref_depth, ref_intrinsics, ref_radius = _intrinsics_grads(gb, torch.float64, None, SETTINGS[setting])
    depth, intrinsics, radius = _intrinsics_grads(gb, torch.float32, lanes, SETTINGS[setting])
    assert ref_intrinsics.abs().max() > 1e-3  # (the comparison means something)
    assert relative_error(intrinsics, ref_intrinsics) <= 1e-4
    assert relative_error(depth, ref_depth) <= 1e-4
    assert abs(float(radius - ref_radius)) <= 1e-4 * abs(float(ref_radius)) + 1e-4 * float(ref_depth.abs().sum())


# ------------------------------------------------------------------------------- what it covers
def test_kernel_covers_gbuffer_gradients_and_the_intrinsics(built, monkeypatch):
    gb = example_gbuffer(12, 16)
    covers = soft_module.kernel_covers
    depth = gb.depth.clone().requires_grad_()
    graph = GBuffer(depth=depth, camera=gb.camera)
    for mode in ("soft", "straight_through"):
        assert covers(BitmaskAO(mode=mode), graph) is None
    assert "hard mode" in covers(BitmaskAO(mode="hard", weighting="cosine"), graph)
    intrinsics = gb.camera.intrinsics.clone().requires_grad_()
    moving = GBuffer(depth=gb.depth, camera=PinholeCamera(intrinsics, gb.camera.height, gb.camera.width))
    assert covers(BitmaskAO(mode="soft"), moving) is None
    assert "hard mode" in covers(BitmaskAO(mode="hard", weighting="cosine"), moving)
    # the auto backend takes the kernel for a depth gradient
    calls = count_kernel_calls(monkeypatch, "bitmask")
    vis = BitmaskAO(mode="soft", slices=2, steps=3)(graph).visibility
    (g_depth,) = torch.autograd.grad(vis.sum(), [depth])
    assert calls == [1] and g_depth.abs().sum() > 0
    # and for the sectors and fetch of torch-ao fit's default pipeline (cosine, edge-aware)
    vis = BitmaskAO(mode="soft", slices=2, steps=3, weighting="cosine", fetch="edge_aware")(graph).visibility
    (g_depth,) = torch.autograd.grad(vis.sum(), [depth])
    assert calls == [1, 1] and g_depth.abs().sum() > 0


def test_gbuffer_gradients_on_two_threads_equal_one_thread(built):
    """The taps' gradients go to per-thread images summed after the rows: the same gradients on any number
    of threads, up to the order of the float32 sums."""
    gb = FRAMES["rough"]()
    (vis1, grads1), (vis2, grads2) = on_threads(lambda: _values_and_grads(gb, torch.float32, "simd", SETTINGS[0]))
    assert torch.equal(vis1, vis2)
    for a, b in zip(grads1, grads2):
        assert relative_error(b, a) <= 1e-6


@pytest.mark.parametrize("mode", ["soft", "straight_through"])
def test_a_constant_ambient_colour_runs_with_the_kernel(built, mode, monkeypatch):
    """A constant ambient colour is the visibility times the colour (0 on background): the module's call runs the
    soft kernel, and its ambient light and the gradients of a weighted sum of it (depth, normals, radius,
    thickness) agree with the float64 tensor walk's."""
    calls = count_kernel_calls(monkeypatch, "bitmask")  # (the soft kernel: the last of bitmask's)
    colour = (0.2, 0.5, 1.0)
    settings = dict(mode=mode, slices=3, steps=4, weighting="cosine", fetch="edge_aware", tau=0.3, ambient=colour)

    def ambient_and_grads(dtype, backend):
        gb0 = FRAMES["rough"]().to(dtype=dtype)
        depth = gb0.depth.detach().clone().requires_grad_()
        normals = gb0.view_normals().detach().clone().requires_grad_()
        module = BitmaskAO(backend=backend, **settings).to(dtype)
        out = module(GBuffer(depth=depth, normals=normals, camera=gb0.camera))
        loss = (out.ambient * torch.linspace(-0.5, 1.5, out.ambient.numel(), dtype=dtype).view_as(out.ambient)).sum()
        grads = torch.autograd.grad(loss, [depth, normals, module.radius, module.thickness])
        return out, [g.double() for g in grads]

    ref, ref_grads = ambient_and_grads(torch.float64, "torch")
    out, grads = ambient_and_grads(torch.float32, "kernel")
    assert calls == [1]
    want = torch.where(FRAMES["rough"]().valid, out.visibility * torch.tensor(colour).view(1, 3, 1, 1), 0.0)
    assert torch.equal(out.ambient, want)
    assert (out.ambient.double() - ref.ambient).abs().max() <= 1e-5
    for name, g, r in zip(("depth", "normals", "radius", "thickness"), grads, ref_grads):
        assert r.abs().sum() > 0, name
        assert relative_error(g, r) <= 1e-4, (name, relative_error(g, r))


SPHERE_SETTINGS = [dict(mode="soft", sample_extent="sphere", tau=0.3),
                   dict(mode="straight_through", sample_extent="sphere", weighting="cosine", bent_normals=True),
                   dict(mode="soft", sample_extent="sphere", radius=1.2, thickness=0.3)]


def _module_grads(gb0: GBuffer, dtype: torch.dtype, backend: str, settings: dict):
    """A module's visibility and d(weighted visibility and bent normal)/d(depth, normals, radius, thickness)."""
    g = gb0.to(dtype=dtype)
    depth = g.depth.detach().clone().requires_grad_()
    normals = g.view_normals().detach().clone().requires_grad_()
    module = BitmaskAO(backend=backend, **settings).to(dtype)
    out = module(GBuffer(depth=depth, normals=normals, camera=g.camera))
    loss = (out.visibility * _loss_weights(out.visibility).to(dtype)).sum()
    if out.bent_normal is not None:
        loss = loss + (out.bent_normal * torch.linspace(0.5, 1.5, out.bent_normal.numel(), dtype=dtype).view_as(out.bent_normal)).sum()
    grads = torch.autograd.grad(loss, [depth, normals, module.radius, module.thickness])
    return out.visibility.detach().double(), [x.double() for x in grads]


@pytest.mark.parametrize("setting", range(len(SPHERE_SETTINGS)))
def test_steps_over_the_spheres_extent_in_the_soft_kernel(built, setting):
    """``sample_extent="sphere"`` (the walk's steps over the radius' sphere's screen extent) in the soft and
    straight-through kernel: values within 1e-5, gradients of depth, normals, radius and thickness within 1e-4
    relative of the float64 tensor walk (measured: 1.2e-6 and 1.6e-5 at most)."""
    gb = FRAMES["rough"]()
    settings = SPHERE_SETTINGS[setting]
    reference, ref_grads = _module_grads(gb, torch.float64, "torch", settings)
    out, grads = _module_grads(gb, torch.float32, "kernel", settings)
    flat, _ = _module_grads(gb, torch.float64, "torch", {**settings, "sample_extent": "radius"})
    assert (flat - reference).abs().max() > 0.01  # (the sphere's extent moves the steps)
    assert (out - reference).abs().max() <= 1e-5
    for g, ref in zip(grads, ref_grads):
        assert relative_error(g, ref) <= 1e-4, relative_error(g, ref)


def test_steps_over_the_spheres_extent_move_with_the_radius(built):
    """Without a G-buffer gradient the soft kernel's forward carries the radius' and thickness' derivatives (its
    "soft_gradients" walk: step_motion, whose span grows with the sphere's stretch too): within 1e-4 relative."""
    gb = FRAMES["rough"]()
    grads = []
    for dtype, backend in ((torch.float64, "torch"), (torch.float32, "kernel")):
        module = BitmaskAO(backend=backend, mode="soft", sample_extent="sphere", tau=0.3).to(dtype)
        vis = module(gb.to(dtype=dtype)).visibility
        grads.append(torch.autograd.grad((vis * _loss_weights(vis).to(dtype)).sum(), [module.radius, module.thickness]))
    for g, ref in zip(grads[1], grads[0]):
        assert abs(float(g) - float(ref)) <= 1e-4 * abs(float(ref)), (float(g), float(ref))


SEGMENT_SETTINGS = [dict(variant="exact", union="sectors", mode="soft"), dict(mode="soft", clip_to_radius=True, tau=0.3),
                    dict(mode="soft", thickness_direction="depth", tau=0.3),
                    dict(variant="exact", union="sectors", mode="straight_through", bent_normals=True)]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(SEGMENT_SETTINGS)))
def test_the_exact_variants_segments_in_the_soft_kernel(built, setting, lanes, monkeypatch):
    """The ``"exact"`` variant's segment geometry with the sector union in soft and straight-through mode (the back
    point along the sample's camera ray, the segment clipped to the radius' sphere: bitmask.h's segment_angles, its
    adjoint in dual lanes): values within 1e-5, gradients of depth, normals, radius and thickness within 2e-4 relative
    of the float64 tensor walk, with the G-buffer's gradients (the backward's walk) and without (the forward's
    derivative channels). Measured: 3.6e-6 and 9.4e-5 (straight-through's radius) at most."""
    if lanes == "scalar":
        use_scalar_lanes(monkeypatch, soft_module)
    gb = FRAMES["rough"]()
    settings = SEGMENT_SETTINGS[setting]
    reference, ref_grads = _module_grads(gb, torch.float64, "torch", settings)
    out, grads = _module_grads(gb, torch.float32, "kernel", settings)
    assert (out - reference).abs().max() <= 1e-5
    for g, ref in zip(grads, ref_grads):
        assert relative_error(g, ref) <= 2e-4, relative_error(g, ref)
    params = []
    for dtype, backend in ((torch.float64, "torch"), (torch.float32, "kernel")):
        module = BitmaskAO(backend=backend, **settings).to(dtype)
        vis = module(gb.to(dtype=dtype)).visibility
        params.append(torch.autograd.grad((vis * _loss_weights(vis).to(dtype)).sum(), [module.radius, module.thickness]))
    for g, ref in zip(params[1], params[0]):
        assert abs(float(g) - float(ref)) <= 2e-4 * abs(float(ref)), (float(g), float(ref))
