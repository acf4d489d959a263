"""The walk's backward (walk_grad_cpu.cpp: the horizon accumulators' plain walk records the steps that changed
each slice's state, a reverse-mode replay of those differentiates them; the SSAO family's replays every step:
lanes_rev.h) against the tensor-op walk's autograd in float64, the specification: gradients of depth (through
positions, normals and inverse depth), of given normals and of the parameters, for GTAO's three variants, HBAO,
UE4 SSAO and PSSAO, every fetch and border, SIMD and scalar lanes; and a finite-difference check of the
kernel's own gradient."""
import dataclasses

import pytest
import torch

from torch_ao.camera import PinholeCamera
from torch_ao.examples import example_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import gtao_covers, hbao_covers, pssao_covers, ue4_ssao_covers
from torch_ao.kernels.walk_grad import MAX_CUDA_STEPS
from torch_ao.methods.gtao import GTAO
from torch_ao.methods.hbao import HBAO
from torch_ao.methods.pssao import PSSAO
from torch_ao.methods.ue4_ssao import UE4SSAO

from kernel_agreement import assert_depth_gradient_matches_central_differences, relative_error, upstream_weights
from test_kernels import built, pytestmark, rough_gbuffer  # noqa: F401

#: (module, options, frozen parameters): every accumulator of horizon.h and ssao.h, every fetch and border, both noises
#: and staggered steps, records whose sides cross a word; the "-most" cases take as many steps as a CUDA thread's
#: backward does (MAX_CUDA_STEPS), where its tape (walk_grad.h's tape_capacity) holds the most takes: scalar lanes
#: run that thread's code
CASES = {
    "exact": (GTAO, dict(slices=4, steps=4), ()),
    "exact-falloff-bent": (GTAO, dict(slices=3, steps=5, radius=0.6, falloff_range=0.5, bent_normals=True), ()),
    "exact-power": (GTAO, dict(slices=2, steps=5, jitter=False, step_power=2.0, min_step_px=2.0, final_power=1.7), ()),
    "exact-screen": (GTAO, dict(slices=2, steps=4, azimuth="screen", search_scale=1.5, max_radius_px=8.0,
                                step_power=1.5), ()),
    "exact-nearest-clamp": (GTAO, dict(slices=3, steps=6, fetch="nearest", border="clamp", falloff_range=0.3), ()),
    "exact-bilinear-clamp": (GTAO, dict(slices=3, steps=6, border="clamp", radius=1.5), ()),
    "exact-hilbert-stagger": (GTAO, dict(slices=3, steps=3, noise="hilbert_r2", stagger=True, seed=4), ()),
    "exact-edge-aware": (GTAO, dict(slices=4, steps=5, fetch="edge_aware", falloff_range=0.4), ()),
    "exact-edge-aware-clamp": (GTAO, dict(slices=3, steps=6, fetch="edge_aware", border="clamp", bent_normals=True), ()),
    "hdrp": (GTAO, dict(variant="hdrp", slices=3, steps=5, multibounce=True), ()),
    "hdrp-nearest": (GTAO, dict(variant="hdrp", slices=2, steps=6, fetch="nearest", projected_normal_weight=False), ()),
    "hdrp-edge-aware": (GTAO, dict(variant="hdrp", slices=3, steps=5, fetch="edge_aware"), ()),
    "ue4": (GTAO, dict(variant="ue4", slices=3, steps=5, thickness_heuristic=0.4), ()),
    "ue4-nearest-clamp": (GTAO, dict(variant="ue4", slices=2, steps=6, fetch="nearest", border="clamp"), ()),
    "ue4-stagger": (GTAO, dict(variant="ue4", slices=3, steps=4, stagger=True, seed=2), ()),
    "ue4-edge-aware": (GTAO, dict(variant="ue4", slices=3, steps=5, fetch="edge_aware"), ()),
    "ue4-edge-aware-most": (GTAO, dict(variant="ue4", slices=2, steps=MAX_CUDA_STEPS, fetch="edge_aware", stagger=True,
                                       azimuth="screen"), ()),
    "hdrp-most": (GTAO, dict(variant="hdrp", slices=2, steps=MAX_CUDA_STEPS, bent_normals=True), ()),
    "hbao": (HBAO, dict(slices=6, steps=4), ()),
    "hbao-view-most": (HBAO, dict(slices=2, steps=MAX_CUDA_STEPS, elevation="view"), ()),
    "hbao-max-quadratic": (HBAO, dict(slices=5, steps=5, accumulate="max", falloff="quadratic"), ()),
    "hbao-view": (HBAO, dict(slices=4, steps=5, elevation="view", radius=0.8), ()),
    "hbao-nearest-clamp": (HBAO, dict(slices=4, steps=6, fetch="nearest", border="clamp"), ()),
    "hbao-edge-aware-clamp": (HBAO, dict(slices=4, steps=5, fetch="edge_aware", border="clamp"), ()),
    "hbao-max-edge-aware": (HBAO, dict(slices=4, steps=5, accumulate="max", fetch="edge_aware"), ()),
    "hbao-hilbert-stagger": (HBAO, dict(slices=4, steps=4, noise="hilbert_r2", stagger=True, seed=1), ()),
    "ue4ssao": (UE4SSAO, dict(), ()),
    "ue4ssao-bilinear-soft": (UE4SSAO, dict(sample_set="uniform", slices=4, steps=3, fetch="bilinear", border="drop",
                                            flat_softness=0.05), ()),
    "ue4ssao-edge-aware-accurate": (UE4SSAO, dict(sample_set="uniform", slices=5, steps=2, fetch="edge_aware",
                                                  accurate_angle=True, radius=0.6), ()),
    "ue4ssao-ue4_6-clamp": (UE4SSAO, dict(sample_set="ue4_6", steps=3, fetch="bilinear", border="clamp",
                                          accurate_angle=True, flat_softness=0.01, final_power=2.0), ()),
    "ue4ssao-most": (UE4SSAO, dict(sample_set="uniform", slices=2, steps=MAX_CUDA_STEPS, fetch="bilinear",
                                   border="drop", flat_softness=0.02), ()),
    "pssao": (PSSAO, dict(), ()),
    "pssao-bilinear": (PSSAO, dict(normalize="directions", slices=6, steps=5, fetch="bilinear"), ()),
    "pssao-clamp": (PSSAO, dict(slices=5, steps=4, border="clamp", distance_bias=0.5), ()),
    "pssao-edge-aware": (PSSAO, dict(slices=12, steps=6, fetch="edge_aware", normalize="directions"), ()),
    "pssao-most": (PSSAO, dict(slices=2, steps=MAX_CUDA_STEPS, fetch="bilinear"), ()),
    # (GTAO's record in two words, slice 2's side -1 in bits 60-71; HBAO's slices of 40 bits, across words; HBAO's and
    # GTAO's of 80 bits; named to sort last, which keeps every other case's alternation of given and reconstructed
    # normals)
    "wide-record": (GTAO, dict(slices=3, steps=12, radius=1.2), ()),
    "wide-halves": (HBAO, dict(slices=2, steps=20), ()),
    "wide-steps": (HBAO, dict(slices=2, steps=40), ()),  # (a slice's bits beyond one word: set in the record directly)
    "wide-steps-replaced": (GTAO, dict(slices=2, steps=40), ()),  # (... each side's last take's, as the slice ends)
    # slices drawn by the projected normal's density: the azimuth and the slice's weight differentiated too (named
    # to sort last as well)
    "with-projected-normal-exact": (GTAO, dict(slices=4, steps=4, slice_sampling="projected_normal",
                                               falloff_range=0.4, bent_normals=True), ()),
    "with-projected-normal-hdrp": (GTAO, dict(variant="hdrp", azimuth="view", slices=3, steps=5, fetch="edge_aware",
                                              slice_sampling="projected_normal"), ()),
    "with-projected-normal-ue4": (GTAO, dict(variant="ue4", azimuth="view", slices=3, steps=4, stagger=True,
                                             slice_sampling="projected_normal"), ()),
    "with-projected-normal-most": (GTAO, dict(variant="hdrp", azimuth="view", slices=2, steps=MAX_CUDA_STEPS,
                                              bent_normals=True, slice_sampling="projected_normal"), ()),
}
#: the kernel sums function of each module (patched for the lanes) and its covers
KERNEL_SUMS = {GTAO: ("gtao", "gtao_sums"), HBAO: ("gtao", "hbao_sums"), UE4SSAO: ("ssao", "ue4_ssao_sums"),
               PSSAO: ("ssao", "pssao_sums")}
