"""Where the CUDA walk's time goes, measured by A/B: the same kernel compiled several ways, and the same kernel
over several sampling settings, timed on one GPU in one run. The binaries are compiled off the GPU (NVRTC from
NVIDIA's pip package, as the GPU's torch would compile them), so the GPU's time goes to timing alone.

    python benchmarks/cuda_variants.py build .cuda_variants          # here: a cubin per compile variant
    python benchmarks/cuda_variants.py run .cuda_variants --json out.json   # on the GPU

``run`` records the kernel launches that each case's module makes (its arguments), then launches each variant's
kernel of the same name on them: the median of ``--repeat`` launches timed with CUDA events, and how far its
output is from the ``base`` variant's (the library's own options). Time over the settings cases gives the cost
of a step, a slice and the pixel's set-up; time over the compile variants the cost of IEEE arithmetic,
registers and the like.

    NVRTC=/path/to/libnvrtc.so.13 python benchmarks/cuda_variants.py build DIR   # a given NVRTC (default: the
    newest of NVIDIA's pip packages)
"""
from __future__ import annotations

import argparse
import ctypes
import glob
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torch_ao.kernels import launch  # noqa: E402

#: compile variants: NVRTC options, and edits of the source (old, new)
VARIANTS = {
    "base": (launch._NVRTC_OPTIONS, ()),
    "fmad": (("-std=c++17",), ()),
    "fast_math": (("-std=c++17", "--use_fast_math"), ()),
    "ftz_approx_div_sqrt": ((*launch._NVRTC_OPTIONS, "-ftz=true", "-prec-div=false", "-prec-sqrt=false"), ()),
    "no_launch_bounds": (launch._NVRTC_OPTIONS, (("__launch_bounds__(128, 3)", ""),)),
    "maxreg_96": ((*launch._NVRTC_OPTIONS, "-maxrregcount=96"), (("__launch_bounds__(128, 3)", ""),)),
    "maxreg_64": ((*launch._NVRTC_OPTIONS, "-maxrregcount=64"), (("__launch_bounds__(128, 3)", ""),)),
}


def _nvrtc() -> ctypes.CDLL:
    """NVRTC: $NVRTC, else the newest of NVIDIA's pip packages (its builtins library loaded first: NVRTC opens it
    by name at compile time, and a pip package's folder is not on the loader's path)."""
    path = os.environ.get("NVRTC")
    if not path:
        import nvidia

        found = sorted((p for root in nvidia.__path__ for p in glob.glob(os.path.join(root, "*", "lib", "libnvrtc.so.*"))
                        if ".alt." not in p and "builtins" not in p), key=lambda p: p.rsplit(".so.", 1)[1])
        if not found:
            raise SystemExit("no NVRTC: pip install nvidia-cuda-nvrtc (the GPU's torch's CUDA version)")
        path = found[-1]
    for builtins in glob.glob(os.path.join(os.path.dirname(path), "libnvrtc-builtins.so.*")):
        if ".alt." not in builtins:
            ctypes.CDLL(builtins, mode=ctypes.RTLD_GLOBAL)
    return ctypes.CDLL(path)


def build(directory: Path, arch: int, variants: list[str] | None = None) -> None:
    from torch_ao.kernels.cuda_offline import _check, _read

    nvrtc = _nvrtc()
    major, minor = ctypes.c_int(), ctypes.c_int()
    nvrtc.nvrtcVersion(ctypes.byref(major), ctypes.byref(minor))
    directory.mkdir(parents=True, exist_ok=True)
    for name, (options, edits) in VARIANTS.items():
        if variants and name not in variants:
            continue
        source = launch.cuda_source()
        for old, new in edits:
            assert old in source, f"{name}: {old!r} is not in the source"
            source = source.replace(old, new)
        program = ctypes.c_void_p()
        _check(nvrtc, nvrtc.nvrtcCreateProgram(ctypes.byref(program), source.encode(), b"walk_cuda.cu", 0, None, None))
        flags = [f"--gpu-architecture=sm_{arch}".encode(), *(o.encode() for o in options)]
        status = nvrtc.nvrtcCompileProgram(program, len(flags), (ctypes.c_char_p * len(flags))(*flags))
        if status != 0:
            raise SystemExit(f"{name}: NVRTC failed\n{_read(nvrtc, program, 'ProgramLog')}")
        size = ctypes.c_size_t()
        _check(nvrtc, nvrtc.nvrtcGetCUBINSize(program, ctypes.byref(size)))
        cubin = ctypes.create_string_buffer(size.value)
        _check(nvrtc, nvrtc.nvrtcGetCUBIN(program, cubin))
        nvrtc.nvrtcDestroyProgram(ctypes.byref(program))
        (directory / f"{name}.cubin").write_bytes(cubin.raw)
        print(f"{name}: {size.value} bytes (NVRTC {major.value}.{minor.value}, sm_{arch})", flush=True)


