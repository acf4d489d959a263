"""Numerical stability matrix (issue 7): every method and mode, forward and backward, on stiff
parameters, extreme geometry, extreme frames and extreme cameras.

Each case asserts: no NaN/Inf in any output or gradient (depth, normals, light, parameters);
visibility in [0, 1] (except faithful variants that document otherwise); background pixels get
visibility 1 and zero gradient. A fast subset runs by default; the whole matrix is marked slow.
"""
from __future__ import annotations

import inspect

import pytest
import torch

from stability_cases import FRAMES
from torch_ao.camera import PinholeCamera
from torch_ao.gbuffer import GBuffer
from torch_ao.methods import get_method

#: name -> (method, constructor options, visibility may leave [0, 1])
CONFIGS: dict[str, tuple[str, dict, bool]] = {
    "ssao": ("ssao", {}, False),
    "hbao": ("hbao", {}, False),
    "hbao-quadratic": ("hbao", {"falloff": "quadratic"}, False),
    "ue4_ssao": ("ue4_ssao", {}, False),
    "pssao": ("pssao", {}, False),
    "pssao-directions": ("pssao", {"normalize": "directions"}, False),
    "gtao": ("gtao", {}, False),
    "gtao-hdrp": ("gtao", {"variant": "hdrp"}, False),
    "gtao-ue4": ("gtao", {"variant": "ue4"}, False),
    "gtao-bent-multibounce": ("gtao", {"bent_normals": True, "multibounce": True}, False),
    "bitmask-hard": ("bitmask", {"mode": "hard"}, False),
    "bitmask-soft": ("bitmask", {"mode": "soft"}, False),
    "bitmask-straight-through": ("bitmask", {"mode": "straight_through"}, False),
    "bitmask-cosine-soft": ("bitmask", {"mode": "soft", "weighting": "cosine", "bent_normals": True}, False),
    "bitmask-hdrp-round": ("bitmask", {"variant": "hdrp", "rounding": "round"}, False),
    "ssilvb-soft": ("ssilvb", {"mode": "soft", "weighting": "cosine"}, False),
    "ssilvb-hard-ambient": ("ssilvb", {"mode": "hard", "ambient": (0.2, 0.3, 0.4), "rounding": "floor"}, False),
    # The GLSL seed divides sliceCount + 1 slices by sliceCount: its visibility can exceed 1 (documented).
    "ssilvb-glsl": ("ssilvb", {"variant": "ssilvb_glsl"}, True),
    "ssilvb-glsl-soft": ("ssilvb", {"variant": "ssilvb_glsl", "mode": "soft"}, True),
    # Mesa's roundings: its normalize divides by the length unguarded, so a zero normal would be NaN light
    "ssilvb-glsl-mesa": ("ssilvb", {"variant": "ssilvb_glsl", "glsl_numerics": "mesa"}, True),
    "ssilvb-glsl-mesa-soft": ("ssilvb", {"variant": "ssilvb_glsl", "mode": "soft", "glsl_numerics": "mesa"}, True),
}

FAST_FRAMES = ("scene", "bg_nan", "single_pixel", "1x1", "discontinuity")


def _accepts(cls, name: str) -> bool:
    return name in inspect.signature(cls.__init__).parameters


def build(config: str, **overrides):
    method, options, _ = CONFIGS[config]
    cls = get_method(method)
    common = {"slices": 2, "steps": 3, "radius": 1.0, "seed": 1}
    kwargs = {k: v for k, v in common.items() if k in cls.options()} | options  # (PSSAO has no radius or seed)
    kwargs |= {k: v for k, v in overrides.items() if _accepts(cls, k)}
    return cls(**kwargs)


def leaves(gb: GBuffer) -> tuple[GBuffer, dict[str, torch.Tensor]]:
    """A copy of ``gb`` whose float inputs require grad."""
    inputs = {"depth": gb.depth.detach().clone().requires_grad_(True)}
    for key in ("normals", "light"):
        x = getattr(gb, key)
        if x is not None:
            inputs[key] = x.detach().clone().requires_grad_(True)
    g = GBuffer(inputs["depth"], gb.camera, normals=inputs.get("normals"), light=inputs.get("light"),
                mask=gb.mask, object_id=gb.object_id)
    return g, inputs


