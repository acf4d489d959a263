"""What walking at half resolution costs and saves: forward (and soft forward+backward) time of a method at
``@full`` and ``@half`` on one frame, and the share of the half-resolution call spent outside the walk
(decimation, normals, the joint bilateral upsample).

    python benchmarks/bench_resolution.py                    # 640x360 example frame, 1 thread
    python benchmarks/bench_resolution.py --size 320x180 --threads 2

Times are medians after one warm-up: wall and process CPU time (the steadier one on a shared machine).
"""
from __future__ import annotations

import argparse
import os

import torch

import torch_ao
from torch_ao.bench import time_calls
from torch_ao.examples import example_gbuffer
from torch_ao.resolution import downsample_gbuffer

CASES = {
    "gtao high": lambda res: torch_ao.GTAO(preset=f"high@{res}"),
    "bitmask high (kernel)": lambda res: torch_ao.BitmaskAO(preset=f"high@{res}"),
    "bitmask high (tensor ops)": lambda res: torch_ao.BitmaskAO(preset=f"high@{res}", backend="torch"),
    "bitmask ultra (kernel)": lambda res: torch_ao.BitmaskAO(preset=f"ultra@{res}"),
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", default="640x360", help="WxH of the example frame")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--backward", action=argparse.BooleanOptionalAction, default=True,
                   help="also time soft BitmaskAO forward+backward")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    W, H = (int(s) for s in args.size.split("x"))
    gb = example_gbuffer(H, W)
    print(f"{W}x{H}, {args.threads} thread(s), load average {os.getloadavg()[0]:.1f}")
    print("| case | full ms (CPU) | half ms (CPU) | full / half (CPU) | half: outside the walk (CPU ms) |")
    print("| --- | --- | --- | --- | --- |")

    def timed(fn):
        return tuple(1e3 * t for t in time_calls(fn, repeats=args.repeats, warmup=1))

    with torch.no_grad():
        for name, make in CASES.items():
            full, half = make("full"), make("half")
            (fw, fc), (hw, hc) = timed(lambda: full(gb)), timed(lambda: half(gb))
            normals = gb.view_normals(half.normals_method)
            low = downsample_gbuffer(gb, 2, normals=normals)
            walk_only = make("full")
            _, wc = timed(lambda: walk_only(low))
            print(f"| {name} | {fw:.1f} ({fc:.1f}) | {hw:.1f} ({hc:.1f}) | {fw / hw:.2f} ({fc / hc:.2f}) | {hc - wc:.1f} |")
    if args.backward:
        for res in ("full", "half"):
            module = torch_ao.BitmaskAO(preset=f"high@{res}", mode="soft")
            depth = gb.depth.clone().requires_grad_(True)
            frame = torch_ao.GBuffer(depth=depth, camera=gb.camera, normals=gb.normals, mask=gb.mask)

            def step():
                module(frame).visibility.sum().backward()

            w, c = timed(step)
            print(f"| soft bitmask high fwd+bwd @{res} | {w:.1f} ms (CPU {c:.1f}) | | | |")


if __name__ == "__main__":
    main()