COVERS = {GTAO: gtao_covers, HBAO: hbao_covers, UE4SSAO: ue4_ssao_covers, PSSAO: pssao_covers}


def patch_gbuffer() -> GBuffer:
    """A plane facing the camera with the rough frame's bumps in one window: HBAO's plane samples never rise
    above its tangent (lifted by the angle bias), so the pixels of a row far from the bumps take no step in any
    direction, and those beside them take steps only in the directions toward the bumps: walk_grad.h's backward
    skips the directions (and the rows' blocks of pixels) that took nothing."""
    gb = rough_gbuffer(20, 64)
    bumps = torch.zeros_like(gb.depth, dtype=torch.bool)
    bumps[..., 6:16, 26:38] = True  # (in front of the plane: 0.7 to 1.95)
    return GBuffer(depth=torch.where(bumps, gb.depth - 0.7, torch.where(gb.depth.isinf(), gb.depth, 2.0)),
                   camera=gb.camera)


FRAMES = {"example": lambda: example_gbuffer(24, 40), "rough": lambda: rough_gbuffer(20, 28), "patch": patch_gbuffer}


def _reference_dtype(frame: str, options: dict) -> torch.dtype:
    """The dtype of the tensor path a case is compared with. The rough frame's noisy depth has no tied
    samples: float64, the specification. Where ties or kinks are built in, rounding decides which sample (or
    bilinear cell) carries the gradient, and the reference is the tensor path in float32, which rounds as
    the kernel does: the example's floor and wall are planes, whose samples lie in a pixel's tangent plane
    (tied with the hemisphere's boundary), and without jitter a horizontal slice's samples sit on texel rows
    (the bilinear interpolation's kink)."""
    return torch.float32 if frame == "example" or options.get("jitter") is False else torch.float64


