"""The exact union's kernel with gradients (walk.h with exact_soft.h: ``BitmaskAO(variant="exact")`` in soft and
straight-through mode, what ``torch-ao fit --variant exact`` fits) against the tensor-op walk: values to 1e-5 of
the float64 walk, gradients of radius, thickness and the back-face model's thickness_scale to 1e-4 relative, in
both lane types; central differences; the forward equal to the hard exact kernel's; what it does not cover."""
import pytest
import torch

from kernel_agreement import assert_values_agree
from test_kernels import FRAMES, built, pytestmark  # noqa: F401  (built: the fixture; the skip)
from test_kernels_exact import with_backface
from torch_ao.camera import PinholeCamera
from torch_ao.examples import example_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import exact_hard
from torch_ao.kernels.bitmask import module_thickness, thickness_options
from torch_ao.kernels.soft_exact import exact_soft, exact_soft_covers
from torch_ao.methods.bitmask import BitmaskAO
from torch_ao.thickness import BackfaceThickness

SETTINGS = [
    dict(slices=3, steps=4),  # the variant's defaults: cosine, along the ray, clipped, sphere extent, edge-aware
    dict(slices=2, steps=5, thickness=BackfaceThickness(scale=0.8, thickness=0.05)),  # what fit --thickness backface fits
    dict(slices=3, steps=3, weighting="uniform", thickness_direction="view", clip_to_radius=False,
         sample_extent="radius", fetch="bilinear", border="clamp", seed=2),
    dict(slices=2, steps=4, fetch="nearest", radius=0.6, thickness=0.2, jitter=False),
    dict(slices=3, steps=4, thickness=BackfaceThickness(), noise="hilbert_r2", stagger=True, seed=3, step_power=2.0,
         min_step_px=1.0, sector_epsilon=0.01, mode="straight_through"),
    dict(slices=3, steps=4, azimuth="screen", thickness=BackfaceThickness(scale=0.9, thickness=0.05)),
    dict(slices=3, steps=4, thickness_growth=0.7),  # a growth: t (1 + g |delta|), |delta| moving with the fetch
    dict(slices=2, steps=5, thickness=BackfaceThickness(scale=0.8, thickness=0.05, growth=0.5)),
]


def _parameters(module: BitmaskAO) -> list[str]:
    back = isinstance(module.thickness_model, BackfaceThickness)
    grows = module.thickness_model.growth is not None
    return ["radius", "thickness"] + (["thickness_scale"] if back else []) + (["thickness_growth"] if grows else [])


def visibility_and_grads(gb: GBuffer, lanes: str, setting: dict, dtype=torch.float32):
    """The visibility and the gradients of a weighted sum of it (weights not uniform, so that every pixel's
    gradient counts differently): lanes ``"torch"`` is the tensor path (in ``dtype``)."""
    settings = {"mode": "soft", **setting}
    module = BitmaskAO(variant="exact", backend="torch" if lanes == "torch" else "kernel", **settings).to(dtype)
    names = _parameters(module)
    frame = gb.to(dtype=dtype)
    if lanes == "scalar":
        vis = _kernel(module, frame, "scalar")
    else:
        if lanes == "simd":
            assert exact_soft_covers(module, frame) is None
        vis = module(frame).visibility
    loss = (vis * torch.linspace(0.5, 1.5, vis.numel(), dtype=vis.dtype).view_as(vis)).sum()
    grads = torch.autograd.grad(loss, [getattr(module, n) for n in names])
    return vis.detach().double(), {n: float(g) for n, g in zip(names, grads)}


