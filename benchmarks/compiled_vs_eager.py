"""A module's call under ``torch.compile`` (Inductor, ``dynamic=False``) against the same call eagerly, on the CPU:
the forward, and forward + backward with depth and normal gradients (a new G-buffer each call, so that neither
side reuses the G-buffer's derived positions and normals). Best of ``--repeat`` calls each, interleaved (the
machine's load moves), process CPU time; the compiled module's first call (its compile) in wall seconds.
Markdown on stdout:

    OMP_NUM_THREADS=1 python benchmarks/compiled_vs_eager.py --frame room_corner --size 640x360
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's torch_ao, not an installed copy

import bench_vs_shader as shader_bench  # noqa: E402
import torch_ao  # noqa: E402

MODULES = {
    "GTAO": lambda s: torch_ao.GTAO(**s),
    "HBAO": lambda s: torch_ao.HBAO(**s),
    "BitmaskAO, cosine": lambda s: torch_ao.BitmaskAO(weighting="cosine", **s),  # (uniform hard masks: no gradient)
    "soft BitmaskAO": lambda s: torch_ao.BitmaskAO(mode="soft", **s),
}


def call_of(run, gbuffer, gradients: bool):
    """One call of ``run``: its forward under ``no_grad``, or forward + backward of the visibility's sum."""
    def call():
        if not gradients:
            with torch.no_grad():
                run(torch_ao.GBuffer(depth=gbuffer.depth, camera=gbuffer.camera, normals=gbuffer.normals,
                                     mask=gbuffer.mask))
            return
        depth = gbuffer.depth.detach().clone().requires_grad_(True)
        normals = gbuffer.normals.detach().clone().requires_grad_(True)
        run(torch_ao.GBuffer(depth=depth, camera=gbuffer.camera, normals=normals, mask=gbuffer.mask)
            ).visibility.sum().backward()
    return call


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--modules", nargs="+", default=list(MODULES), choices=list(MODULES))
    p.add_argument("--frame", default="room_corner", choices=list(shader_bench.FRAMES))
    p.add_argument("--size", default="640x360")
    p.add_argument("--setting", default="4x4", help="slices x steps")
    p.add_argument("--repeat", type=int, default=7)
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")  # (Inductor's deprecation notes)
    W, H = (int(v) for v in args.size.split("x"))
    slices, steps = (int(v) for v in args.setting.split("x"))
    gbuffer = shader_bench.frame_gbuffer(args.frame, H, W)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s); {args.frame} {args.size}, "
          f"{slices} x {steps}; CPU ms, best of {args.repeat}\n")
    print("| module | call | eager | compiled | compiled / eager | first compiled call (s) |")
    print("|---|---|---:|---:|---:|---:|")
    for name in args.modules:
        for gradients in (False, True):
            module = MODULES[name](dict(slices=slices, steps=steps))
            torch._dynamo.reset()
            calls, first, best = {}, {}, {}
            for label, run in (("eager", module), ("compiled", torch.compile(module, dynamic=False))):
                calls[label] = call_of(run, gbuffer, gradients)
                start = time.time()
                calls[label]()
                first[label], best[label] = time.time() - start, float("inf")
            for _ in range(args.repeat):
                for label, call in calls.items():
                    start = time.process_time()
                    call()
                    best[label] = min(best[label], time.process_time() - start)
            what = "fwd+bwd, depth + normals" if gradients else "forward"
            print(f"| `{name}` | {what} | {best['eager'] * 1e3:.1f} | {best['compiled'] * 1e3:.1f} | "
                  f"{best['compiled'] / best['eager']:.2f}× | {first['compiled']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