def cases() -> dict:
    """``{label: module}``: the hard walk over its sampling (slices x steps a side), its fetch, and the
    pipelines of the GPU targets."""
    import torch_ao
    from torch_ao.thickness import BackfaceThickness

    k = dict(backend="kernel")
    hard = lambda **o: torch_ao.BitmaskAO(**k, **o)  # noqa: E731
    return {
        "hard high (3x3)": hard(preset="high"),
        "hard 3x1": hard(slices=3, steps=1), "hard 3x6": hard(slices=3, steps=6), "hard 6x3": hard(slices=6, steps=3),
        "hard 1x3": hard(slices=1, steps=3),
        "hard high, nearest": hard(preset="high", fetch="nearest"),
        "hard high, no jitter": hard(preset="high", jitter=False),
        "exact + backface + edge_aware": hard(preset="high", variant="exact", thickness=BackfaceThickness(),
                                              fetch="edge_aware"),
        "gtao high": torch_ao.GTAO(preset="high", **k),
    }


def record_launches(module, gbuffer) -> list:
    """The kernel launches ``module(gbuffer)`` makes: ``(name, grid, block, args)``, the arguments kept."""
    import torch

    launches = []

    class Recorder:
        def __init__(self, name):
            self.name = name

        def __call__(self, grid, block, args):
            launches.append((self.name, grid, block, list(args)))

    real = launch._cuda_kernel
    launch._cuda_kernel = lambda name, index: Recorder(name)
    try:
        with torch.no_grad():
            module(gbuffer)
    finally:
        launch._cuda_kernel = real
    return launches


def run(directory: Path, warmup: int, repeat: int, variants: list[str] | None, chosen: list[str] | None, out_json: str | None):
    import torch
    from torch.cuda._utils import _cuda_load_module

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_cuda import median_ms
    from bench_vs_shader import frame_gbuffer

    device = torch.device("cuda")
    gbuffer = frame_gbuffer("floor_wall", 1080, 1920).to(device=device)
    names = launch.cuda_entry_names()
    binaries = {p.stem: p.read_bytes() for p in sorted(directory.glob("*.cubin"))
                if not variants or p.stem in variants}
    modules = {v: _cuda_load_module(b, list(names)) for v, b in binaries.items()}
    rows = []
    for label, module in cases().items():
        if chosen and not any(s in label for s in chosen):
            continue
        module = module.to(device)
        launches = [l for l in record_launches(module, gbuffer) if l[0].startswith("tao_walk_")]
        reference = None
        for variant, kernels in modules.items():
            times, outs = [], []
            for name, grid, block, args in launches:
                kernel = kernels[name]
                go = lambda: kernel(grid=grid, block=block, args=args)  # noqa: E731
                times.append(median_ms(go, device, warmup=warmup, repeat=repeat))
                outs.append(args[9].clone())  # (walk_cuda.cu's TAO_CUDA_ENTRY: out after the nine inputs)
            if reference is None:
                reference = outs
            gaps = [(a - b).abs().masked_fill(a.isnan() & b.isnan(), 0.0).nan_to_num(1e9) for a, b in zip(outs, reference)]
            diff = max(float(g.max()) for g in gaps)
            share = max(float((g > 1e-6).float().mean()) for g in gaps)
            row = {"case": label, "variant": variant, "ms": sum(times), "max_diff": diff, "share_differing": share,
                   "kernels": [l[0] for l in launches]}
            rows.append(row)
            print(f"{label:32s} {variant:22s} {row['ms']:8.3f} ms  max |d| {diff:.2e}  {100 * share:6.3f} % px",
                  flush=True)
            if out_json:
                Path(out_json).write_text(json.dumps(rows, indent=1))
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("what", choices=("build", "run"))
    p.add_argument("directory", type=Path)
    p.add_argument("--arch", type=int, default=90)
    p.add_argument("--warmup", type=int, default=3, help="launches before the timed ones (ncu: 0)")
    p.add_argument("--repeat", type=int, default=20)
    p.add_argument("--variants", nargs="*")
    p.add_argument("--cases", nargs="*", help="labels' substrings")
    p.add_argument("--json")
    args = p.parse_args(argv)
    if args.what == "build":
        build(args.directory, args.arch, args.variants)
    else:
        run(args.directory, args.warmup, args.repeat, args.variants, args.cases, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