#: (case, frame): every case on the rough frame; on the planar example frame the bilinear fetch with the
#: dropped border (a clamped border or a nearest fetch reads texels of the pixel's own plane, tied with its
#: tangent plane, where the kernel's and torch's rounding of the same angle can pick differently)
PAIRS = [(case, "rough") for case in sorted(CASES)] + [
    (case, "example") for case in sorted(CASES)
    if CASES[case][1].get("fetch", "bilinear") == "bilinear" and CASES[case][1].get("border", "drop") == "drop"
    and CASES[case][0] is not PSSAO] + [  # (PSSAO's max(n . d, 0) of a plane's own samples sits at its kink, n . d = 0)
    (case, "patch") for case in sorted(CASES) if CASES[case][0] is HBAO]

def _module(case: str, backend: str):
    """The case's module on ``backend``, its frozen parameters not requiring gradients."""
    make, options, frozen = CASES[case]
    module = make(backend=backend, **options)
    for name in frozen:
        getattr(module, name).requires_grad_(False)
    return module


def _given_normals(gb: GBuffer, make) -> torch.Tensor:
    """The normals a case is given: the G-buffer's reconstruction. PSSAO's a = max(n . d, 0) has its kink where
    a sample lies in the pixel's tangent plane, as the neighbours the normals were reconstructed from do (to
    rounding): its normals are tilted off it."""
    normals = gb.view_normals().detach()
    if make is PSSAO:
        normals = torch.nn.functional.normalize(normals + torch.tensor([0.2, -0.1, 0.1]).view(1, 3, 1, 1), dim=1)
    return normals


