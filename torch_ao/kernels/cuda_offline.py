"""The CUDA kernels built for a GPU on a machine without one: :func:`~torch_ao.kernels.launch.cuda_source`
compiled by NVIDIA's NVRTC to PTX, as :func:`~torch_ao.kernels.launch.run_walk` compiles it on a GPU, and
assembled by ``ptxas`` to the GPU's machine code, which says what each kernel needs of the GPU (registers per
thread, stack, spills) and so how many of its threads an SM can hold.

NVRTC and ``ptxas`` come from NVIDIA's pip packages (``pip install "torch_ao[cuda-offline]"``:
``nvidia-cuda-nvrtc-cu12``, ``nvidia-cuda-nvcc-cu12``); no GPU, driver or CUDA toolkit is needed. CI compiles
the kernels this way (``tests/test_kernels_nvrtc.py``), and ``benchmarks/cuda_resources.py`` prints the
table of docs/performance.md.
"""
from __future__ import annotations

import ctypes
import glob
import math
import os
import re
import shutil
import subprocess
import tempfile
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

from .launch import cuda_entry_names, cuda_groups, cuda_options, cuda_source, thread_locale_kept

__all__ = ["nvrtc_library", "nvrtc_version", "ptxas_path", "compile_ptx", "compile_groups", "KernelResources",
           "kernel_resources", "KERNEL_NAMES"]



#: the ``__global__`` entry points of walk_cuda.cu: a walk per accumulator, the horizon accumulators' record and
#: backward, the soft walk's backward, the hard sector walks' record and backward
KERNEL_NAMES = cuda_entry_names()
#: what an SM of compute capability 8.0 to 9.0 holds: registers, warps, blocks, and the registers of a warp are
#: allocated in units of this many
_SM = {"registers": 65536, "warps": 64, "blocks": 32, "register_unit": 256}


def _nvidia_paths(*parts: str) -> list[str]:
    """Paths matching ``parts`` under the ``nvidia`` namespace package of NVIDIA's pip wheels."""
    try:
        import nvidia
    except ImportError:
        return []
    return sorted(p for root in nvidia.__path__ for p in glob.glob(os.path.join(root, *parts)))


def nvrtc_library() -> ctypes.CDLL | None:
    """NVRTC (``libnvrtc.so``) from NVIDIA's pip package, else the system's, else ``None``."""
    for path in _nvidia_paths("cuda_nvrtc", "lib", "libnvrtc.so*") + ["libnvrtc.so", "libnvrtc.so.12"]:
        if "builtins" in path or ".alt." in path:
            continue
        try:
            return ctypes.CDLL(path)
        except OSError:
            continue
    return None


def nvrtc_version() -> tuple[int, int] | None:
    """The (major, minor) version of :func:`nvrtc_library`'s NVRTC, ``None`` where there is none."""
    nvrtc = nvrtc_library()
    if nvrtc is None:
        return None
    major, minor = ctypes.c_int(), ctypes.c_int()
    _check(nvrtc, nvrtc.nvrtcVersion(ctypes.byref(major), ctypes.byref(minor)))
    return major.value, minor.value


def ptxas_path() -> str | None:
    """``ptxas`` from NVIDIA's pip package, else on ``PATH``, else ``None``."""
    found = _nvidia_paths("cuda_nvcc", "bin", "ptxas")
    return found[0] if found else shutil.which("ptxas")


def compile_ptx(arch: int = 90, options: tuple[str, ...] | list[str] | None = None, *, full: bool = False) -> str:
    """The PTX of every CUDA kernel for compute capability ``arch`` (90: H100/H200), compiled by NVRTC with
    ``options`` (default those :func:`~torch_ao.kernels.launch.run_walk` passes for the lean build, or with
    ``full`` the full one's: :func:`~torch_ao.kernels.launch.cuda_options`). Raises ``RuntimeError`` with the
    compiler's log when the source does not compile, and when NVRTC is not found."""
    nvrtc = nvrtc_library()
    if nvrtc is None:
        raise RuntimeError("NVRTC not found: pip install nvidia-cuda-nvrtc-cu12 (or torch_ao[cuda-offline])")
    program = ctypes.c_void_p()
    source = cuda_source().encode()
    with thread_locale_kept():
        _check(nvrtc, nvrtc.nvrtcCreateProgram(ctypes.byref(program), source, b"walk_cuda.cu", 0, None, None))
        try:
            options = cuda_options(full) if options is None else options
            flags = [f"--gpu-architecture=compute_{int(arch)}".encode()] + [o.encode() for o in options]
            status = nvrtc.nvrtcCompileProgram(program, len(flags), (ctypes.c_char_p * len(flags))(*flags))
            log = _read(nvrtc, program, "ProgramLog")
            if status != 0:
                raise RuntimeError(f"NVRTC could not compile the CUDA kernels for compute_{arch}:\n{log}")
            return _read(nvrtc, program, "PTX")
        finally:
            nvrtc.nvrtcDestroyProgram(ctypes.byref(program))


