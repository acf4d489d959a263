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
from torch.utils._python_dispatch import TorchDispatchMode

import torch_ao
from test_kernels import built  # noqa: F401  (the fixture: the C++ kernels built)
from torch_ao.thickness import BackfaceThickness

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_vs_shader import frame_gbuffer  # noqa: E402

_READS = (torch.ops.aten._local_scalar_dense.default, torch.ops.aten.item.default, torch.ops.aten.is_nonzero.default)

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


class HostReads(TorchDispatchMode):
    """Counts the operators that turn a tensor's value into a Python number."""

    def __init__(self):
        super().__init__()
        self.reads = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func in _READS:
            self.reads.append(func)
        return func(*args, **(kwargs or {}))


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