def _kernel(module, gb, lanes, **overrides):
    form = module_thickness(module, gb)
    args = dict(slices=module.slices, steps=module.steps, radius=module.radius, thickness=form.offset, layer=form.layer,
                layer_scale=None if form.layer is None else form.scale, thickness_growth=form.growth,
                step_power=module.step_power,
                min_step_px=module.min_step_px, jitter=module.jitter, seed=module.seed, noise=module.noise,
                stagger=module.stagger, fetch=module.fetch, border=module.border, weighting=module.weighting,
                thickness_direction=module.thickness_direction, clip_to_radius=module.clip_to_radius,
                sample_extent=module.sample_extent, sector_epsilon=module.sector_epsilon, azimuth=module.azimuth,
                lanes=lanes)
    args.update(overrides)
    return exact_soft(gb, gb.view_normals(), **args)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_values_and_gradients_equal_the_tensor_walk(built, frame, setting, lanes):
    gb = with_backface(FRAMES[frame]())
    reference, ref_grads = visibility_and_grads(gb, "torch", SETTINGS[setting], torch.float64)
    out, grads = visibility_and_grads(gb, lanes, SETTINGS[setting])
    assert reference.min() < 0.9  # something is occluded: the comparison means something
    # float32 against float64: an angle's rounding near a clip or an edge-aware cell's ratio can flip a decision
    assert_values_agree(out, reference, gb.valid, atol=1e-5, bound=0.05, share=0.99)
    # the float32 tensor walk decides as the kernel does
    vis32, ref32 = visibility_and_grads(gb, "torch", SETTINGS[setting])
    assert (out - vis32).abs().max() <= 1e-5
    scale = max(abs(v) for v in ref32.values())
    for name, want in ref32.items():
        assert abs(grads[name] - want) <= 1e-4 * abs(want) + 1e-6 * scale, (name, grads[name], want)
        assert abs(grads[name] - ref_grads[name]) <= 2e-3 * scale, (name, grads[name], ref_grads[name])
    assert abs(ref32["radius"]) > 0.01  # (the thickness' may vanish: thin occluders clipped to the sphere)


def test_every_parameters_gradient_is_there_on_a_frame_with_thick_occluders(built):
    """On the rough frame the back-face layer's thickness matters: all three gradients are large."""
    gb = with_backface(FRAMES["rough"]())
    _, grads = visibility_and_grads(gb, "simd", SETTINGS[1])
    assert all(abs(g) > 1.0 for g in grads.values()), grads


@pytest.mark.parametrize("setting", [0, 1])
def test_gradients_match_finite_differences(built, setting):
    """Central differences of the kernel's own float32 forward (h = 1e-3) on the rough frame (thick
    occluders: every parameter matters). Clamped borders and the bilinear fetch: with ``border="drop"`` a
    sample leaving the image jumps from occluding to not, and the edge-aware fetch jumps between its taps and
    the nearest one, steps the gradient (rightly, as the tensor path's) does not see. The exact union is
    piecewise smooth (its sort, its clips): a 3 % tolerance."""
    gb = with_backface(FRAMES["rough"]())
    module = BitmaskAO(variant="exact", mode="soft", border="clamp", fetch="bilinear", **SETTINGS[setting])
    names = _parameters(module)
    params = {n: getattr(module, n).detach().clone().requires_grad_() for n in names}

    def mean(values):
        kwargs = dict(radius=values["radius"], thickness=values["thickness"])
        if "thickness_scale" in values:
            kwargs["layer_scale"] = values["thickness_scale"]
        return _kernel(module, gb, "simd", **kwargs).double().mean()

    grads = torch.autograd.grad(mean(params), list(params.values()))
    h = 1e-3
    with torch.no_grad():
        for (name, value), g in zip(params.items(), grads):
            up, down = dict(params), dict(params)
            up[name], down[name] = value + h, value - h
            fd = (mean(up).item() - mean(down).item()) / (2 * h)
            assert abs(fd) > 1e-3, name
            assert g.item() == pytest.approx(fd, rel=3e-2), (name, g.item(), fd)


