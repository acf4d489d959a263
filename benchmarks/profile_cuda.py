"""Where a CUDA call's time goes: for each of bench_cuda.py's cases, the call's time (CUDA events, median), the
time its kernels run on the GPU (torch.profiler's device times, per call), the walk's own kernels among them,
how many kernels it launches, and how often the host waits for the GPU (synchronisations and copies to or from
the host), the memory it allocates at its peak, and the device memory held outside torch's allocator after it
(the CUDA context and the driver's local memory for the kernels' stacks, which grows to the largest launched and
stays: a case that raises it launched a kernel with a larger stack). A call whose kernels take far less than the
call is bound by the host's launching.

    python benchmarks/profile_cuda.py                    # 1920x1080, every case
    python benchmarks/profile_cuda.py --cases "gtao high, fwd" --top 8
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections import defaultdict
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).parent))

from bench_cuda import batched, call, cases, median_ms  # noqa: E402
from bench_vs_shader import frame_gbuffer  # noqa: E402

_WAITS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaMemcpy", "cudaMemcpyAsync", "cudaEventSynchronize")


def profile_case(fn, calls: int) -> dict:
    """``fn`` profiled over ``calls`` calls: per call, the device time of every kernel (by name), launches and
    host waits."""
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(calls):
            fn()
        torch.cuda.synchronize()
    kernels, launches, waits = defaultdict(float), 0, defaultdict(int)
    for event in prof.events():
        if event.device_type == torch.autograd.DeviceType.CUDA:
            kernels[event.name] += event.device_time_total / 1000 / calls  # (µs) -> ms per call
            launches += 1
        elif any(event.name.startswith(w) for w in _WAITS):
            waits[event.name] += 1
    return {"device_ms": sum(kernels.values()), "kernels": dict(kernels), "launches": launches / calls,
            "waits": {k: v / calls for k, v in waits.items()}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="1920x1080", help="WIDTHxHEIGHT")
    p.add_argument("--calls", type=int, default=5, help="profiled calls per case")
    p.add_argument("--repeat", type=int, default=10, help="timed calls per case (median reported)")
    p.add_argument("--top", type=int, default=4, help="kernels listed per case, by device time")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--cases", nargs="*", help="labels' substrings to run (default: all but the tensor walk's)")
    p.add_argument("--json", help="also write the results here")
    args = p.parse_args(argv)
    device = torch.device("cuda")
    width, height = (int(v) for v in args.size.lower().split("x"))
    gbuffer = frame_gbuffer("floor_wall", height, width).to(device=device)
    # (the tensor walk's rows, seconds a call, only when a substring names them)
    chosen = {k: v for k, v in cases().items() if ("(torch)" not in k or any("(torch)" in s for s in args.cases or ()))
              and (not args.cases or any(s in k for s in args.cases))}
    if not args.cases or any("batch" in s for s in args.cases):
        chosen[f"bitmask high, hard, batch {args.batch}"] = cases()["bitmask high, hard"]
    results = []
    for label, (make, gradients) in chosen.items():
        gb = batched(gbuffer, args.batch) if label.endswith(f"batch {args.batch}") else gbuffer
        try:
            fn = call(make, gradients, gb, device)
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            base = torch.cuda.memory_allocated()
            ms = median_ms(fn, device, warmup=2, repeat=args.repeat)
            peak = (torch.cuda.max_memory_allocated() - base) / 2**20
            free, total = torch.cuda.mem_get_info()
            outside = (total - free - torch.cuda.memory_reserved()) / 2**20
            row = {"case": label, "call_ms": ms, "peak_mb": peak, "outside_mb": outside,
                   **profile_case(fn, args.calls)}
        except Exception as exc:  # noqa: BLE001 - reported, the other cases still run
            row = {"case": label, "error": f"{type(exc).__name__}: {str(exc)[:300]}"}
            print(f"{label}: FAILED {row['error']}", flush=True)
            results.append(row)
            continue
        results.append(row)
        top = sorted(row["kernels"].items(), key=lambda kv: -kv[1])[:args.top]
        waits = ", ".join(f"{k} {v:g}" for k, v in row["waits"].items()) or "none"
        print(f"{label}: call {ms:.3f} ms, kernels {row['device_ms']:.3f} ms on the GPU "
              f"({row['launches']:g} launches), host waits: {waits}, peak {peak:.0f} MB, "
              f"outside torch's allocator {outside:.0f} MB", flush=True)
        for name, t in top:
            print(f"    {t:9.3f} ms  {name[:90]}", flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(results, indent=1))
    walk = [r for r in results if "call_ms" in r]
    if walk:
        print(f"median share of a call spent in kernels: "
              f"{statistics.median(r['device_ms'] / r['call_ms'] for r in walk):.0%}")
    return 1 if any("error" in r for r in results) else 0


if __name__ == "__main__":
    raise SystemExit(main())
