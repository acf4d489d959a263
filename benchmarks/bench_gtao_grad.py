"""The walk's backward (the horizon kernels' and the SSAO family's: gradients of depth and the parameters)
against their forward, kernel and tensor path.

``GTAO`` (``--methods``: ``gtao`` the exact variant, ``hdrp``, ``ue4``), ``HBAO`` (``hbao``: incremental,
``hbao-max``), ``UE4SSAO`` (``ue4ssao``: evenly spaced directions), ``PSSAO`` (``pssao``) and ``SSAO`` (``ssao``: the
hemisphere kernel's 2 x slices x steps points, its logistic step) on ``torch_ao.examples.example_gbuffer`` with
``depth.requires_grad``; the loss is the
visibility's sum. Rows per method and ``slices x steps``: the kernel's forward (no gradient), the kernel's
forward + backward, the tensor path's forward + backward, and the ratios to the kernel's forward. Median of
``--repeat`` calls after one warm-up; the machine may be shared: read the ratios of one run.

    OMP_NUM_THREADS=1 python benchmarks/bench_gtao_grad.py --threads 1 --methods gtao,hdrp,ue4,hbao,hbao-max
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
from torch_ao.methods.hbao import HBAO  # noqa: E402
from torch_ao.methods.pssao import PSSAO  # noqa: E402
from torch_ao.methods.ssao import SSAO  # noqa: E402
from torch_ao.methods.ue4_ssao import UE4SSAO  # noqa: E402

#: the modules benchmarked
METHODS = {"gtao": (GTAO, {}), "hdrp": (GTAO, {"variant": "hdrp"}), "ue4": (GTAO, {"variant": "ue4"}),
           "hbao": (HBAO, {}), "hbao-max": (HBAO, {"accumulate": "max"}),
           "ue4ssao": (UE4SSAO, {"sample_set": "uniform"}), "pssao": (PSSAO, {}), "ssao": (SSAO, {"softness": 0.05})}


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
    parser.add_argument("--methods", default="gtao,hbao", help=f"comma-separated, of {', '.join(METHODS)}")
    parser.add_argument("--no-torch", action="store_true", help="skip the tensor path's rows (its column reads nan)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    W, H = map(int, args.size.split("x"))
    gb0 = example_gbuffer(H, W)
    print(f"{W}x{H}, {args.threads} thread(s), median of {args.repeat}")
    print("method | slices x steps | kernel fwd (ms) | kernel fwd+bwd (ms) | torch fwd+bwd (ms) | kernel ratio | "
          "torch ratio")
    for method in args.methods.split(","):
        make, options = METHODS[method]
        for setting in args.settings.split(","):
            slices, steps = map(int, setting.split("x"))

            def module(backend):
                return make(slices=slices, steps=steps, backend=backend, **options)

            def forward():
                with torch.no_grad():
                    module("kernel")(gb0)

            def forward_backward(backend):
                def run():
                    depth = gb0.depth.clone().requires_grad_(True)
                    module(backend)(GBuffer(depth=depth, camera=gb0.camera)).visibility.sum().backward()
                return run

            fwd = _median_seconds(forward, args.repeat)
            kernel = _median_seconds(forward_backward("kernel"), args.repeat)
            tensor = float("nan") if args.no_torch else _median_seconds(forward_backward("torch"), args.repeat)
            print(f"{method} | {slices} x {steps} | {1e3 * fwd:.1f} | {1e3 * kernel:.1f} | {1e3 * tensor:.1f} | "
                  f"{kernel / fwd:.1f} | {tensor / fwd:.1f}")


if __name__ == "__main__":
    main()