def check(config: str, gb: GBuffer, **overrides) -> None:
    module = build(config, **overrides)
    unbounded = CONFIGS[config][2]
    g, inputs = leaves(gb)
    out = module(g)
    outputs = {k: v for k, v in vars(out).items() if v is not None}
    for name, value in outputs.items():
        assert torch.isfinite(value).all(), f"{config}: non-finite {name}"
    vis = out.visibility
    if not unbounded:
        assert vis.min() >= 0 and vis.max() <= 1, f"{config}: visibility outside [0,1]: {vis.min()}..{vis.max()}"
    background = ~g.valid
    assert torch.all(vis[background] == 1), f"{config}: background visibility is not 1"
    weights = {k: torch.rand_like(v) for k, v in outputs.items()}
    loss = sum((v * weights[k]).sum() for k, v in outputs.items())
    if not loss.requires_grad:  # hard bitmasks are piecewise constant: no graph at all
        assert CONFIGS[config][1].get("mode", "hard") == "hard" and CONFIGS[config][0] in ("bitmask", "ssilvb"), config
        return
    params = [p for p in module.parameters() if p.requires_grad]
    grads = torch.autograd.grad(loss, list(inputs.values()) + params, allow_unused=True)
    for name, grad in zip(list(inputs) + [n for n, p in module.named_parameters() if p.requires_grad], grads):
        if grad is None:
            continue
        assert torch.isfinite(grad).all(), f"{config}: non-finite gradient for {name}"
        if name in inputs:
            mask = background.expand_as(grad)
            assert torch.all(grad[mask] == 0), f"{config}: gradient of {name} on background pixels"


@pytest.mark.parametrize("frame", FAST_FRAMES)
@pytest.mark.parametrize("config", list(CONFIGS))
def test_fast_matrix(config, frame):
    check(config, FRAMES[frame]())


@pytest.mark.slow
@pytest.mark.parametrize("frame", list(FRAMES))
@pytest.mark.parametrize("config", list(CONFIGS))
def test_full_matrix(config, frame):
    check(config, FRAMES[frame]())


STIFF = [
    {"radius": 1e-4}, {"radius": 1e6}, {"thickness": 0.0}, {"thickness": 1e-6}, {"thickness": 1e3}, {"thickness": 1e6},
    {"falloff": 0.0}, {"falloff": 1.0}, *({"tau": t} for t in (1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6)),
]


@pytest.mark.parametrize("overrides", STIFF, ids=[",".join(f"{k}={v:g}" for k, v in o.items()) for o in STIFF])
@pytest.mark.parametrize("config", list(CONFIGS))
def test_stiff_parameters(config, overrides):
    name, value = next(iter(overrides.items()))
    try:
        build(config, **overrides)
    except ValueError as err:  # outside the parameter's documented range: refused by name
        assert str(err).startswith(f"{name}:"), err
        return
    check(config, FRAMES["scene"](), **overrides)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("config", list(CONFIGS))
def test_dtypes(config, dtype):
    gb = FRAMES["scene"](torch.float32)
    low = GBuffer(gb.depth.to(dtype), gb.camera, normals=gb.normals.to(dtype), light=gb.light.to(dtype))
    out = build(config)(low)
    assert torch.isfinite(out.visibility).all()
    if CONFIGS[config][1].get("glsl_numerics") == "mesa":
        # The driver's roundings: whether a centre-texel fetch's back cosine rounds below -1 (no occlusion) or
        # not (the whole half circle) turns on the last bit, so another dtype's inputs give other pixels.
        return
    ref = build(config)(gb).visibility
    tol = {torch.float16: 0.05, torch.bfloat16: 0.15}.get(dtype, 1e-4)
    assert (out.visibility.float() - ref).abs().mean() < tol


@pytest.mark.parametrize("config", list(CONFIGS))
def test_layouts_and_batch_composition(config):
    gb = FRAMES["batch16"]()
    module = build(config)
    full = module(gb).visibility
    # Non-contiguous and channels-last inputs give the same numbers.
    depth_nc = gb.depth.transpose(-1, -2).contiguous().transpose(-1, -2)
    normals_cl = gb.normals.contiguous(memory_format=torch.channels_last)
    light_cl = gb.light.contiguous(memory_format=torch.channels_last)
    assert not depth_nc.is_contiguous()
    other = module(GBuffer(depth_nc, gb.camera, normals=normals_cl, light=light_cl)).visibility
    assert torch.allclose(full, other, atol=1e-12)
    # Results do not depend on batch composition.
    for i in (0, 5, 15):
        cam = PinholeCamera(gb.camera.intrinsics[i:i + 1], gb.camera.height, gb.camera.width)
        one = module(GBuffer(gb.depth[i:i + 1], cam, normals=gb.normals[i:i + 1], light=gb.light[i:i + 1])).visibility
        assert torch.allclose(full[i:i + 1], one, atol=1e-12)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
@pytest.mark.parametrize("config", list(CONFIGS))
def test_cuda_matches_cpu(config):
    gb = FRAMES["scene"](torch.float32)
    cpu = build(config)(gb).visibility
    gpu = build(config).cuda()(gb.to("cuda")).visibility.cpu()
    assert torch.isfinite(gpu).all()
    assert (cpu - gpu).abs().max() < 1e-3


# ---------------------------------------------------------------------------------------- range bounds
RANGE_FRAMES = ("sky_fltmax", "sky_1e20", "depth_1e14", "depth_1e19", "widest_camera_far", "narrowest_camera_far")


