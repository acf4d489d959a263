"""What each CUDA kernel needs of the GPU, without a GPU: the kernels compiled by NVRTC and assembled by ptxas
(torch_ao.kernels.cuda_offline) for a compute capability, one Markdown row per kernel: registers per thread,
stack bytes (local memory), spilled bytes, and the share of an SM's warps that blocks of ``--threads`` threads
(the launch's: torch_ao.kernels.launch._THREADS) keep resident. ``--full``: the full build's (walk.h's
TAO_FULL_WALK, which a call needing one of the options the lean build leaves out runs), with the lean build's
registers and spills beside each.

    pip install "torch_ao[cuda-offline]"
    python benchmarks/cuda_resources.py --arch 90
    python benchmarks/cuda_resources.py --arch 90 --full
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torch_ao.kernels.cuda_offline import compile_groups, kernel_resources  # noqa: E402
from torch_ao.kernels.launch import _THREADS  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", type=int, default=90, help="compute capability x 10 (90: H100/H200)")
    ap.add_argument("--threads", type=int, default=_THREADS, help="threads per block")
    ap.add_argument("--full", action="store_true", help="the full build's kernels, the lean build's beside them")
    args = ap.parse_args(argv)
    report = kernel_resources(compile_groups(args.arch, full=args.full), args.arch)
    lean = kernel_resources(compile_groups(args.arch), args.arch) if args.full else {}
    print(f"sm_{args.arch}, {args.threads} threads per block, the {'full' if args.full else 'lean'} build\n")
    beside = " lean: registers, spilled |" if args.full else ""
    print(f"| kernel | registers | stack (bytes) | spilled (bytes) | occupancy |{beside}")
    print(f"|---|---:|---:|---:|---:|{'---:|' if args.full else ''}")
    for name, used in report.items():
        row = (f"| `{name}` | {used.registers} | {used.stack} | {used.spill_stores + used.spill_loads} | "
               f"{used.occupancy(args.threads):.0%} |")
        if name in lean:
            row += f" {lean[name].registers}, {lean[name].spill_stores + lean[name].spill_loads} |"
        print(row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