def _gradients(gb0: GBuffer, case: str, backend: str, dtype: torch.dtype, given_normals: bool,
               intrinsics: bool = False):
    """The visibility and d(loss)/d(depth[, normals], every parameter[, the intrinsics]) for loss = weighted
    visibility (+ bent normal), the G-buffer in ``dtype``."""
    make = CASES[case][0]
    depth = gb0.depth.detach().to(dtype).clone().requires_grad_(True)
    normals = None
    if given_normals:
        normals = _given_normals(gb0, make).to(dtype).clone().requires_grad_(True)
    camera = dataclasses.replace(gb0.camera, intrinsics=gb0.camera.intrinsics.to(dtype).clone().requires_grad_(intrinsics))
    gb = GBuffer(depth=depth, normals=normals, camera=camera)
    module = _module(case, backend)
    parameters = {name: p for name, p in module.named_parameters() if p.requires_grad}
    out = module(gb)
    loss = (out.visibility * upstream_weights(out.visibility)).sum()
    if getattr(out, "bent_normal", None) is not None:
        loss = loss + (out.bent_normal * upstream_weights(out.bent_normal)).sum()
    loss.backward()
    # (a parameter with no effect on this call, as UE4 SSAO's flat_softness at 0, has no gradient on either path)
    grads = {"depth": depth.grad} | {name: p.grad for name, p in parameters.items() if p.grad is not None}
    if given_normals:  # (UE4 SSAO reads no normal: zero, or none on the tensor path)
        grads["normals"] = torch.zeros_like(normals) if normals.grad is None else normals.grad
    if intrinsics:
        grads["intrinsics"] = camera.intrinsics.grad
    return out.visibility.detach().double(), {name: g.double() for name, g in grads.items()}


def _patch_lanes(monkeypatch, make, lanes: str) -> None:
    """The kernel sums of module ``make`` run on ``lanes``."""
    import importlib

    where, name = KERNEL_SUMS[make]
    kernel_module = importlib.import_module(f"torch_ao.kernels.{where}")
    monkeypatch.setattr(kernel_module, name, _with_lanes(getattr(kernel_module, name), lanes))


def _with_lanes(fn, lanes):
    def run(*args, **kwargs):
        kwargs["lanes"] = lanes
        return fn(*args, **kwargs)
    return run


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("case, frame", PAIRS)
def test_kernel_gradients_equal_the_tensor_walk(built, monkeypatch, lanes, case, frame):
    make = CASES[case][0]
    _patch_lanes(monkeypatch, make, lanes)
    gb = FRAMES[frame]()
    given = sorted(CASES).index(case) % 2 == 1  # normals given (their gradient) or reconstructed from depth
    assert COVERS[make](_module(case, "kernel"), _requiring(gb)) is None
    reference_out, reference = _gradients(gb, case, "torch", _reference_dtype(frame, CASES[case][1]), given)
    out, grads = _gradients(gb, case, "kernel", torch.float32, given)
    # UE4 SSAO's x = (1 - angle) / (weight + 0.001) amplifies float32 rounding up to 1000 times: the tensor path
    # itself in float32 is up to 4e-5 (visibility) and 1.8e-4 (gradients, relative) off its float64 values
    amplified = make is UE4SSAO
    assert torch.allclose(out, reference_out, atol=2e-4 if amplified else 5e-5)  # (float32 against float64)
    assert reference["depth"].abs().max() > 1e-2  # the loss depends on the depth: the comparison means something
    assert set(grads) == set(reference) and len(reference) >= 2
    # HDRP's projected-normal angle is fast_acos(clamp(cos n)), whose slope 1 / (2 sqrt(1 - |cos n|)) is
    # unbounded where the projected normal meets V: there float rounding (and the clamp at |cos n| = 1)
    # changes a pixel's gradient (and its neighbours' depth, through the normals reconstructed from it). The
    # entries that differ most (1%) are left out for it: with given normals it agrees everywhere. On the planar
    # example frame a tie between samples of the plane is broken by rounding (_reference_dtype), which moves
    # one pixel's gradient to another sample: the same 1% is left out there
    trim = 0.01 if CASES[case][1].get("variant") == "hdrp" or frame == "example" else 0.0
    for name in reference:
        if name == "radius" and float(reference[name]) == 0:
            # the radius clamped in pixels everywhere (max_radius_px) has no effect; the kernel's gradient is
            # Euler's sum of the G-buffer's terms (walk_grad), which cancel to their float32 rounding
            terms = float((reference["depth"].abs() * gb.depth.double()).nansum())
            assert abs(float(grads[name])) <= 1e-8 * terms, (float(grads[name]), terms)
            continue
        # (UE4 SSAO's radius: Euler's identity sums the G-buffer's and three lengths' terms, which cancel to it,
        # so it carries their float32 rounding: up to 1.3e-3 on the scalar lanes, 1.9e-4 on the float32 tensor path)
        tolerance = (3e-3 if name == "radius" else 1e-3) if amplified else 2e-4
        assert relative_error(grads[name], reference[name], trim) < tolerance, name


