"""A position buffer read between texels (``fetch="bilinear"`` or ``"edge_aware"``) in the kernels: its four taps'
positions interpolated perspective-correctly, as the tensor path's ``Footprint.position`` (``walk.h``'s
``position_taps``, the CPU kernels'), for every method's forward. The buffer here is not the unprojected depth (each point moved
along its camera ray by up to 5 %, smoothly across the image), so a kernel that interpolated the depth instead
would be off by up to 0.4-0.7 in visibility. Gradients through such a read: tests/test_kernels_position_grads.py; the
CUDA kernels' (their full build's): tests/test_kernels_cuda.py."""
import pytest
import torch

import torch_ao
from kernel_agreement import assert_masks_agree, assert_values_agree, use_scalar_lanes_in_every_kernel
from test_kernels import built, rough_gbuffer  # noqa: F401  (built: the fixture)

MODULES = {
    "BitmaskAO hard": lambda backend, fetch: torch_ao.BitmaskAO(mode="hard", fetch=fetch, backend=backend),
    "BitmaskAO exact": lambda backend, fetch: torch_ao.BitmaskAO(variant="exact", mode="soft", fetch=fetch, backend=backend),
    "SSILVB soft": lambda backend, fetch: torch_ao.SSILVB(mode="soft", fetch=fetch, bent_normals=True, backend=backend),
    "GTAO": lambda backend, fetch: torch_ao.GTAO(fetch=fetch, bent_normals=True, backend=backend),
    "HBAO": lambda backend, fetch: torch_ao.HBAO(fetch=fetch, backend=backend),
    "SSAO": lambda backend, fetch: torch_ao.SSAO(fetch=fetch, backend=backend),
    "UE4SSAO": lambda backend, fetch: torch_ao.UE4SSAO(fetch=fetch, backend=backend),
    "PSSAO": lambda backend, fetch: torch_ao.PSSAO(fetch=fetch, backend=backend),
}


def moved_positions() -> tuple[torch_ao.GBuffer, torch_ao.GBuffer]:
    """The rough frame with a position buffer off its depth, and the frame of its depth alone."""
    gb = rough_gbuffer()
    light = torch.rand(gb.depth.shape[0], 3, *gb.depth.shape[-2:], generator=torch.Generator().manual_seed(3))
    scale = 1.0 + 0.05 * torch.sin(torch.linspace(0.0, 6.0, gb.depth.shape[-1])).view(1, 1, 1, -1)
    moved = torch_ao.GBuffer(depth=None, camera=gb.camera, position=gb.positions() * scale, light=light)
    return moved, torch_ao.GBuffer(depth=gb.depth, camera=gb.camera, light=light)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("fetch", ["bilinear", "edge_aware"])
@pytest.mark.parametrize("name", MODULES)
def test_a_position_buffer_read_between_texels_is_the_tensor_paths(built, name, fetch, lanes, monkeypatch):
    if lanes == "scalar":
        use_scalar_lanes_in_every_kernel(monkeypatch)
    gb, depth_only = moved_positions()
    with torch.no_grad():
        reference = MODULES[name]("torch", fetch)(gb)
        kernel = MODULES[name]("kernel", fetch)(gb)
        of_depth = MODULES[name]("torch", fetch)(depth_only)
    assert (reference.visibility - of_depth.visibility).abs().max() > 0.02  # (the buffer is read, not the depth)
    if name == "BitmaskAO hard":
        assert_masks_agree(kernel.visibility, reference.visibility, gb.valid, torch_ao.BitmaskAO().slices)
    else:
        assert_values_agree(kernel.visibility, reference.visibility, gb.valid, atol=1e-4, bound=0.05)
    for field in ("indirect", "bent_normal"):
        if getattr(reference, field) is not None:
            assert_values_agree(getattr(kernel, field), getattr(reference, field), gb.valid, atol=1e-4, bound=0.05)
