#!/usr/bin/env bash
# On the GPU machine (Python 3.12, torch+CUDA, lightning, nvcc, ninja; no registry): install what
# scripts/device_wheels.sh carried in .device/, then run the CUDA tests and the GPU benchmarks, writing each
# stage's log under $OUT as it finishes. Each stage has its own time limit (seconds, env STAGE_LIMIT_<name>),
# so one slow stage cannot eat the call, and all end by DEADLINE (seconds, default 540).
# Usage: [DEADLINE=S] [STAGE_LIMIT_<name>=S] bash scripts/device_check.sh [tests|render|train|all|profile|paper] [--dry-run]
# profile (issue 43, GPU parity): host syncs per step (CUDA's own count), torch.profiler of a DPMM step, and standard /
# NIW / DPMM on fox and ethiopian_head, seeds 0-1, quick protocol, on gsplat; then bench/results/device_<card>.{md,json}.
# It resumes: run it again on the same (warm) machine and finished runs are kept. Its logs go to one file, log.txt, and
# its results to $OUT (the device tool returns at most 8 files).
# paper (issue 51, bench/device_paper.py): (a) parity as profile's (standard / NIW / DPMM, fox and ethiopian_head, seeds
# 0-1, quick protocol), (b) the paper's protocol at 7k steps, b3dgs standard beside a bare gsplat loop
# (bench/gsplat_loop.py), then NIW and DPMM, (c) standard at 30k on one scene: in that priority, each run started only
# if it fits before DEADLINE, resumable; $OUT gets log.txt and device_<card>.{md,json}. PAPER_ARGS: extra arguments of
# bench.device_paper (e.g. "--parts parity paper"). --dry-run (or DRY_RUN=1): the same stage on the CPU at a tiny
# size, no GPU, no installs (the carried scenes if .device has them, else ../shared's, else the synthetic scene).
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-outputs/device}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0}
export MAX_JOBS=${MAX_JOBS:-$(nproc)}
PY=$(command -v python3 || command -v python)
what=${1:-all}
dry=""  # --dry-run / DRY_RUN=1: the paper stage on the CPU (no nvidia-smi, installs or gsplat build)
[[ ${2:-} == --dry-run || ${DRY_RUN:-0} == 1 ]] && dry=1
DEADLINE=${DEADLINE:-540}  # seconds for the whole check (the device tool cuts a command at 600)
t0=$(date +%s)
LOGNAME_ALL=""  # profile: every stage's output in $OUT/log.txt
[[ $what == profile || $what == paper ]] && LOGNAME_ALL=log.txt
stage() {  # stage NAME LIMIT_S CMD...: run CMD under a time limit, its output to $OUT/NAME.txt (or log.txt) and here
  local name=$1 limit=$2; shift 2
  local logf="$OUT/${LOGNAME_ALL:-$name.txt}"
  local var="STAGE_LIMIT_${name}"; limit=${!var:-$limit}
  local left=$(( DEADLINE - ($(date +%s) - t0) ))  # never past the whole check's deadline
  (( left < limit )) && limit=$left
  if (( limit < 10 )); then echo "== $name skipped: under 10 s left of its limit or of the ${DEADLINE}s deadline" | tee -a "$logf"; return; fi
  echo "== $name (limit ${limit}s, at +$(( $(date +%s) - t0 ))s)" | tee -a "$logf"
  timeout --kill-after=10 "$limit" "$@" > >(tee -a "$logf") 2>&1
  local rc=$?
  echo "== $name rc=$rc after +$(( $(date +%s) - t0 ))s" | tee -a "$logf"
}
[[ -z $dry ]] && {
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
  nvcc --version | tail -2
  "$PY" -c "import torch, sys; print(sys.version.split()[0], torch.__version__, torch.version.cuda, torch.cuda.is_available())"
  # the carried wheels (antlr4's sdist builds with the image's setuptools), then b3dgs itself, without a registry
  if [[ -d .device/wheels ]]; then
    "$PY" -m pip install -q --no-deps --no-index --no-build-isolation .device/wheels/* 2>&1 | grep -v "root' user"
  fi
  "$PY" -m pip install -q --no-deps --no-index --no-build-isolation -e . 2>&1 | grep -v "root' user" \
    || echo "editable install failed; using PYTHONPATH"
  "$PY" -m pip list 2>/dev/null | grep -i -E "^(torch|lightning|gsplat|hydra-core|omegaconf|kornia|filelock) "
} 2>&1 | tee -a "$OUT/${LOGNAME_ALL:-setup.txt}"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
if [[ -d .device/shared/data ]]; then  # the carried bench scene and LPIPS weights
  export B3DGS_SHARED="$PWD/.device/shared"
  [[ -f .device/shared/lpips/lpips_alex.pth ]] && export B3DGS_LPIPS_WEIGHTS="$PWD/.device/shared/lpips/lpips_alex.pth"
fi
# gsplat's JIT build (minutes) starts now, beside the C++ CPU extension's build that the first test triggers (paper
# needs no C++ extension: only gsplat's build runs)
if [[ -z $dry ]]; then
  stage gsplat_build 300 "$PY" -c \
    "import time; t=time.time(); from gsplat.cuda._backend import _C; print('gsplat _C', _C is not None, round(time.time()-t, 1), 's')" &
  build_pid=$!
  [[ $what == paper ]] || "$PY" -c "import time; t=time.time(); from b3dgs.render._ext import load_extension; load_extension(); print('b3dgs C++ ext', round(time.time()-t,1), 's')" \
    2>&1 | tee -a "$OUT/${LOGNAME_ALL:-setup.txt}" || true
  wait $build_pid
fi
if [[ $what == tests || $what == all ]]; then
  # the CUDA-marked tests, then gsplat's on its CPU emulation (tests/gsplat_cpu.py); the real kernels use fast
  # math, so test_gsplat_matches_torch[cuda] allows 1e-4 where the emulation holds 1e-5
  stage pytest_cuda 240 "$PY" -m pytest -q -rs --durations=8 -p no:cacheprovider -m cuda
fi
if [[ $what == train || $what == all ]]; then
  stage train_cuda 240 "$PY" -m bench.train --device cuda --scenes fox --models standard niw dpmm
  cp bench/results/train_cuda.json "$OUT/" 2>/dev/null
fi
if [[ $what == render || $what == all ]]; then
  stage render 120 "$PY" -m bench.render --renderers cpu gsplat torch --sizes 10000 100000
  cp bench/results/render.json "$OUT/" 2>/dev/null
fi
if [[ $what == tests || $what == all ]]; then  # last: it needs no GPU, only this machine's torch
  stage pytest_gsplat 120 "$PY" -m pytest -q -rs -p no:cacheprovider -k gsplat -m "not cuda"
fi
if [[ $what == profile ]]; then
  R=outputs/device/results  # ignored: kept on a warm machine between calls, so a second call resumes
  mkdir -p "$R"
  card=$("$PY" -c "import torch; n=torch.cuda.get_device_name(0).lower(); print(next((c for c in ('h200','h100','a100','l40s','l4') if c in n), 'gpu'))")
  # PROFILE_SCENES / PROFILE_SEEDS: the trainings (default: fox and ethiopian_head, seeds 0 1; a COLMAP scene needs
  # pycolmap there); PROFILE_QUICK=1: the trainings first, then the syncs of DPMM alone, no torch.profiler stage
  scenes=${PROFILE_SCENES:-fox ethiopian_head}; seeds=${PROFILE_SEEDS:-0 1}
  if [[ ${PROFILE_QUICK:-0} == 1 ]]; then
    stage train_cuda 900 "$PY" -m bench.train --device cuda --scenes $scenes --models standard niw dpmm --seeds $seeds \
      --results "$R"
    stage host_syncs 90 "$PY" -m bench.host_syncs --device cuda --steps 300 --models dpmm --results "$R"
  else
    # first the two short stages (what a step costs and why), then the trainings that decide (12 runs, resumable)
    [[ -f $R/step_profile_cuda.json ]] || stage step_profile 60 "$PY" -m bench.device_profile profile --device cuda \
      --models dpmm --results "$R"
    stage host_syncs 90 "$PY" -m bench.host_syncs --device cuda --steps 300 --models niw dpmm --results "$R"
    stage train_cuda 900 "$PY" -m bench.train --device cuda --scenes $scenes --models standard niw dpmm \
      --seeds $seeds --results "$R"
  fi
  STAGE_LIMIT_report=30 DEADLINE=$(( DEADLINE + 30 )) stage report 30 "$PY" -m bench.device_profile report --card "$card" --results "$R"
  cp "$R"/device_*.md "$R"/device_*.json "$R"/train_cuda.json "$R"/host_syncs_cuda.md "$R"/step_profile_cuda.json "$OUT"/ 2>/dev/null
fi
if [[ $what == paper ]]; then
  W=outputs/device/paper  # ignored: kept on a warm machine between calls, so a second call resumes
  dry_args=()
  [[ -n $dry ]] && { W=outputs/device/paper_dry; dry_args=(--dry-run); }
  left=$(( DEADLINE - ($(date +%s) - t0) ))
  # the runs start only while they fit before the deadline less 30 s (a run may outlast its estimate; the stage's
  # time limit ends it, and the report of the runs before it is already written)
  stage paper "$left" "$PY" -m bench.device_paper --work "$W" --out "$OUT" --deadline-s $(( left - 30 )) \
    "${dry_args[@]}" ${PAPER_ARGS:-}
fi
echo "device_check done after +$(( $(date +%s) - t0 ))s"