@pytest.mark.parametrize("frame", ["sky_fltmax", "widest_camera_far"])
@pytest.mark.parametrize("config", list(CONFIGS))
def test_engine_sky_and_widest_camera(config, frame):
    check(config, FRAMES[frame]())


@pytest.mark.slow
@pytest.mark.parametrize("frame", RANGE_FRAMES)
@pytest.mark.parametrize("config", list(CONFIGS))
def test_range_bounds_at_the_frames_scale(config, frame):
    """The same at radius and thickness of the frame's own scale (1e14 world units)."""
    check(config, FRAMES[frame](), radius=1e14, thickness=1e14)


@pytest.mark.parametrize("value", [torch.finfo(torch.float32).max, 1e20, 1e15])
@pytest.mark.parametrize("config", ["gtao", "pssao", "bitmask-soft", "hbao"])
def test_huge_sky_is_background_exactly_like_inf(config, value):
    """Depth at or above BACKGROUND_DEPTH is background: the result equals that of an inf sky, bit for bit."""
    from stability_cases import sky
    from torch_ao.gbuffer import BACKGROUND_DEPTH

    assert value >= BACKGROUND_DEPTH
    huge, inf = sky(value, torch.float32), sky(float("inf"), torch.float32)
    assert int((~huge.valid).sum()) == 3 * 16
    a, b = build(config)(huge).visibility, build(config)(inf).visibility
    assert torch.equal(a, b) and bool((a[..., :3, :] == 1).all())


def test_depth_just_below_the_background_threshold_is_geometry():
    from stability_cases import sky
    from torch_ao.gbuffer import BACKGROUND_DEPTH

    gb = sky(BACKGROUND_DEPTH * (1 - 1e-6), torch.float64)
    assert bool(gb.valid.all())


@pytest.mark.parametrize("fx, message", [
    (1e-20, "intrinsics: fx must be in [0.016, 1.6e+10] pixels for a 16x12 image"),
    (0.0159, "intrinsics: fx must be in [0.016, 1.6e+10]"),
    (1.61e10, "intrinsics: fx must be in [0.016, 1.6e+10]"),
])
def test_intrinsics_no_camera_can_have_are_refused(fx, message):
    K = torch.tensor([[fx, 0, 7.5], [0, 10.0, 5.5], [0, 0, 1]])
    with pytest.raises(ValueError) as err:
        PinholeCamera(K, 12, 16)
    assert str(err.value).startswith(message), err.value
    PinholeCamera(torch.tensor([[0.016, 0, 7.5], [0, 1.6e10, 5.5], [0, 0, 1]]), 12, 16)  # the bounds themselves


def test_principal_point_far_outside_is_refused():
    ok = torch.tensor([[10.0, 0, 7.5 + 64], [0, 10.0, 5.5], [0, 0, 1]])
    PinholeCamera(ok, 12, 16)  # 4 image sizes off
    bad = ok.clone()
    bad[0, 2] += 0.5
    with pytest.raises(ValueError, match=r"^intrinsics: cx must be within 64 pixels of the image centre 7.5, got 72"):
        PinholeCamera(bad, 12, 16)


def test_cli_ao_on_an_fltmax_sky_is_finite_with_the_sky_as_background(tmp_path, capsys):
    import numpy as np

    from stability_cases import sky
    from torch_ao.cli import main
    from torch_ao.io import read_npz, save_npz

    gb = sky(float("inf"), torch.float32)
    depth = gb.depth.clone()
    depth[..., :3, :] = torch.finfo(torch.float32).max
    src = save_npz(tmp_path / "sky_fltmax.npz", depth=depth, intrinsics=gb.camera.intrinsics[0].numpy())
    for method in ("gtao", "pssao", "bitmask"):
        out = tmp_path / f"{method}.npz"
        assert main(["ao", str(src), "--method", method, "--out", str(out)]) == 0
        assert "mean visibility nan" not in capsys.readouterr().out
        vis = read_npz(out)["visibility"]
        assert np.isfinite(vis).all() and (vis[0, :3] == 1).all() and (vis[0, 3:] < 1).any()


def test_cli_refuses_a_non_finite_output_naming_the_method(tmp_path, capsys, monkeypatch):
    """The safety net: a method that returned NaN is reported by name, exit 2, nothing written."""
    from torch_ao.cli import main
    from torch_ao.methods.base import AOOutput

    import torch_ao.commands.ao as ao_command

    real = ao_command.build_method

    def broken(name, args):
        module = real(name, args)

        class NaNMethod(torch.nn.Module):
            def forward(self, gb):
                out = module(gb)
                vis = out.visibility.clone()
                vis[..., 0, 0] = float("nan")
                return AOOutput(visibility=vis)
        return NaNMethod()

    monkeypatch.setattr(ao_command, "build_method", broken)
    out = tmp_path / "x.npz"
    assert main(["ao", "--method", "gtao", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("torch-ao ao: error: gtao: visibility has 1 NaN and 0 infinite values of ") and err.count("\n") == 1
    assert not out.exists()
