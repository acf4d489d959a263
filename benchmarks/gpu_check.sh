#!/usr/bin/env bash
# The GPU check, for a machine with an NVIDIA GPU (the `device` tool's H200 or any CUDA box), in well
# under 8 minutes: the CUDA tests (they skip without a GPU) and the CUDA benchmarks. Run from the repo
# root. Everything it prints also goes to ${OUT:-gpu-check}/log.
set -uo pipefail
out=${OUT:-gpu-check}
mkdir -p "$out"
exec > >(tee "$out/log") 2>&1
export PYTHONUNBUFFERED=1
python3 -c "import torch; assert torch.cuda.is_available(), 'no CUDA device'; print(torch.__version__, torch.cuda.get_device_name())" || exit 1
python3 -m pip install -q --no-deps -e . 2>/dev/null || export PYTHONPATH=$PWD
python3 -c "import kornia" 2>/dev/null || python3 -m pip install -q kornia
# CUDA tests: every test that names cuda (they skip cleanly on CPU-only machines).
timeout 150 python3 -m pytest -q -x -k cuda tests || echo "gpu_check: CUDA tests failed or timed out"
# 1920x1080 high (3x3) hard bitmask AO, soft forward+backward, batch 8; horizon methods at 1280x720.
timeout 60 python3 benchmarks/bench_bitmask.py --device cuda --size 1920x1080 --repeat 5 || echo "gpu_check: bench_bitmask failed"
timeout 60 python3 benchmarks/bench_methods.py --device cuda --sizes 1280x720 --repeats 3 || echo "gpu_check: bench_methods failed"
# the soft kernel with radius/thickness and with G-buffer gradients (tao_soft_backward), and the hard cosine and exact
# union kernels with G-buffer gradients (tao_hard_backward, tao_exact_backward) at 1920x1080, 4 x 3 (high's steps)
timeout 150 python3 benchmarks/bench_bitmask.py --soft-kernel --device cuda --size 1920x1080 --steps 3 --repeat 5 || echo "gpu_check: soft kernel table failed"
