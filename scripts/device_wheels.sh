#!/usr/bin/env bash
# Prepare, on this machine, what the GPU machine lacks (it reaches no registry) in .device/ (git-ignored; name
# `.device` in the device tool's `carry`): the wheels its image does not hold, and the bench scenes (DEVICE_SCENES,
# default fox and ethiopian_head) with the LPIPS weights (DEVICE_LPIPS=0: without) from the shared folder
# ($B3DGS_SHARED, else ../shared). Then, there: bash scripts/device_check.sh [all|profile|paper]
# What it carries (2026-11-28): wheels 14 MB (gsplat 6.5, kornia-rs 5.3, kornia 1.9, the rest 0.6), fox 3.6 MB (67 views,
# 270x480), ethiopian_head 8.9 MB (66 views, 553x553, COLMAP .bin with its SfM points: the smallest COLMAP scene of
# ../shared/data; dtu_scan24 is 12 MB), LPIPS 9.5 MB: .device 36 MB, 40 MiB with the repository. The paper stage
# trains these scenes at their full (carried) resolution; it stops here if the whole would pass 60 MiB.
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p .device/wheels
# pure-Python wheels (antlr4-python3-runtime is an sdist; device_check.sh builds it with --no-build-isolation)
python -m pip download -q --no-deps -d .device/wheels gsplat==1.5.3 hydra-core==1.3.2 omegaconf==2.3.0 \
  antlr4-python3-runtime==4.9.3 kornia plyfile "filelock>=3.30"
python -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .device/wheels kornia-rs
shared=${B3DGS_SHARED:-../shared}
# the scenes the device stages train (DEVICE_SCENES) and, unless DEVICE_LPIPS=0, the LPIPS weights: the whole working
# tree travels, at most 64 MiB, and the repository alone is ~35 MB
mkdir -p .device/shared/data .device/shared/lpips
for scene in ${DEVICE_SCENES:-fox ethiopian_head}; do
  rm -rf ".device/shared/data/$scene"; cp -r "$shared/data/$scene" .device/shared/data/
done
if [[ ${DEVICE_LPIPS:-1} != 0 ]]; then cp "$shared/lpips/lpips_alex.pth" .device/shared/lpips/; fi
du -sh .device/wheels .device/shared
travels=$(( ( $(git ls-files -z | xargs -0 du -cb 2>/dev/null | tail -1 | cut -f1) + $(du -sb .device | cut -f1) ) / 1048576 ))
echo "travels: $travels MiB of 64"
ls -la .device/wheels
if (( travels > 60 )); then
  echo "device_wheels: error: $travels MiB would travel, over the 64 MiB a call carries less a margin (fix: fewer DEVICE_SCENES, or DEVICE_LPIPS=0)" >&2
  exit 2
fi