def _requiring(gb: GBuffer) -> GBuffer:
    return GBuffer(depth=gb.depth.clone().requires_grad_(True), camera=gb.camera)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["exact-falloff-bent", "exact-nearest-clamp", "exact-hilbert-stagger", "exact-edge-aware",
                                  "with-projected-normal-exact", "hdrp", "ue4", "hbao-edge-aware-clamp",
                                  "hbao", "hbao-max-quadratic", "hbao-hilbert-stagger", "ue4ssao-bilinear-soft",
                                  "pssao-bilinear"])
def test_kernel_gradient_matches_finite_differences(built, case):
    """The gradcheck of a small frame: the kernel's float32 depth gradient against central differences (1e-6)
    of the tensor path's float64 forward, on every 6th pixel. Normals are given (the reconstruction from depth
    picks the side with the smaller discontinuity, which has no derivative where the sides are close), the
    rough depth has no ties: every derivative is defined."""
    make, options, _ = CASES[case]
    gb = rough_gbuffer(12, 14)
    assert_depth_gradient_matches_central_differences(  # (every 6th pixel of the frame: 41 of 246)
        lambda backend: make(backend=backend, trainable=False, **options), gb, _given_normals(gb, make), every=6)


def test_gradient_calls_run_on_the_kernel(built):
    gb = _requiring(example_gbuffer(12, 20))
    for module in (GTAO(slices=2, steps=3, backend="kernel"), HBAO(slices=4, steps=3, backend="kernel"),
                   GTAO(variant="hdrp", fetch="nearest", border="clamp", backend="kernel"),
                   UE4SSAO(trainable=False, backend="kernel"), PSSAO(slices=4, steps=3, backend="kernel")):
        assert COVERS[type(module)](module, gb) is None
        out = module(gb).visibility
        assert out.grad_fn is not None
        out.sum().backward()
        assert torch.isfinite(gb.depth.grad).all() and gb.depth.grad.abs().max() > 0
        gb.depth.grad = None


def _intrinsics_requiring(gb: GBuffer) -> GBuffer:
    camera = dataclasses.replace(gb.camera, intrinsics=gb.camera.intrinsics.clone().requires_grad_(True))
    return GBuffer(depth=gb.depth, camera=camera)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("case", ["exact", "exact-edge-aware", "exact-screen", "hdrp-nearest", "ue4", "hbao-view",
                                  "hbao-edge-aware-clamp", "ue4ssao-bilinear-soft", "pssao-bilinear", "pssao-clamp", "hdrp-most"])
def test_kernel_intrinsics_gradients_equal_the_tensor_walk(built, monkeypatch, lanes, case):
    """The intrinsics reach the walk twice: through the positions (torch's unprojection, by autograd) and in the
    kernel (the slice's screen direction and extent in pixels, a bilinear fetch's unprojection: seed_camera's
    leaves). Their sum, and the depth's gradient beside it, against the float64 tensor path's autograd."""
    make = CASES[case][0]
    _patch_lanes(monkeypatch, make, lanes)
    gb = rough_gbuffer(20, 28)
    assert COVERS[make](_module(case, "kernel"), _intrinsics_requiring(gb)) is None
    _, reference = _gradients(gb, case, "torch", torch.float64, False, intrinsics=True)
    _, grads = _gradients(gb, case, "kernel", torch.float32, False, intrinsics=True)
    assert reference["intrinsics"].abs().max() > 1e-3  # (the comparison means something)
    trim = 0.01 if CASES[case][1].get("variant") == "hdrp" else 0.0  # (fast_acos' slope: as the test above)
    assert relative_error(grads["depth"], reference["depth"], trim) < (1e-3 if make is UE4SSAO else 2e-4)
    assert relative_error(grads["intrinsics"], reference["intrinsics"]) < (1e-3 if make is UE4SSAO else 2e-4)


