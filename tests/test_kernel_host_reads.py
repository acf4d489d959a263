"""A kernel call reads nothing back to the host: no tensor's value is turned into a Python number on the way to
the kernels, forward or backward. On a GPU such a read makes the call wait for the GPU, and a call that waits
cannot be captured in a CUDA graph. On the CPU the same reads are ATen's ``_local_scalar_dense`` (``.item()``,
``float(t)``, ``bool(t)``), which a dispatch mode sees, so CI checks it without a GPU; on a GPU
``test_kernel_calls_replay_in_a_cuda_graph`` captures the same calls.
"""
import sys
from pathlib import Path

import pytest
import torch

import torch_ao
from test_kernels import built  # noqa: F401  (the fixture: the C++ kernels built)
from torch_ao.thickness import BackfaceThickness

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_vs_shader import frame_gbuffer  # noqa: E402
from call_overhead import HostReads  # noqa: E402  (on the CPU: ATen's _local_scalar_dense, item, is_nonzero)

#: one module per kernel family, as their CUDA calls are made (backend="kernel": an uncovered call raises)
MODULES = {
    "bitmask hard": lambda: torch_ao.BitmaskAO(preset="high", backend="kernel"),
    "bitmask cosine": lambda: torch_ao.BitmaskAO(preset="high", weighting="cosine", backend="kernel"),
    "exact + backface + edge_aware": lambda: torch_ao.BitmaskAO(preset="high", variant="exact", thickness=BackfaceThickness(),
                                                                fetch="edge_aware", backend="kernel"),
    "soft": lambda: torch_ao.BitmaskAO(preset="high", mode="soft", backend="kernel"),
    "gtao hard cut": lambda: torch_ao.GTAO(preset="high", backend="kernel"),
    "gtao falloff": lambda: torch_ao.GTAO(preset="high", falloff_range=0.5, backend="kernel"),
    "hbao": lambda: torch_ao.HBAO(preset="high", backend="kernel"),
    "ue4 ssao": lambda: torch_ao.UE4SSAO(backend="kernel"),
    "pssao": lambda: torch_ao.PSSAO(backend="kernel"),
    "ssao": lambda: torch_ao.SSAO(backend="kernel"),
}


def _gbuffer(device="cpu", gradients=False):
    g = frame_gbuffer("floor_wall", 24, 32).to(device=device)
    if not gradients:
        return g
    return torch_ao.GBuffer(depth=g.depth.clone().requires_grad_(True), camera=g.camera,
                            normals=g.normals.clone().requires_grad_(True), light=g.light,
                            backface_depth=g.backface_depth)


@pytest.mark.parametrize("name", MODULES)
def test_a_kernel_forward_reads_nothing_back(built, name):
    module, g = MODULES[name](), _gbuffer()
    module(g)  # (the first call builds and caches what later calls reuse)
    with torch.no_grad(), HostReads() as mode:
        out = module(g)
    assert torch.isfinite(out.visibility).all()
    assert mode.reads == []


@pytest.mark.parametrize("name", [n for n in MODULES if n not in ("bitmask hard",)])  # (hard uniform: no gradient)
def test_a_kernel_forward_and_backward_read_nothing_back(built, name):
    module, g = MODULES[name](), _gbuffer(gradients=True)
    module(g).visibility.sum().backward()
    module.zero_grad()
    with HostReads() as mode:
        module(g).visibility.sum().backward()
    assert g.depth.grad is not None and torch.isfinite(g.depth.grad).all()
    assert mode.reads == []


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("name", MODULES)
def test_kernel_calls_replay_in_a_cuda_graph(name):
    module, g = MODULES[name]().cuda(), _gbuffer("cuda")
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side), torch.no_grad():
        for _ in range(2):  # warm-up outside the capture: kernels loaded, settings and derived buffers cached
            eager = module(g).visibility.clone()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph), torch.no_grad():
        captured = module(g).visibility
    graph.replay()
    torch.cuda.synchronize()
    assert torch.equal(captured, eager)


def test_a_gbuffer_reads_its_checks_back_once():
    """Every value check of a G-buffer with each optional buffer (a 0/1 float mask converted, object ids, a back-face
    layer, a position buffer) is read back in one read, and its camera's conversion and expansion read nothing."""
    g = frame_gbuffer("floor_wall", 24, 32)
    B = 2
    depth = g.depth.expand(B, -1, -1, -1)
    buffers = dict(normals=g.normals.expand(B, -1, -1, -1), light=g.light.expand(B, -1, -1, -1),
                   mask=torch.ones_like(depth), object_id=torch.zeros_like(depth, dtype=torch.int32),
                   backface_depth=depth + 0.3, position=g.positions().expand(B, -1, -1, -1))
    camera = g.camera.to(dtype=torch.float64)  # (batch 1: the G-buffer converts and expands it)
    with HostReads() as mode:
        built = torch_ao.GBuffer(depth=depth.double(), camera=camera, **buffers)
    assert len(mode.reads) == 1
    assert built.camera.batch_size == B and built.camera.intrinsics.dtype == torch.float64
    assert built.mask.dtype == torch.bool and torch.equal(built.valid, g.valid.expand(B, -1, -1, -1))
    with HostReads() as mode:
        g.camera.to(dtype=torch.float64).expand(B).to(dtype=torch.float32)
    assert mode.reads == []


@pytest.mark.parametrize("fault, message", [
    (dict(normals=torch.nan), "normals: non-finite values on valid"),
    (dict(light=torch.inf), "light: non-finite values on valid"),
    (dict(normals=0.0), "normals: zero-length normals"),
    (dict(mask=0.5), "mask: expected bool or 0/1 values"),
    (dict(object_id=-1), "object_id: ids must be >= 0"),
    (dict(backface_depth=-1.0), r"backface_depth: expected values >= depth on valid pixels, 1 are not"),
    (dict(depth=-1.0), "depth: negative values found"),
])
def test_a_gbuffer_refuses_the_checks_it_reads_at_once(fault, message):
    """Each check read back at the end still raises its own error, naming its buffer (one texel wrong)."""
    g = frame_gbuffer("floor_wall", 24, 32)
    buffers = dict(depth=g.depth.clone(), normals=g.normals.clone(), light=g.light.clone(),
                   mask=torch.ones_like(g.depth), object_id=torch.zeros_like(g.depth, dtype=torch.int64),
                   backface_depth=g.depth + 0.3)
    (name, value), = fault.items()
    texel = (0, slice(None), 20, 16)  # (a floor pixel: valid)
    if name == "backface_depth":
        buffers[name][texel] = buffers["depth"][texel] + value
    else:
        buffers[name][texel] = value
    with pytest.raises(ValueError, match=message):
        torch_ao.GBuffer(camera=g.camera, **buffers)
