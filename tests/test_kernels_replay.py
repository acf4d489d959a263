"""A backward that walks its slices again (in dual lanes or on a tape) samples the texels, and drops the samples, that
its forward did: every operation of lanes_dual.h and lanes_rev.h keeps the value lanes' value (a quotient divides, an
fma is fused). The frame here puts steps on texel rows: without jitter and with slices along screen directions,
a slice along the image's rows has its steps on the pixel's own row, whose vertical offset is a rounding residual
of zero; on the top row a bilinear footprint then reaches row -1 (the sample dropped, at the `drop` border) or
not, depending on that residual's sign. A replay whose quotient was a product by the reciprocal took the other side
there: its light, depth and normal gradients 5-15 % off the tensor walk's."""
import math

import pytest
import torch

import torch_ao
from torch_ao.camera import PinholeCamera
from torch_ao.gbuffer import GBuffer
from kernel_agreement import use_scalar_lanes
from test_kernels import built  # noqa: F401  (the fixture: the C++ kernels built)

ON_ROWS = dict(jitter=False, azimuth="screen", slices=2, steps=3)
MODULES = {
    "hard SSILVB, cosine": lambda backend: torch_ao.SSILVB(mode="hard", weighting="cosine", backend=backend, **ON_ROWS),
    "soft SSILVB": lambda backend: torch_ao.SSILVB(mode="soft", backend=backend, **ON_ROWS),
    "soft exact union": lambda backend: torch_ao.BitmaskAO(variant="exact", mode="soft", backend=backend, **ON_ROWS),
    "GTAO": lambda backend: torch_ao.GTAO(backend=backend, **ON_ROWS),
    "HBAO": lambda backend: torch_ao.HBAO(backend=backend, **ON_ROWS),
}


def frame() -> tuple[torch.Tensor, PinholeCamera, torch.Tensor]:
    """tests/test_kernels.py's rough depth at 8x16 (background in the top left), and a light."""
    H, W = 8, 16
    v, u = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    noise = torch.rand(1, 1, H, W, generator=torch.Generator().manual_seed(11))
    depth = 2.0 + 0.6 * torch.sin(9 * u + 4 * v) * torch.cos(7 * v) + 0.05 * noise
    depth[:, :, :5, :9] = math.inf
    light = 0.1 + 0.8 * torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(1))
    return depth, PinholeCamera.from_fov(55.0, H, W), light


def gradients(name: str, backend: str) -> dict[str, torch.Tensor]:
    depth, camera, light = frame()
    depth, light = depth.requires_grad_(), light.requires_grad_()
    normals = GBuffer(depth=depth, camera=camera).view_normals().detach().requires_grad_()
    out = MODULES[name](backend)(GBuffer(depth=depth, camera=camera, normals=normals, light=light))
    loss = 0.0
    for value in (out.visibility, getattr(out, "indirect", None)):
        if value is not None:
            weights = torch.linspace(0.5, 1.5, value.numel(), dtype=torch.float64).view_as(value)
            loss = loss + (value.double() * weights).sum()
    leaves = {"depth": depth, "normals": normals, "light": light}
    grads = torch.autograd.grad(loss, list(leaves.values()), allow_unused=True)
    return {key: g.double() for key, g in zip(leaves, grads) if g is not None}


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("name", MODULES)
def test_a_replay_on_texel_rows_gives_the_tensor_walks_gradients(built, name, lanes, monkeypatch):
    """Against the float32 tensor walk, whose forward takes the same side of every boundary as the kernel's; in the
    SIMD lanes and in the scalar lanes (the CUDA thread's arithmetic)."""
    if lanes == "scalar":
        from torch_ao.kernels import bitmask, launch, soft_bitmask, soft_exact, walk_grad

        for module in (bitmask, launch, soft_bitmask, soft_exact, walk_grad):
            use_scalar_lanes(monkeypatch, module)
    reference, kernel = gradients(name, "torch"), gradients(name, "kernel")
    assert set(kernel) == set(reference) and "depth" in kernel
    for key, want in reference.items():
        assert want.abs().max() > 0, key  # (something flows: the comparison means something)
        error = float((kernel[key] - want).norm() / want.norm())
        assert error < 1e-4, (key, error)
