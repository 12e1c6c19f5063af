#!/usr/bin/env bash
# On the GPU machine (Python 3.12, torch+CUDA, lightning, nvcc, ninja; no registry): install the carried
# wheels, then run the CUDA tests and the GPU benchmarks, writing everything under $OUT as it finishes
# (a command is cut at 10 minutes). Usage: bash scripts/device_check.sh [tests|render|train|all]
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-outputs/device}
mkdir -p "$OUT"
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
pip install -q --no-deps --no-index --no-build-isolation .device/wheels/* >/dev/null 2>&1 || true
pip install -q --no-deps -e . >/dev/null 2>&1
what=${1:-all}
if [[ $what == tests || $what == all ]]; then
  python -m pytest -q -rs -m cuda 2>&1 | tee "$OUT/pytest_cuda.txt"
  # gsplat on the GPU against the same tests on its CPU emulation (tests/gsplat_cpu.py); the real kernels
  # use fast math, so test_gsplat_matches_torch[cuda] allows 1e-4 where the emulation holds 1e-5
  python -m pytest -q -rs -k gsplat 2>&1 | tee "$OUT/pytest_gsplat.txt"
fi
if [[ $what == render || $what == all ]]; then
  python bench/render.py --renderers cpu gsplat torch --sizes 10000 100000 2>&1 | tee "$OUT/render.txt"
  cp bench/results/render.* "$OUT/" 2>/dev/null
fi
if [[ $what == train || $what == all ]]; then
  python bench/train.py --device cuda --scenes fox --models standard niw dpmm 2>&1 | tee "$OUT/train_cuda.txt"
  cp bench/results/train_cuda.* "$OUT/" 2>/dev/null
fi
