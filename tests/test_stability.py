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
