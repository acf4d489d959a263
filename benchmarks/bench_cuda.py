"""The CUDA kernels' times against the one-walk issue's GPU targets, timed with CUDA events.

    python benchmarks/bench_cuda.py                        # 1920x1080 floor/wall frame on the GPU
    python benchmarks/bench_cuda.py --device cpu --size 160x90 --repeat 3   # the same cases on the CPU

Every case forces ``backend="kernel"`` (a call the kernels do not cover raises instead of running the tensor
walk), except the ``torch`` rows, which run the tensor walk on the same device for comparison. Each case is
warmed up (the first call compiles the kernels), then timed ``--repeat`` times; the median is reported, with
the peak memory the call allocated on the device. The frame is a floor meeting a wall with back faces 0.3
world units behind every surface (bench_vs_shader.py's ``floor_wall``).

Targets (the anchors: bitmask AO 0.51 ms at 1080p on an RTX 2080, XeGTAO High 0.56 ms on an RTX 2060):
``high`` hard bitmask AO at 1920x1080 <= 0.15 ms, the exact + back-face pipeline <= 0.3 ms, soft forward+backward
with G-buffer gradients <= 1 ms, batch 8 <= 8x batch 1.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))

from bench_vs_shader import frame_gbuffer  # noqa: E402

import torch_ao  # noqa: E402
from torch_ao.fitted import FittedPipeline  # noqa: E402
from torch_ao.thickness import BackfaceThickness  # noqa: E402


def cases() -> dict:
    """``{label: (make module, gradients)}``; gradients: ``None`` (forward under no_grad), ``"params"``
    (the module's float parameters), ``"gbuffer"`` (depth and normals too)."""
    kernel = dict(backend="kernel")
    exact = dict(variant="exact", thickness=BackfaceThickness(), fetch="edge_aware", **kernel)
    return {
        "bitmask high, hard": (lambda: torch_ao.BitmaskAO(preset="high", **kernel), None),
        "bitmask high, hard (torch)": (lambda: torch_ao.BitmaskAO(preset="high", backend="torch"), None),
        "bitmask very_high, hard": (lambda: torch_ao.BitmaskAO(preset="very_high", **kernel), None),
        "bitmask high, cosine": (lambda: torch_ao.BitmaskAO(preset="high", weighting="cosine", **kernel), None),
        "exact + backface + edge_aware, high": (lambda: torch_ao.BitmaskAO(preset="high", **exact), None),
        "shipped pipeline (very_high + denoiser)": (lambda: FittedPipeline(
            "bitmask", {"preset": "very_high", "thickness_model": "backface", "fetch": "edge_aware", **kernel},
            denoiser=True), None),
        "gtao high": (lambda: torch_ao.GTAO(preset="high", **kernel), None),
        "gtao high + denoiser": (lambda: FittedPipeline("gtao", {"preset": "high", **kernel}, denoiser=True), None),
        "soft high, fwd+bwd, params": (lambda: torch_ao.BitmaskAO(preset="high", mode="soft", **kernel), "params"),
        "soft high, fwd+bwd, gbuffer": (lambda: torch_ao.BitmaskAO(preset="high", mode="soft", **kernel), "gbuffer"),
        "soft high, fwd+bwd, gbuffer (torch)": (lambda: torch_ao.BitmaskAO(preset="high", mode="soft",
                                                                           backend="torch"), "gbuffer"),
        "exact + backface, fwd+bwd, gbuffer": (lambda: torch_ao.BitmaskAO(preset="high", **exact), "gbuffer"),
        "gtao high, fwd+bwd, gbuffer": (lambda: torch_ao.GTAO(preset="high", **kernel), "gbuffer"),
        "ssilvb_glsl soft 4 x 4, fwd+bwd, gbuffer": (lambda: torch_ao.SSILVB(variant="ssilvb_glsl", mode="soft", slices=4,
                                                                           steps=4, **kernel), "gbuffer"),
        # the full build's (launch.full_walk): slices drawn by the projected normal's density, beside the lean
        # build's rows above
        "bitmask high, hard, projected-normal slices": (lambda: torch_ao.BitmaskAO(
            preset="high", slice_sampling="projected_normal", **kernel), None),
        "soft high, fwd+bwd, gbuffer, projected-normal slices": (lambda: torch_ao.BitmaskAO(
            preset="high", mode="soft", slice_sampling="projected_normal", **kernel), "gbuffer"),
    }


def batched(gbuffer, batch: int):
    """``gbuffer`` repeated ``batch`` times along the batch dimension."""
    if batch == 1:
        return gbuffer
    cam = gbuffer.camera
    camera = torch_ao.PinholeCamera(cam.intrinsics.expand(batch, -1, -1).contiguous(), cam.height, cam.width)
    rep = lambda t: None if t is None else t.repeat(batch, 1, 1, 1)  # noqa: E731
    return torch_ao.GBuffer(depth=rep(gbuffer.depth), camera=camera, normals=rep(gbuffer.normals),
                            light=rep(gbuffer.light), backface_depth=rep(gbuffer.backface_depth))


def call(make, gradients, gbuffer, device):
    """One call of the case on ``gbuffer``: a function running it once."""
    module = make().to(device)
    if gradients is None:
        def forward():
            with torch.no_grad():
                module(gbuffer)
        return forward
    gb = gbuffer
    if gradients == "gbuffer":
        gb = torch_ao.GBuffer(depth=gbuffer.depth.detach().clone().requires_grad_(True), camera=gbuffer.camera,
                              normals=gbuffer.normals.detach().clone().requires_grad_(True), light=gbuffer.light,
                              backface_depth=gbuffer.backface_depth)

    def forward_backward():
        module.zero_grad(set_to_none=True)
        out = module(gb)
        out.visibility.sum().backward()
    return forward_backward


def median_ms(fn, device, warmup: int, repeat: int) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        if device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            end.record()
            end.synchronize()
            times.append(start.elapsed_time(end))
        else:
            t = time.perf_counter()
            fn()
            times.append(1000 * (time.perf_counter() - t))
    return statistics.median(times)


def write_json(args, device, rows) -> None:
    Path(args.json).write_text(json.dumps({"device": str(device), "size": args.size, "rows": rows,
                                           "name": torch.cuda.get_device_name() if device.type == "cuda" else ""},
                                          indent=1))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda")
    p.add_argument("--size", default="1920x1080", help="WIDTHxHEIGHT")
    p.add_argument("--repeat", type=int, default=20, help="timed calls per case (median reported)")
    p.add_argument("--batch", type=int, default=8, help="the batched row's batch size")
    p.add_argument("--cases", nargs="*", help="labels' substrings to run (default: all)")
    p.add_argument("--json", help="also write the results here")
    args = p.parse_args(argv)
    device = torch.device(args.device)
    width, height = (int(v) for v in args.size.lower().split("x"))
    gbuffer = frame_gbuffer("floor_wall", height, width).to(device=device)
    rows = []
    chosen = {k: v for k, v in cases().items() if not args.cases or any(s in k for s in args.cases)}
    chosen[f"bitmask high, hard, batch {args.batch}"] = chosen.get("bitmask high, hard", cases()["bitmask high, hard"])
    for label, (make, gradients) in chosen.items():
        gb = batched(gbuffer, args.batch) if label.endswith(f"batch {args.batch}") else gbuffer
        try:
            fn = call(make, gradients, gb, device)
            if device.type == "cuda":
                torch.cuda.synchronize()
                torch.cuda.reset_peak_memory_stats()
                base = torch.cuda.memory_allocated()
            # the tensor walk's rows are seconds a call at 1080p: a few calls give its scale
            ms = median_ms(fn, device, warmup=1 if "(torch)" in label else 2,
                           repeat=min(args.repeat, 3) if "(torch)" in label else args.repeat)
            mb = (torch.cuda.max_memory_allocated() - base) / 2**20 if device.type == "cuda" else float("nan")
            rows.append({"case": label, "ms": ms, "peak_mb": mb})
            print(f"{label:45s} {ms:9.3f} ms  {mb:8.1f} MB", flush=True)
        except Exception as exc:  # noqa: BLE001 - a case that fails is reported and the others still run
            rows.append({"case": label, "error": f"{type(exc).__name__}: {exc}"})
            print(f"{label:45s} FAILED {type(exc).__name__}: {str(exc)[:300]}", flush=True)
        if args.json:  # after every row, so that a run stopped by its time limit keeps the rows it measured
            write_json(args, device, rows)
    one = next((r["ms"] for r in rows if r["case"] == "bitmask high, hard" and "ms" in r), None)
    many = next((r["ms"] for r in rows if r["case"].endswith(f"batch {args.batch}") and "ms" in r), None)
    if one and many:
        print(f"batch {args.batch} / batch 1: {many / one:.2f}x (target <= {args.batch}x)")
    return 1 if any("error" in r for r in rows) else 0


if __name__ == "__main__":
    raise SystemExit(main())
