"""A call's fixed cost: what a layer pays per batch beside its kernels' work.

On a frame too small for the kernels' work to count (16x16 by default), one thread, it times the three stages
of a training step as a model makes it, each the median of ``--repeat`` calls after a warm-up: building the
`GBuffer` from tensors that need gradients, the module's forward, and the backward of its visibility's sum.
Beside each it counts the stage's reads back to the host (ATen's ``_local_scalar_dense``, ``item`` and
``is_nonzero``, which a dispatch mode sees on the CPU): on a GPU each is a wait for the GPU, and a stage that waits
cannot be captured in a CUDA graph.

    OMP_NUM_THREADS=1 python benchmarks/call_overhead.py [--size 16x16] [--repeat 300]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's torch_ao, not an installed copy

import torch_ao  # noqa: E402
from torch_ao.examples import example_gbuffer  # noqa: E402

_READS = (torch.ops.aten._local_scalar_dense.default, torch.ops.aten.item.default, torch.ops.aten.is_nonzero.default)

MODULES = {
    "GTAO": lambda: torch_ao.GTAO(),
    "HBAO": lambda: torch_ao.HBAO(),
    "BitmaskAO soft": lambda: torch_ao.BitmaskAO(mode="soft"),
    "SSILVB soft": lambda: torch_ao.SSILVB(mode="soft"),
}


class HostReads(TorchDispatchMode):
    """Lists the operators that turn a tensor's value into a Python number (``reads``), while it is entered."""

    def __init__(self):
        super().__init__()
        self.reads = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func in _READS:
            self.reads.append(func)
        return func(*args, **(kwargs or {}))


class Stage:
    """A stage's seconds, and with ``count_reads`` its reads back to the host."""

    def __init__(self, count_reads: bool = False):
        self.mode = HostReads() if count_reads else None
        self.seconds, self.reads = 0.0, 0

    def __enter__(self):
        if self.mode is not None:
            self.mode.__enter__()
        self.start = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self.start
        if self.mode is not None:
            self.mode.__exit__(*exc)
            self.reads = len(self.mode.reads)


def step(module, frame: torch_ao.GBuffer, count_reads: bool = False) -> tuple[Stage, Stage, Stage]:
    """One training step's stages: building the G-buffer, the forward, the backward."""
    depth = frame.depth.clone().requires_grad_(True)
    normals = frame.normals.clone().requires_grad_(True)
    stages = Stage(count_reads), Stage(count_reads), Stage(count_reads)
    with stages[0]:
        gbuffer = torch_ao.GBuffer(depth=depth, camera=frame.camera, normals=normals, light=frame.light)
    with stages[1]:
        out = module(gbuffer)
    with stages[2]:
        out.visibility.sum().backward()
    return stages


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="16x16", help="HxW of the frame")
    parser.add_argument("--repeat", type=int, default=300)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    H, W = (int(v) for v in args.size.split("x"))
    frame = example_gbuffer(H, W)
    print(f"| module ({H}x{W}, one thread) | `GBuffer(...)` µs | forward µs | backward µs | host reads: GBuffer, forward, backward |")
    print("|---|---:|---:|---:|---|")
    for name, make in MODULES.items():
        module = make()
        for _ in range(10):
            step(module, frame)
        runs = list(zip(*(step(module, frame) for _ in range(args.repeat))))
        medians = [1e6 * statistics.median(stage.seconds for stage in run) for run in runs]
        counts = [stage.reads for stage in step(module, frame, count_reads=True)]
        print(f"| {name} | {medians[0]:.0f} | {medians[1]:.0f} | {medians[2]:.0f} | {', '.join(map(str, counts))} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
