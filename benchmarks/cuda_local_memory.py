"""The device memory that a CUDA backward's local memory takes, measured on the GPU.

The driver reserves a thread's local memory (its stack) for every thread the GPU can hold, about
(stack + 512 bytes) x multiprocessors x threads per multiprocessor, and keeps it once a launch has needed it
(docs/performance.md, "A backward's local memory"). This script runs one forward + backward of each size of the
horizon backward on a small G-buffer, smallest first: GTAO's exact variant (``tao_backward_gtao_small``), the
hdrp variant at 4 steps a side (``_short``) and at 9 (the full one). After each it prints the kernel's local
memory (``cuFuncGetAttribute``), the context's stack limit (``cuCtxGetLimit``: the per-thread size the driver
reserved for), the device memory held outside torch's allocator, and the reservation the rule predicts. Needs a
GPU; run it in a fresh process (the reservation only grows):

    python benchmarks/cuda_local_memory.py
"""
from __future__ import annotations

import ctypes
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch_ao  # noqa: E402
from torch_ao.examples import example_gbuffer  # noqa: E402
from torch_ao.kernels import launch  # noqa: E402

_LOCAL_SIZE_BYTES = 3  # CUfunction_attribute CU_FUNC_ATTRIBUTE_LOCAL_SIZE_BYTES
_STACK_SIZE = 0  # CUlimit CU_LIMIT_STACK_SIZE
_CASES = (("GTAO exact", "tao_backward_gtao_small", dict(variant="exact", steps=4)),
          ("GTAO hdrp, 4 steps", "tao_backward_gtao_short", dict(variant="hdrp", steps=4)),
          ("GTAO hdrp, 9 steps", "tao_backward_gtao", dict(variant="hdrp", steps=9)))


def outside_allocator_mb() -> float:
    """Device memory in use that torch's caching allocator does not hold (the context, the driver's local memory)."""
    free, total = torch.cuda.mem_get_info()
    return (total - free - torch.cuda.memory_reserved()) / 2**20


def main() -> int:
    if not torch.cuda.is_available():
        print("needs a CUDA device")
        return 1
    libcuda = torch.cuda._utils._get_gpu_runtime_library()
    props = torch.cuda.get_device_properties(0)
    threads = props.multi_processor_count * props.max_threads_per_multi_processor
    gb = example_gbuffer(90, 160).to("cuda")
    gb.depth.requires_grad_(True)
    torch.cuda.synchronize()
    rows = [{"case": "before any backward", "outside_mb": outside_allocator_mb()}]
    print(f"{props.name}: {props.multi_processor_count} SMs x {props.max_threads_per_multi_processor} threads; "
          f"outside torch's allocator before any backward: {rows[0]['outside_mb']:.0f} MB")
    for label, kernel_name, options in _CASES:
        torch_ao.GTAO(**options, backend="kernel").cuda()(gb).visibility.sum().backward()
        torch.cuda.synchronize()
        kernel = launch._cuda_kernel(kernel_name, torch.cuda.current_device())
        local, stack = ctypes.c_int(), ctypes.c_size_t()
        libcuda.cuFuncGetAttribute(ctypes.byref(local), _LOCAL_SIZE_BYTES, kernel.func)
        libcuda.cuCtxGetLimit(ctypes.byref(stack), _STACK_SIZE)
        row = {"case": label, "kernel": kernel_name, "local_bytes": local.value, "stack_limit": stack.value,
               "outside_mb": outside_allocator_mb(),
               "predicted_mb": (local.value + 512) * threads / 2**20}
        rows.append(row)
        print(f"{label} ({kernel_name}): local {row['local_bytes']} B a thread, stack limit {row['stack_limit']} B, "
              f"outside torch's allocator {row['outside_mb']:.0f} MB (the rule: {row['predicted_mb']:.0f} MB "
              f"beside the context)", flush=True)
    print(json.dumps(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
