"""Where a forward + backward with G-buffer gradients spends its time: the kernel's forward, the kernel's backward
and the torch ops around them (the frame's preparation — positions, unit normals, channel-last copies — their
backward through autograd, and the sums for the scalar parameters), against the hard forward of the same module
(``bench_vs_shader.py``'s reference for the row). Any forward + backward case of ``bench_vs_shader.py`` can be
asked for (``--cases soft_parameters``: the soft walk with the radius' and thickness' gradients, whose kernel forward
is the walk with the reverse scan).

Each case of ``bench_vs_shader.py`` is run on its frames, sizes and settings: best of ``--repeat`` calls after a
warm-up, process CPU time, one thread unless ``--threads``; the kernels' own time is read from ``--repeat`` more
calls under ``torch.profiler`` (the operators of the ``torch_ao_kernels`` namespace, the least of each), the torch
ops' is the rest. The last column is what a 3x target leaves the backward kernel: three hard forwards less the
kernel's forward and the torch ops (a backward that walks again, as a reverse pass that keeps nothing per sample
must, needs at least the kernel forward's time). Markdown on stdout:

    OMP_NUM_THREADS=1 python benchmarks/gbuffer_breakdown.py --repeat 5
    python benchmarks/gbuffer_breakdown.py --cases soft_gbuffer --frames room_corner --sizes 1280x720
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's torch_ao, not an installed copy

import bench_vs_shader as shader_bench  # noqa: E402

CASES = ("soft_gbuffer", "cosine_edge_gbuffer", "ssilvb_soft_gbuffer", "gtao_gbuffer", "hbao_gbuffer")


def kernel_ms(fn, repeat: int) -> dict[str, float]:
    """CPU ms of each ``torch_ao_kernels`` operator in a call of ``fn``: the least of ``repeat`` calls."""
    from torch.profiler import ProfilerActivity, profile

    least: dict[str, float] = {}
    for _ in range(repeat):
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            fn()
        for e in prof.key_averages():
            if e.key.startswith("torch_ao_kernels::"):
                op = e.key.split("::", 1)[1]
                least[op] = min(least.get(op, float("inf")), e.self_cpu_time_total / 1e3)
    return least


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="+", default=list(CASES))
    p.add_argument("--frames", nargs="+", default=list(shader_bench.FRAMES))
    p.add_argument("--sizes", nargs="+", default=["640x360"])
    p.add_argument("--settings", nargs="+", default=["4x4", "4x8"])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    cases = shader_bench._cases()
    unknown = [c for c in args.cases if c not in cases or cases[c].gradients is None]
    if unknown:
        raise SystemExit(f"--cases: not a forward + backward case of bench_vs_shader.py: {unknown}")
    print(f"torch {torch.__version__}, {args.threads} thread(s); CPU ms, best of {args.repeat}\n")
    print("| frame | size, slices × steps | case | hard forward | kernel forward | kernel backward | torch ops "
          "| total (× hard) | the backward's budget at 3× |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|")
    for frame in args.frames:
        for size in args.sizes:
            W, H = (int(v) for v in size.split("x"))
            gbuffer = shader_bench.frame_gbuffer(frame, H, W)
            for setting in args.settings:
                slices, steps = (int(v) for v in setting.split("x"))
                s = dict(slices=slices, steps=steps, radius=1.0, thickness=0.5)
                for name in args.cases:
                    case = cases[name]
                    hard = shader_bench.best_ms(shader_bench.case_call(cases[case.against], gbuffer, s), args.repeat)[1]
                    call = shader_bench.case_call(case, gbuffer, s)
                    total = shader_bench.best_ms(call, args.repeat)[1]
                    ops = kernel_ms(call, args.repeat)
                    backward = sum(ms for op, ms in ops.items() if "backward" in op)
                    forward = sum(ops.values()) - backward
                    rest = max(total - forward - backward, 0.0)
                    print(f"| {frame} | {W}×{H}, {slices} × {steps} | `{name}` | {hard:.0f} | {forward:.0f} | "
                          f"{backward:.0f} | {rest:.0f} | {total:.0f} ({total / hard:.2f}×) | "
                          f"{3 * hard - forward - rest:.0f} |", flush=True)


if __name__ == "__main__":
    main()