def test_ue4_radius_gradient_carries_its_epsilon():
    """The ue4 variant's rsqrt(|d|^2 + 1e-4) is not scale-invariant: Euler's identity for the radius needs the
    epsilon's own gradient (a seeded setting of dimension 2). On a frame scaled down 100 times (|d|^2 near the
    epsilon) the kernel's radius gradient is the float64 tensor path's; without the epsilon's term it would not be."""
    gb = rough_gbuffer(20, 28)
    small = GBuffer(depth=gb.depth / 100, camera=gb.camera)
    grads = []
    for backend, dtype in (("torch", torch.float64), ("kernel", torch.float32)):
        module = GTAO(variant="ue4", slices=3, steps=5, radius=0.01, backend=backend).to(dtype)
        out = module(small.to(dtype=dtype)).visibility
        (g,) = torch.autograd.grad((out * upstream_weights(out)).sum(), [module.radius])
        grads.append(float(g))
    assert abs(grads[0]) > 1e-2
    assert grads[1] == pytest.approx(grads[0], rel=2e-4)


@pytest.mark.parametrize("case", ["exact", "hbao"])
def test_threads_scatter_into_their_own_images(built, case):
    gb = rough_gbuffer(20, 28)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        _, one = _gradients(gb, case, "kernel", torch.float32, True)
        torch.set_num_threads(3)
        _, three = _gradients(gb, case, "kernel", torch.float32, True)
    finally:
        torch.set_num_threads(before)
    for name in one:
        assert torch.allclose(one[name], three[name], rtol=1e-5, atol=1e-6), name


def test_zero_length_projected_normals_give_the_tensor_paths_finite_gradients(monkeypatch):
    """Normals along the first slice's axis: on the image's middle row (whose view directions lie in the
    x-z plane) the slice along +u projects them to zero length, and atan2(0, 0) is their angle. The dual
    walk takes no derivative there (as torch's norm at 0), instead of sqrt's and atan2's 0/0, and gives
    the tensor path's gradients."""
    import torch_ao.walk.walk as walk_module

    cam = PinholeCamera.from_fov(60.0, 9, 9)
    normals = torch.zeros(1, 3, 9, 9)
    normals[:, 1] = 1.0
    # (not a plane: on a plane every sample of a side gives the same horizon, and the max's gradient is a tie)
    depth0 = 2.0 + 0.1 * torch.rand(1, 1, 9, 9, generator=torch.Generator().manual_seed(0))
    lengths = []
    geometry = walk_module.slice_geometry
    monkeypatch.setattr(walk_module, "slice_geometry",
                        lambda *a: lengths.append((g := geometry(*a)).normal_length.detach()) or g)
    grads = []
    for backend in ("kernel", "torch"):
        depth, n = depth0.clone().requires_grad_(True), normals.clone().requires_grad_(True)
        GTAO(backend=backend, jitter=False, slices=2, steps=3)(GBuffer(depth, cam, normals=n)).visibility.sum().backward()
        grads.append((depth.grad, n.grad))
    zero = (lengths[0] == 0).view(9, 9)  # (the case: the tensor path's first slice, on the middle row)
    assert int(zero[4].sum()) >= 5 and int(zero.sum()) == int(zero[4].sum())
    (depth_k, normals_k), (depth_t, normals_t) = grads
    assert bool(torch.isfinite(depth_k).all()) and bool(torch.isfinite(normals_k).all())
    torch.testing.assert_close(depth_k, depth_t, rtol=1e-4, atol=1e-6)
    # (a normal's own gradient where its projection is zero, or within rounding of it, is the kink's: the
    # middle row's are left out)
    off_row = [0, 1, 2, 3, 5, 6, 7, 8]
    torch.testing.assert_close(normals_k[..., off_row, :], normals_t[..., off_row, :], rtol=1e-4, atol=1e-6)
