#!/usr/bin/env bash
# The GPU check, for a machine with an NVIDIA GPU (the `device` tool's H200 or any CUDA box), in about five
# minutes: the kernels built (the C++ ones for the tests' CPU side, the CUDA ones once by NVRTC), the CUDA tests
# (they skip without a GPU) and the local memory each horizon backward reserves (benchmarks/cuda_local_memory.py), then
# benchmarks/profile_cuda.py's times against the GPU targets (call, kernels, host waits). Run from the repo
# root. Everything it prints also goes to ${OUT:-gpu-check}/log, the timings to profile_cuda.json beside it.
#
# Packages the machine lacks (kornia on the device tool's image, which has no network) travel as wheels in
# .whl/ (docs/performance.md, "GPU"): they are installed into /tmp/site. A CUDA binary compiled elsewhere for the
# machine's torch and GPU (walk_sm90_<key>.bin, as launch._cuda_binary names it) can travel in .cuda_cache/: it
# is loaded instead of compiling, and compiled afresh if the driver refuses it. Both builds, the lean one and the
# full one (walk.h's TAO_FULL_WALK), are compiled or loaded before the tests.
set -uo pipefail
out=${OUT:-gpu-check}
mkdir -p "$out"
exec > >(tee "$out/log") 2>&1
export PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1 TORCH_AO_CUDA_CACHE=/tmp/torch_ao_cuda
stage() { echo "== $(date +%T) $*"; }
export PYTHONPATH=$PWD
if compgen -G ".whl/*.whl" >/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && export PYTHONPATH=/tmp/site:$PWD
fi
python3 -c "import torch, kornia; assert torch.cuda.is_available(), 'no CUDA device'
print('torch', torch.__version__, 'CUDA', torch.version.cuda, 'kornia', kornia.__version__, torch.cuda.get_device_name())" \
  || exit 1
nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.mem,utilization.gpu --format=csv
stage "build: the C++ forward and backward libraries and the CUDA kernels, side by side"
python3 -c "from torch_ao.kernels.build import cpu_kernels; cpu_kernels()" > "$out/build_forward.txt" 2>&1 &
forward=$!
python3 -c "from torch_ao.kernels import build; build.load_walk_grad_library()" \
  > "$out/build_backward.txt" 2>&1 &
backward=$!
mkdir -p "$TORCH_AO_CUDA_CACHE"
compgen -G ".cuda_cache/*.bin" >/dev/null && cp .cuda_cache/*.bin "$TORCH_AO_CUDA_CACHE"/
timeout 420 python3 -c "import time, torch; from concurrent.futures import ThreadPoolExecutor; from torch_ao.kernels import launch
print('torch', torch.__version__, 'CUDA', torch.version.cuda, 'cached binaries:', sorted(p.name for p in launch.cuda_cache_dir().glob('*.bin')))
jobs = [(full, group) for full in (False, True) for group in launch.cuda_groups()]  # the lean build's groups, the full one's
def load(job):  # (NVRTC runs outside the GIL: the groups compile side by side)
    t = time.time(); k = launch._cuda_kernels(0, *job); return job, k, time.time() - t
start = time.time(); done = list(ThreadPoolExecutor(8).map(load, jobs))
if any(isinstance(k, Exception) for _, k, _ in done) and any(launch.cuda_cache_dir().glob('*.bin')):
    print('a cached binary was refused:', [str(k)[:300] for _, k, _ in done if isinstance(k, Exception)][0])
    [p.unlink() for p in launch.cuda_cache_dir().glob('*.bin')]; launch._cuda_kernels.cache_clear()
    start = time.time(); done = list(ThreadPoolExecutor(8).map(load, jobs))
for (full, group), k, seconds in done:
    if isinstance(k, Exception): raise k
    print(len(k), 'CUDA kernels of the', 'full' if full else 'lean', 'build, group', group, 'in', round(seconds, 1), 's')
print('every group compiled or loaded in', round(time.time() - start, 1), 's')" \
  || echo "gpu_check: the CUDA kernels did not compile"
wait $forward || { echo "gpu_check: C++ forward build failed"; tail -20 "$out/build_forward.txt"; }
wait $backward || { echo "gpu_check: C++ backward build failed"; tail -20 "$out/build_backward.txt"; }
stage "local memory: what each size of the horizon backward reserves on this GPU (a fresh process)"
timeout 90 python3 benchmarks/cuda_local_memory.py || echo "gpu_check: cuda_local_memory failed or timed out"
stage "CUDA tests: those that need a GPU (CI runs the CUDA source's logic on the CPU)"
timeout 200 python3 -m pytest -q -p no:cacheprovider -rfEs --durations=8 \
  tests/test_kernels_cuda.py::test_cuda_kernels_agree_with_the_cpu_operator \
  tests/test_kernels_cuda.py::test_cuda_gbuffer_gradients_agree_with_the_cpu tests/test_stability.py::test_cuda_matches_cpu \
  tests/test_kernels_combinations.py::test_cuda_kernel_agrees_with_the_tensor_walk_on_drawn_options \
  tests/test_kernel_host_reads.py::test_kernel_calls_replay_in_a_cuda_graph \
  || echo "gpu_check: CUDA tests failed or timed out"
stage "timings at 1920x1080: each case's call, its kernels' time on the GPU, launches, host waits, peak memory"
# (a rerun of part of it: GPU_CHECK_CASES="soft high;gtao high" profiles the cases whose labels hold those)
cases=(); [ -n "${GPU_CHECK_CASES:-}" ] && IFS=';' read -ra cases <<< "$GPU_CHECK_CASES" && cases=(--cases "${cases[@]}")
timeout 150 python3 benchmarks/profile_cuda.py "${cases[@]}" --json "$out/profile_cuda.json" \
  || echo "gpu_check: profile_cuda failed or timed out"
if [ -n "${GPU_CHECK_TORCH_ROWS:-}" ]; then  # the tensor walk on the same GPU (a minute: seconds a call)
  stage "the tensor walk's rows: benchmarks/bench_cuda.py"
  timeout 150 python3 benchmarks/bench_cuda.py --cases "(torch)" --json "$out/bench_cuda.json" || echo "gpu_check: bench_cuda failed"
fi
nvidia-smi --query-gpu=clocks.sm,clocks.mem,temperature.gpu,power.draw --format=csv
stage "torch.compile of CUDA kernel modules against eager (GPU_CHECK_COMPILE=0: not)"
[ "${GPU_CHECK_COMPILE:-1}" = 0 ] || timeout 150 python3 -m pytest -q -p no:cacheprovider -rfEs tests/test_compile.py::test_compiled_cuda_kernels_match_eager \
  || echo "gpu_check: torch.compile tests failed or timed out"
stage "torch.compile: the graphs and graph breaks of each kernel family's call on CUDA (benchmarks/compile_breaks.py)"
[ "${GPU_CHECK_COMPILE:-1}" = 0 ] || timeout 150 python3 benchmarks/compile_breaks.py --device cuda \
  || echo "gpu_check: compile_breaks failed or timed out"
stage done
