"""How ``torch.compile`` traces each fused kernel family's call: the graphs and graph breaks that
``torch._dynamo.explain`` finds in one call of each of tests/kernel_cases.py's modules (backend ``auto``) on a
small G-buffer (with a light buffer and a back-face layer), without gradients and with depth and normal
gradients, and the first line of each distinct break reason. On the CPU every call is one graph with no break
(tests/test_compile.py asserts it); on CUDA this counts what the kernels' launches cost a compiled model.
Markdown on stdout:

    python benchmarks/compile_breaks.py                 # CPU
    python benchmarks/compile_breaks.py --device cuda   # a GPU (benchmarks/gpu_check.sh runs it)
"""
from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))  # this checkout's torch_ao, not an installed copy

import torch_ao  # noqa: E402
from kernel_cases import KERNEL_CALLS  # noqa: E402
from torch_ao.examples import example_gbuffer  # noqa: E402


def explain(module: torch.nn.Module, gbuffer: torch_ao.GBuffer, gradients: bool) -> tuple[int, int, list[str]]:
    """``(graphs, breaks, reasons)`` of one traced call of ``module`` on ``gbuffer`` (depth and normals requiring
    grad where ``gradients``)."""
    torch._dynamo.reset()
    depth, normals = gbuffer.depth.detach().clone(), gbuffer.normals.detach().clone()
    if gradients:
        depth.requires_grad_(True), normals.requires_grad_(True)
    B, _, H, W = depth.shape
    light = torch.rand(B, 3, H, W, generator=torch.Generator().manual_seed(0)).to(depth.device)  # (SSILVB's)
    frame = torch_ao.GBuffer(depth=depth, camera=gbuffer.camera, normals=normals, light=light, mask=gbuffer.mask,
                             backface_depth=gbuffer.depth * 1.3)
    explained = torch._dynamo.explain(module)(frame)
    reasons = sorted({b.reason.strip().splitlines()[0][:140] for b in explained.break_reasons})
    return explained.graph_count, explained.graph_break_count, reasons


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--size", default="24x32", help="HxW of the G-buffer")
    ap.add_argument("--cases", nargs="*", default=list(KERNEL_CALLS), choices=list(KERNEL_CALLS))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    H, W = map(int, args.size.split("x"))
    gbuffer = example_gbuffer(H, W).to(device=args.device)
    print(f"torch {torch.__version__}, device {args.device}, {H}x{W}\n")
    print("| call | graphs / breaks | with depth + normal gradients | break reasons |")
    print("|---|---:|---:|---|")
    for name in args.cases:
        module = KERNEL_CALLS[name]().to(args.device)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            plain, grads = explain(module, gbuffer, False), explain(module, gbuffer, True)
        reasons = "; ".join(sorted(set(plain[2]) | set(grads[2]))).replace("|", "\\|") or "none"
        print(f"| `{name}` | {plain[0]} / {plain[1]} | {grads[0]} / {grads[1]} | {reasons} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