@pytest.mark.parametrize("setting", [0, 1, 4, 7])
def test_straight_through_and_soft_forwards_are_the_hard_exact_kernels(built, setting):
    gb = with_backface(FRAMES["rough"]())
    for mode in ("soft", "straight_through"):
        module = BitmaskAO(variant="exact", **dict(SETTINGS[setting], mode=mode))
        out = module(gb).visibility
        assert out.requires_grad
        with torch.no_grad():
            hard = _kernel(module, gb, "simd")
            plain = exact_hard(gb, gb.view_normals(), slices=module.slices, steps=module.steps,
                               radius=float(module.radius), **thickness_options(module_thickness(module, gb)),
                               step_power=module.step_power, min_step_px=module.min_step_px,
                               jitter=module.jitter, seed=module.seed, noise=module.noise, stagger=module.stagger,
                               fetch=module.fetch, border=module.border, weighting=module.weighting,
                               thickness_direction=module.thickness_direction, clip_to_radius=module.clip_to_radius,
                               sample_extent=module.sample_extent, sector_epsilon=module.sector_epsilon,
                               azimuth=module.azimuth)
        assert torch.equal(out.detach(), plain) and torch.equal(hard, plain)


def test_auto_runs_it_for_a_gradient_of_the_parameters(built, monkeypatch):
    import torch_ao.kernels.dispatch as dispatch

    calls = []
    monkeypatch.setattr(dispatch, "KERNELS", dict(dispatch.KERNELS, bitmask=tuple(
        (covers, (lambda m, g, run=run: calls.append(run.__name__) or run(m, g))) for covers, run in dispatch.KERNELS["bitmask"])))
    gb = with_backface(FRAMES["example"]())
    module = BitmaskAO(variant="exact", mode="soft", slices=2, steps=3, thickness=BackfaceThickness())
    assert module(gb).visibility.requires_grad and calls == ["exact_soft_forward"]
    module.mode = "hard"  # the exact union has a gradient in hard mode too: the same walk
    assert module(gb).visibility.requires_grad and calls == ["exact_soft_forward"] * 2
    with torch.no_grad():
        module(gb)
    assert calls[-1] == "exact_forward"


def test_covers_names_what_it_does_not_cover():
    gb = with_backface(FRAMES["example"]())
    assert exact_soft_covers(BitmaskAO(variant="exact", mode="soft"), gb) is None
    assert exact_soft_covers(BitmaskAO(variant="exact", mode="straight_through", weighting="uniform"), gb) is None
    graph = GBuffer(depth=gb.depth.clone().requires_grad_(), camera=gb.camera, backface_depth=gb.backface_depth)
    assert exact_soft_covers(BitmaskAO(variant="exact", mode="soft"), graph) is None  # (exact_backward)
    assert exact_soft_covers(BitmaskAO(variant="exact", mode="soft", thickness=torch.full((1, 1, 54, 96), 0.2)),
                             graph) is None  # (a map: the layer's taps get its gradient)
    moving = GBuffer(depth=gb.depth, camera=PinholeCamera(gb.camera.intrinsics.clone().requires_grad_(),
                                                          gb.camera.height, gb.camera.width))
    assert exact_soft_covers(BitmaskAO(variant="exact", mode="soft"), moving) is None  # (the intrinsics' too)
    # (slices drawn by the projected normal's density, with the parameters' gradients: the CPU's kernel)
    assert exact_soft_covers(BitmaskAO(variant="exact", mode="soft", slice_sampling="projected_normal"), gb) is None
    cases = {"union": (BitmaskAO(mode="soft"), gb),
             "steps=40": (BitmaskAO(variant="exact", mode="soft", steps=40), gb),
             "float64": (BitmaskAO(variant="exact", mode="soft"), gb.to(dtype=torch.float64))}
    for word, (module, frame) in cases.items():
        reason = exact_soft_covers(module, frame)
        assert reason is not None and word in reason, (word, reason)


def test_bad_arguments_are_refused_by_name(built):
    gb = example_gbuffer(8, 8)
    with pytest.raises(ValueError, match="radius"):
        exact_soft(gb, gb.view_normals(), slices=2, steps=3, radius=torch.ones(2), thickness=torch.tensor(0.5))
    with pytest.raises(ValueError, match="steps"):
        exact_soft(gb, gb.view_normals(), slices=2, steps=33, radius=torch.tensor(1.0), thickness=torch.tensor(0.5))
