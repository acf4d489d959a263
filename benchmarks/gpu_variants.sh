#!/usr/bin/env bash
# Where the CUDA walk's time goes, on a machine with an NVIDIA GPU, in about three minutes: benchmarks/cuda_variants.py
# times the compile and sampling variants whose binaries travel in .cuda_variants/ (built off the GPU:
# `python benchmarks/cuda_variants.py build .cuda_variants`), then Nsight Compute (where the machine has it)
# profiles the base kernels of three cases. Run from the repo root; everything goes to ${OUT:-gpu-variants}/.
set -uo pipefail
out=${OUT:-gpu-variants}
mkdir -p "$out"
exec > >(tee "$out/log") 2>&1
export PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1 PYTHONPATH=$PWD
stage() { echo "== $(date +%T) $*"; }
if compgen -G ".whl/*.whl" >/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && export PYTHONPATH=/tmp/site:$PWD
fi
nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.mem --format=csv
stage "variants"
timeout 240 python3 benchmarks/cuda_variants.py run .cuda_variants --json "$out/variants.json" ${GPU_VARIANTS_ARGS:-} \
  || echo "gpu_variants: the variants failed or timed out"
if command -v ncu >/dev/null && [ "${GPU_VARIANTS_NCU:-1}" = 1 ]; then
  stage "Nsight Compute: the base kernels of hard high, exact + backface + edge_aware, gtao high"
  timeout 240 ncu --clock-control none -k regex:tao_walk_ --launch-count 3 --set detailed \
    --section SourceCounters --section WarpStateStats --import-source no -f -o "$out/walk" \
    python3 benchmarks/cuda_variants.py run .cuda_variants --variants base --warmup 0 --repeat 1 \
      --cases "hard high (3x3)" "exact + backface" "gtao high" > "$out/ncu_run.txt" 2>&1 \
    || { echo "gpu_variants: ncu failed"; tail -30 "$out/ncu_run.txt"; }
  if [ -f "$out/walk.ncu-rep" ]; then
    ncu -i "$out/walk.ncu-rep" --page details --print-units base > "$out/ncu_details.txt" 2>&1
    ncu -i "$out/walk.ncu-rep" --page source --csv --print-source sass > "$out/ncu_sass.csv" 2>&1 \
      || echo "gpu_variants: no source page"
    grep -E "tao_walk|Duration|Registers Per|Achieved Occupancy|Theoretical Occupancy|Compute \(SM\) Throughput|Memory Throughput|L1/TEX Hit|L2 Hit|Executed Ipc A|Issue Slots Busy|No Eligible|Warp Cycles Per Issued|Local Memory" \
      "$out/ncu_details.txt" | head -80
  fi
fi
stage done