def compile_groups(arch: int = 90, *, full: bool = False, workers: int | None = None) -> dict[str, str]:
    """The PTX of each of walk_cuda.cu's groups of entry points (:func:`~torch_ao.kernels.launch.cuda_groups`),
    ``{group: ptx}``, each group compiled alone, as a call on a GPU compiles it at its first use, for compute
    capability ``arch``, of the lean or the ``full`` build. The groups compile side by side on ``workers`` threads
    (default: one a core; NVRTC runs outside the GIL): on two cores, the twelve groups take 55 s where the whole
    source as one program takes 142."""
    groups = list(cuda_groups())
    workers = workers or min(len(groups), os.cpu_count() or 1)
    with ThreadPoolExecutor(workers) as pool:
        ptx = pool.map(lambda group: compile_ptx(arch, cuda_options(full, group)), groups)
        return dict(zip(groups, ptx))


def _check(nvrtc: ctypes.CDLL, status: int) -> None:
    if status != 0:
        nvrtc.nvrtcGetErrorString.restype = ctypes.c_char_p
        raise RuntimeError(f"NVRTC: {nvrtc.nvrtcGetErrorString(status).decode()}")


def _read(nvrtc: ctypes.CDLL, program: ctypes.c_void_p, what: str) -> str:
    """The program's log or PTX (``what``: ``"ProgramLog"``, ``"PTX"``) as text."""
    size = ctypes.c_size_t()
    _check(nvrtc, getattr(nvrtc, f"nvrtcGet{what}Size")(program, ctypes.byref(size)))
    buffer = ctypes.create_string_buffer(size.value)
    _check(nvrtc, getattr(nvrtc, f"nvrtcGet{what}")(program, buffer))
    return buffer.value.decode()


@dataclass(frozen=True)
class KernelResources:
    """What one kernel's thread needs of the GPU, as ptxas reports it: ``registers``, ``stack`` (bytes of
    local memory: arrays indexed at run time live there), ``spill_stores`` / ``spill_loads`` (bytes of
    registers spilled to local memory; 0 is what a fast kernel has)."""

    registers: int
    stack: int
    spill_stores: int
    spill_loads: int

    def occupancy(self, threads_per_block: int) -> float:
        """The share of an SM's warps (compute capability 8.0-9.0: 64) that blocks of ``threads_per_block``
        threads keep resident, limited by the registers (the usual limit of a long walk) and blocks per SM."""
        warps_per_block = math.ceil(threads_per_block / 32)
        per_warp = math.ceil(self.registers * 32 / _SM["register_unit"]) * _SM["register_unit"]
        blocks = min(_SM["registers"] // (per_warp * warps_per_block), _SM["blocks"],
                     _SM["warps"] // warps_per_block)
        return blocks * warps_per_block / _SM["warps"]


def kernel_resources(ptx: str | Mapping[str, str], arch: int = 90) -> dict[str, KernelResources]:
    """ptxas's report for every kernel of ``ptx`` assembled for ``sm_{arch}``: ``{name: KernelResources}``.
    ``ptx`` is one module's PTX, or several modules' (:func:`compile_groups`), assembled side by side. Raises
    ``RuntimeError`` when ptxas is not found or fails."""
    if isinstance(ptx, Mapping):
        with ThreadPoolExecutor(os.cpu_count() or 1) as pool:
            reports = list(pool.map(lambda module: kernel_resources(module, arch), ptx.values()))
        return {name: used for report in reports for name, used in report.items()}
    ptxas = ptxas_path()
    if ptxas is None:
        raise RuntimeError("ptxas not found: pip install nvidia-cuda-nvcc-cu12 (or torch_ao[cuda-offline])")
    with tempfile.TemporaryDirectory() as tmp:
        source = os.path.join(tmp, "walk.ptx")
        with open(source, "w", encoding="utf-8") as f:
            f.write(ptx)
        run = subprocess.run([ptxas, f"-arch=sm_{int(arch)}", "-v", source, "-o", os.path.join(tmp, "walk.cubin")],
                             capture_output=True, text=True)
    if run.returncode != 0:
        raise RuntimeError(f"ptxas could not assemble the kernels for sm_{arch}:\n{run.stderr}")
    report = {}
    for block in re.split(r"Compiling entry function '", run.stderr)[1:]:
        name = block.split("'", 1)[0]
        number = lambda pattern: int(re.search(pattern, block).group(1))  # noqa: E731
        report[name] = KernelResources(registers=number(r"Used (\d+) registers"),
                                       stack=number(r"(\d+) bytes stack frame"),
                                       spill_stores=number(r"(\d+) bytes spill stores"),
                                       spill_loads=number(r"(\d+) bytes spill loads"))
    return report
