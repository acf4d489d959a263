"""GTAO forward + backward (gradients of depth and radius) against its forward, kernel and tensor path.

``GTAO(variant="exact")`` (bilinear fetch, dropped border: what the kernel's backward covers) on
``torch_ao.examples.example_gbuffer`` with ``depth.requires_grad``; the loss is the visibility's sum.
Rows per ``slices x steps``: the kernel's forward (no gradient), the kernel's forward + backward,
the tensor path's forward + backward, and the ratios to the kernel's forward. Median of ``--repeat``
calls after one warm-up; the machine may be shared: read the ratios of one run.

    OMP_NUM_THREADS=1 python benchmarks/bench_gtao_grad.py --threads 1
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torch_ao.examples import example_gbuffer  # noqa: E402
from torch_ao.gbuffer import GBuffer  # noqa: E402
from torch_ao.methods.gtao import GTAO  # noqa: E402


def _median_seconds(fn, repeat: int) -> float:
    fn()  # warm-up (builds the kernels)
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="640x360", help="WxH")
    parser.add_argument("--settings", default="4x4,4x8", help="comma-separated slices x steps")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    W, H = map(int, args.size.split("x"))
    gb0 = example_gbuffer(H, W)
    print(f"{W}x{H}, {args.threads} thread(s), median of {args.repeat}")
    print("slices x steps | kernel fwd (ms) | kernel fwd+bwd (ms) | torch fwd+bwd (ms) | kernel ratio | torch ratio")
    for setting in args.settings.split(","):
        slices, steps = map(int, setting.split("x"))

        def forward():
            with torch.no_grad():
                GTAO(slices=slices, steps=steps, backend="kernel")(gb0)

        def forward_backward(backend):
            def run():
                depth = gb0.depth.clone().requires_grad_(True)
                GTAO(slices=slices, steps=steps, backend=backend)(GBuffer(depth=depth, camera=gb0.camera)).visibility.sum().backward()
            return run

        fwd = _median_seconds(forward, args.repeat)
        kernel = _median_seconds(forward_backward("kernel"), args.repeat)
        tensor = _median_seconds(forward_backward("torch"), args.repeat)
        print(f"{slices} x {steps} | {1e3 * fwd:.1f} | {1e3 * kernel:.1f} | {1e3 * tensor:.1f} | "
              f"{kernel / fwd:.1f} | {tensor / fwd:.1f}")


if __name__ == "__main__":
    main()
