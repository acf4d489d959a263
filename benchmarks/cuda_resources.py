"""What each CUDA kernel needs of the GPU, without a GPU: the kernels compiled by NVRTC and assembled by ptxas
(torch_ao.kernels.cuda_offline) for a compute capability, one Markdown row per kernel: registers per thread,
stack bytes (local memory), spilled bytes, and the share of an SM's warps that blocks of ``--threads`` threads
(the launch's: torch_ao.kernels.launch._THREADS) keep resident.

    pip install "torch_ao[cuda-offline]"
    python benchmarks/cuda_resources.py --arch 90
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torch_ao.kernels.cuda_offline import compile_ptx, kernel_resources  # noqa: E402
from torch_ao.kernels.launch import _THREADS  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", type=int, default=90, help="compute capability x 10 (90: H100/H200)")
    ap.add_argument("--threads", type=int, default=_THREADS, help="threads per block")
    args = ap.parse_args(argv)
    report = kernel_resources(compile_ptx(args.arch), args.arch)
    print(f"sm_{args.arch}, {args.threads} threads per block\n")
    print("| kernel | registers | stack (bytes) | spilled (bytes) | occupancy |")
    print("|---|---:|---:|---:|---:|")
    for name, used in report.items():
        print(f"| `{name}` | {used.registers} | {used.stack} | {used.spill_stores + used.spill_loads} | "
              f"{used.occupancy(args.threads):.0%} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
