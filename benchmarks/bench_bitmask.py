"""Memory and time of BitmaskAO / SSILVB forward(+backward) on CPU (or CUDA if asked).

Each case runs in its own subprocess, so peak memory is honest: the peak resident set size
of the child's address space (``peak_memory.py``: ``VmHWM``) minus its resident size just before the timed call (after imports and
building the G-buffer). On CUDA, ``torch.cuda.max_memory_allocated`` is reported instead.

    python benchmarks/bench_bitmask.py                 # 640x360 table + 1280x720 soft fwd+bwd
    python benchmarks/bench_bitmask.py --quick         # 320x180 only
    python benchmarks/bench_bitmask.py --size 160x90 --repeat 5   # any size (no 1280x720 row); warm, min of 4
    python benchmarks/bench_bitmask.py --scene stairs --no-720p   # a reference scene's ray-traced G-buffer
    python benchmarks/bench_bitmask.py --soft-kernel --repeat 3   # the soft kernel: gradients of radius and
                                                                  # thickness, or of the G-buffer too, 640x360
                                                                  # and 1280x720 (--steps 4: 4 x 4)

The default frame is a floor meeting a wall (``torch_ao.examples.floor_wall_gbuffer``). The "dense" rows
use ``thickness=1000, sector_epsilon=0``: every sample's interval is non-empty, the worst case for the
soft union (which sweeps only the steps that occlude something).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path


def child(args: dict) -> dict:
    import torch

    from peak_memory import PeakMemory

    from torch_ao.examples import floor_wall_gbuffer
    from torch_ao.gbuffer import GBuffer
    from torch_ao.methods.bitmask import BitmaskAO

    torch.set_num_threads(args.get("threads", 1))
    H, W = args["height"], args["width"]
    if args.get("gbuffer"):
        from torch_ao.io import load_gbuffer

        gb, _ = load_gbuffer(args["gbuffer"])
    else:
        gb, _ = floor_wall_gbuffer(H, W, wall_distance=1.0, light_direction=(0.3, 0.8, 0.5))
    device = args.get("device", "cpu")
    grad = args["backward"]
    params_only = args.get("params_only", False)  # the gradients of radius and thickness, not the G-buffer's
    depth = gb.depth.to(device).requires_grad_(grad and not params_only)
    normals = gb.normals.to(device).requires_grad_(grad and not params_only)
    light = gb.light.to(device).requires_grad_(grad and not params_only)
    gbuf = GBuffer(depth, gb.camera.to(device), normals=normals, light=light)
    extra = {} if args.get("chunk_size") is None else {"chunk_size": args["chunk_size"], "recompute": True}
    if args.get("dense"):
        extra.update(thickness=1000.0, sector_epsilon=0.0)
    if args.get("backend"):
        extra["backend"] = args["backend"]
    module = BitmaskAO(mode=args["mode"], slices=4, steps=args.get("steps", 8), radius=1.0, **{"thickness": 0.5, **extra},
                       indirect=args["indirect"], weighting=args.get("weighting", "uniform"),
                       variant=args.get("variant", "default")).to(device)

    peak = PeakMemory().start()  # the resident size now; the peak is read after the calls
    if device != "cpu":
        torch.cuda.reset_peak_memory_stats()
        torch.cuda.synchronize()
    def call():
        t0, c0 = time.perf_counter(), time.process_time()
        ctx = torch.enable_grad() if grad else torch.no_grad()
        with ctx:
            out = module(gbuf)
            if grad:
                loss = out.visibility.sum() + (out.indirect.sum() if out.indirect is not None else 0)
                loss.backward()
        if device != "cpu":
            torch.cuda.synchronize()
        return time.perf_counter() - t0, time.process_time() - c0, out

    seconds, cpu, out = call()
    if args.get("repeat", 1) > 1:  # warm: the first call above is the warm-up; report the fastest of the rest
        seconds, cpu = min(call()[:2] for _ in range(args["repeat"] - 1))
    peak.stop()
    result = {"seconds": seconds, "cpu_seconds": cpu, "peak_mb": peak.mb, "baseline_mb": peak.baseline_mb}
    if device != "cpu":
        result["peak_mb"] = torch.cuda.max_memory_allocated() / 2**20
    valid = gbuf.valid
    graded = [module.radius.grad, module.thickness.grad] if params_only else [depth.grad]
    result["finite"] = bool(torch.isfinite(out.visibility[valid.expand_as(out.visibility)]).all()) and (
        not grad or all(bool(torch.isfinite(g).all()) for g in graded))
    return result


def run_case(**args) -> dict:
    cmd = [sys.executable, __file__, "--child", json.dumps(args)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--quick", action="store_true", help="320x180 only")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--chunk-size", type=int, default=None)
    parser.add_argument("--no-720p", action="store_true")
    parser.add_argument("--repeat", type=int, default=1,
                        help="calls per case; >1: time the fastest call after the first (warm-up)")
    parser.add_argument("--size", default=None, help="WIDTHxHEIGHT instead of 640x360 (skips the 1280x720 row)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads in each case (default 1)")
    parser.add_argument("--scene", default=None, help="a reference scene (torch_ao.reference.list_scenes()) instead "
                        "of the floor/wall frame: its G-buffer ray traced at the benchmark size")
    parser.add_argument("--soft-kernel", action="store_true", help="the soft kernel's table (gradients of radius and "
                        "thickness, or of the G-buffer too; kernel against tensor path) at 640x360 and 1280x720 instead")
    parser.add_argument("--steps", type=int, default=8, help="steps per side of the --soft-kernel table (4 slices)")
    a = parser.parse_args()
    if a.child:
        print(json.dumps(child(json.loads(a.child))))
        return
    if a.soft_kernel:
        soft_kernel_table(a)
        return
    H, W = (180, 320) if a.quick else (360, 640)
    if a.size:
        W, H = (int(v) for v in a.size.lower().split("x"))
    common = dict(height=H, width=W, device=a.device, chunk_size=a.chunk_size, threads=a.threads, repeat=a.repeat)
    frame = "a floor meeting a wall"
    if a.scene:
        import tempfile

        from torch_ao.io import save_npz
        from torch_ao.reference import get_scene, render_reference

        ref = render_reference(get_scene(a.scene), height=H, width=W, spp=2, max_distance=1.0, progress=False,
                               uniform=False)
        common["gbuffer"] = str(save_npz(Path(tempfile.mkdtemp()) / f"{a.scene}.npz", ref.gbuffer))
        frame = f"scene {a.scene!r}"
    rows = [
        ("hard forward, AO only", dict(mode="hard", backward=False, indirect=False)),
        ("hard forward, AO + indirect", dict(mode="hard", backward=False, indirect=True)),
        ("soft forward, AO only", dict(mode="soft", backward=False, indirect=False)),
        ("soft forward+backward, AO only", dict(mode="soft", backward=True, indirect=False)),
        ("soft forward+backward, AO + indirect", dict(mode="soft", backward=True, indirect=True)),
        ("straight-through forward+backward, AO only", dict(mode="straight_through", backward=True, indirect=False)),
        ("dense: hard forward, AO only", dict(mode="hard", backward=False, indirect=False, dense=True)),
        ("dense: soft forward+backward, AO only", dict(mode="soft", backward=True, indirect=False, dense=True)),
    ]
    print(f"BitmaskAO, {W}x{H} ({frame}), 4 slices x 8 steps per side, device={a.device}, torch threads={a.threads}")
    print(f"{'case':46s} {'time s':>8s} {'peak MB':>9s}")
    results = {}
    for name, args in rows:
        r = run_case(**common, **args)
        results[name] = r
        print(f"{name:46s} {r['seconds']:8.2f} {r['peak_mb']:9.0f}{'' if r['finite'] else '  NON-FINITE'}", flush=True)
    hard = results["hard forward, AO only"]["seconds"]
    soft = results["soft forward+backward, AO only"]["seconds"]
    print(f"soft forward+backward / hard forward = {soft / hard:.2f}x")
    dense = results["dense: soft forward+backward, AO only"]["seconds"] / results["dense: hard forward, AO only"]["seconds"]
    print(f"dense: soft forward+backward / hard forward = {dense:.2f}x")
    print(f"AO+indirect / AO-only (hard forward) = {results['hard forward, AO + indirect']['seconds'] / hard:.2f}x")
    if not a.quick and not a.no_720p and not a.size and not a.scene:
        r = run_case(height=720, width=1280, device=a.device, chunk_size=a.chunk_size, threads=a.threads, mode="soft",
                     backward=True, indirect=False)
        print(f"{'1280x720 soft forward+backward, AO only':46s} {r['seconds']:8.2f} {r['peak_mb']:9.0f}")


def soft_kernel_table(a) -> None:
    """The soft kernel's rows: forward+backward of the scalar radius and thickness (the G-buffer without
    gradients, as ``torch-ao fit``), and of depth and normals too ("G-buffer"; with them the hard cosine and the
    exact union's kernels' backwards), against the kernel's hard forward and the tensor path, CPU and wall time."""
    gbuffer = dict(params_only=False)
    rows = [
        ("hard forward (kernel)", dict(mode="hard", backward=False, backend="kernel")),
        ("soft fwd+bwd (kernel)", dict(mode="soft", backward=True, backend="kernel")),
        ("soft fwd+bwd, cosine (kernel)", dict(mode="soft", backward=True, backend="kernel", weighting="cosine")),
        ("soft fwd+bwd, G-buffer (kernel)", dict(mode="soft", backward=True, backend="kernel", **gbuffer)),
        ("soft fwd+bwd, G-buffer, cosine (kernel)", dict(mode="soft", backward=True, backend="kernel",
                                                         weighting="cosine", **gbuffer)),
        ("straight-through fwd+bwd, G-buffer (kernel)", dict(mode="straight_through", backward=True,
                                                             backend="kernel", **gbuffer)),
        ("hard fwd+bwd, G-buffer, cosine (kernel)", dict(mode="hard", backward=True, backend="kernel",
                                                         weighting="cosine", **gbuffer)),
        ("exact fwd+bwd, G-buffer (kernel)", dict(mode="soft", backward=True, backend="kernel", variant="exact",
                                                  **gbuffer)),
        ("soft fwd+bwd, G-buffer (tensor path)", dict(mode="soft", backward=True, backend="torch", **gbuffer)),
        ("straight-through fwd+bwd (kernel)", dict(mode="straight_through", backward=True, backend="kernel")),
        ("soft fwd+bwd (tensor path)", dict(mode="soft", backward=True, backend="torch")),
        ("soft fwd+bwd, cosine (tensor path)", dict(mode="soft", backward=True, backend="torch", weighting="cosine")),
    ]
    if a.device != "cpu":  # (CUDA: the kernels' rows, timed by the wall clock)
        rows = [(name, args) for name, args in rows if args.get("backend") != "torch"]
    clock = "cpu_seconds" if a.device == "cpu" else "seconds"
    sizes = [(360, 640), (720, 1280)] if not a.size else [tuple(int(v) for v in reversed(a.size.lower().split("x")))]
    for H, W in sizes:
        print(f"BitmaskAO, {W}x{H} (a floor meeting a wall), 4 slices x {a.steps} steps per side, gradients of radius "
              f"and thickness (G-buffer: of depth and normals too), device={a.device}, torch threads={a.threads}")
        print(f"| case | CPU ms | wall ms | peak MB | / hard kernel ({'CPU' if a.device == 'cpu' else 'wall'}) |")
        print("|---|---:|---:|---:|---:|")
        hard = None
        for name, args in rows:
            r = run_case(height=H, width=W, device=a.device, chunk_size=a.chunk_size, threads=a.threads,
                         repeat=a.repeat, indirect=False, steps=a.steps, **{"params_only": True, **args})
            hard = hard or r[clock]
            print(f"| {name} | {1e3 * r['cpu_seconds']:.0f} | {1e3 * r['seconds']:.2f} | {r['peak_mb']:.0f} | "
                  f"{r[clock] / hard:.2f}x |{'' if r['finite'] else '  NON-FINITE'}", flush=True)


if __name__ == "__main__":
    main()
