"""Time and memory of the horizon-family methods (SSAO, HBAO, UE4 SSAO, GTAO, PSSAO), forward and
forward+backward, on CPU (or CUDA with ``--device cuda``).

Every method reads 64 depth samples per pixel, the equivalent of 4 slices x 8 steps per side:

* GTAO (exact variant): 4 slices x 8 steps x 2 sides;
* UE4 SSAO: 4 uniform directions x 8 pairs (``sample_set="uniform"``);
* HBAO and PSSAO: 8 full-circle directions x 8 steps (one side each);
* SSAO: a 64-point hemisphere kernel.

Scene: the built-in floor next to a wall (``floor_wall_gbuffer``), normals from the G-buffer.
Each (method, size, pass) runs in its own subprocess: one warm-up call, then ``--repeats`` timed calls;
the table shows the median. Peak memory is the child's peak resident set size (``ru_maxrss``)
minus its resident size just before the warm-up (after imports and building the G-buffer), so it is
the extra memory one call needs, including the autograd graph for forward+backward; on CUDA it is
``torch.cuda.max_memory_allocated``. Forward+backward keeps every step's intermediates (about 1 GB for
GTAO at 320x180), so from 640x360 up it runs in chunks of 32768 pixels with the walk recomputed in
backward (``chunk_size``/``recompute`` of the modules; ``--chunk-size none`` to disable), marked ``*``. Threads: ``--threads`` (default 1: the walk is many small
tensor operations, and extra threads mostly add contention on a shared machine).

    python benchmarks/bench_methods.py             # 320x180, 640x360, 1280x720
    python benchmarks/bench_methods.py --quick     # 320x180 only, 2 repeats

``--backend`` picks the modules' backend (default ``auto``: the fused kernel where one covers the call, as
GTAO, HBAO, UE4 SSAO, PSSAO and SSAO forward do); the kernel against the tensor path, forward, one thread::

    python benchmarks/bench_methods.py --sizes 640x360 --methods ue4_ssao pssao gtao ssao --no-backward --backend torch
    python benchmarks/bench_methods.py --sizes 640x360 --methods ue4_ssao pssao gtao ssao --no-backward --backend kernel
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import sys
import time

SIZES = {"320x180": (180, 320), "640x360": (360, 640), "1280x720": (720, 1280)}
METHODS = ("ssao", "hbao", "ue4_ssao", "gtao", "pssao")


def build(name: str, chunk_size, backend: str = "auto"):
    from torch_ao.methods.gtao import GTAO
    from torch_ao.methods.hbao import HBAO
    from torch_ao.methods.pssao import PSSAO
    from torch_ao.methods.ssao import SSAO
    from torch_ao.methods.ue4_ssao import UE4SSAO

    mem = {"backend": backend} | ({} if chunk_size is None else {"chunk_size": chunk_size, "recompute": True})
    if name == "ssao":
        return SSAO(samples=64, radius=1.0, **mem)
    if name == "hbao":
        return HBAO(slices=8, steps=8, radius=1.0, **mem)
    if name == "ue4_ssao":
        return UE4SSAO(sample_set="uniform", slices=4, steps=8, radius=1.0, **mem)
    if name == "gtao":
        return GTAO(slices=4, steps=8, radius=1.0, **mem)
    if name == "pssao":
        return PSSAO(slices=8, steps=8, **mem)
    raise ValueError(f"method: unknown {name!r}")


def child(args: dict) -> dict:
    import os
    import resource

    import torch

    from torch_ao.examples import floor_wall_gbuffer
    from torch_ao.gbuffer import GBuffer

    torch.set_num_threads(args["threads"])
    device = args["device"]
    H, W = args["height"], args["width"]
    gb, _ = floor_wall_gbuffer(H, W, wall_distance=1.0)
    module = build(args["method"], args["chunk_size"], args.get("backend", "auto")).to(device)
    grad = args["backward"]

    def rss_kb() -> int:
        with open(f"/proc/{os.getpid()}/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // 1024

    def once() -> float:
        depth = gb.depth.to(device).requires_grad_(grad)
        normals = gb.normals.to(device).requires_grad_(grad)
        gbuf = GBuffer(depth, gb.camera.to(device), normals=normals)
        if device != "cpu":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        with torch.enable_grad() if grad else torch.no_grad():
            out = module(gbuf)
            if grad:
                out.visibility.sum().backward()
        if device != "cpu":
            torch.cuda.synchronize()
        return time.perf_counter() - t0

    baseline = rss_kb()
    if device != "cpu":
        torch.cuda.reset_peak_memory_stats()
    once()  # warm-up
    times = [once() for _ in range(args["repeats"])]
    if device != "cpu":
        peak_mb = torch.cuda.max_memory_allocated() / 2**20
    else:
        peak_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - baseline) / 1024
    return {"seconds": statistics.median(times), "all_seconds": times, "peak_mb": peak_mb}


def chunk_for(size: str, backward: bool, setting: str):
    """The chunk size used for one case (None = the whole frame at once)."""
    if not backward or setting == "none":
        return None
    if setting == "auto":
        H, W = SIZES[size]
        return 32768 if H * W >= 360 * 640 else None
    return int(setting)


def run_case(method, size, backward, opts) -> dict:
    H, W = SIZES[size]
    payload = dict(method=method, height=H, width=W, backward=backward, repeats=opts.repeats, threads=opts.threads,
                   device=opts.device, chunk_size=chunk_for(size, backward, opts.chunk_size), backend=opts.backend)
    proc = subprocess.run([sys.executable, __file__, "--child", json.dumps(payload)], capture_output=True, text=True)
    if proc.returncode != 0:
        return {"error": (proc.stderr.strip().splitlines() or [f"exit {proc.returncode}"])[-1]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="320x180 only, 2 repeats")
    p.add_argument("--sizes", nargs="+", choices=sorted(SIZES), help="image sizes (default: all three)")
    p.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    p.add_argument("--repeats", type=int, default=3, help="timed calls after one warm-up (median reported)")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    p.add_argument("--device", default="cpu")
    p.add_argument("--backend", default="auto", choices=("auto", "kernel", "torch"),
                   help="the modules' backend (auto: a fused kernel where one covers the call)")
    p.add_argument("--chunk-size", default="auto",
                   help="forward+backward: process this many pixels at a time, recomputing the walk in backward "
                        "(bounds memory); 'auto' = 32768 from 640x360 up, 'none' = never")
    p.add_argument("--no-backward", action="store_true", help="forward only")
    p.add_argument("--json", help="also write the raw results here")
    p.add_argument("--child", help=argparse.SUPPRESS)
    opts = p.parse_args(argv)
    if opts.child:
        print(json.dumps(child(json.loads(opts.child))))
        return 0
    sizes = ["320x180"] if opts.quick else (opts.sizes or list(SIZES))
    if opts.quick:
        opts.repeats = min(opts.repeats, 2)
    passes = [False] if opts.no_backward else [False, True]
    import torch

    print(f"# torch {torch.__version__}, {platform.processor() or platform.machine()}, device {opts.device}, "
          f"backend {opts.backend}, "
          f"{opts.threads} thread(s), median of {opts.repeats} after 1 warm-up; fwd+bwd chunking: {opts.chunk_size} "
          f"(* = chunks of that many pixels with recomputation in backward)")
    print()
    print("| method | size | forward (ms) | forward peak (MB) | fwd+bwd (ms) | fwd+bwd peak (MB) |")
    print("| --- | --- | ---: | ---: | ---: | ---: |")
    results = []
    for size in sizes:
        for method in opts.methods:
            row = {"method": method, "size": size}
            for backward in passes:
                r = run_case(method, size, backward, opts)
                row["fwd+bwd" if backward else "forward"] = r
            results.append(row)

            def cell(r, key):
                if r is None:
                    return "-"
                if "error" in r:
                    return "error"
                return f"{r['seconds'] * 1000:.0f}" if key == "t" else f"{r['peak_mb']:.0f}"

            f, b = row.get("forward"), row.get("fwd+bwd")
            chunk = chunk_for(size, True, opts.chunk_size) if b is not None else None
            star = f" (*{chunk})" if chunk else ""
            print(f"| {method} | {size} | {cell(f, 't')} | {cell(f, 'm')} | {cell(b, 't')}{star} | {cell(b, 'm')} |",
                  flush=True)
    errors = [(r["method"], r["size"], k, v["error"]) for r in results for k, v in r.items()
              if isinstance(v, dict) and "error" in v]
    for e in errors:
        print(f"error: {e}", file=sys.stderr)
    if opts.json:
        with open(opts.json, "w") as fh:
            json.dump(results, fh, indent=2)
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
