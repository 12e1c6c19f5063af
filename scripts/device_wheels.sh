#!/usr/bin/env bash
# Download, on this machine, the wheels the GPU machine lacks (it reaches no registry) into .device/wheels
# (git-ignored; name it in the device tool's `carry`). Then, on the GPU machine: bash scripts/device_check.sh
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p .device/wheels
python -m pip download -q --no-deps -d .device/wheels gsplat==1.5.3 hydra-core==1.3.2 omegaconf==2.3.0 \
  antlr4-python3-runtime==4.9.3 kornia
python -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_17_x86_64 \
  -d .device/wheels kornia-rs
ls -la .device/wheels
