#!/usr/bin/env bash
# The seven-scene evidence campaign (issue 21), resumable across sessions and machines:
#   bash scripts/campaign.sh [canonical|compression|active|all]     (default: all, in that order)
#
# Runs from a frozen copy of the current commit (a git worktree under $CAMPAIGN/code), so editing this checkout
# while it runs changes nothing in flight. Every finished unit is archived into THIS checkout's bench/results/
# (runs/, compression_runs/, active_view_runs/) as it finishes: commit those folders to keep the progress. Already
# archived units are skipped, so a new session on a new machine just runs this again.
#   CAMPAIGN   work folder for checkpoints and logs (default /work/campaign; never committed)
#   JOBS       parallel jobs, one thread each (default 2: the two cores)
#   SEEDS      seeds of the canonical grid (default "0 1 2"); compression and active view use seed 0
#   B3DGS_SHARED  the shared data folder (default: ../shared beside this checkout)
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
CAMPAIGN="${CAMPAIGN:-/work/campaign}"
JOBS="${JOBS:-2}"
SEEDS="${SEEDS:-0 1 2}"
SCENES="ethiopian_head fox lego fern flower dtu_scan24 dtu_scan65"
what="${1:-all}"
case "$what" in canonical|compression|active|all) ;; *)
  echo "scripts/campaign.sh: unknown step '$what' (fix: one of canonical, compression, active, all)" >&2; exit 2;;
esac
mkdir -p "$CAMPAIGN"
CODE="$CAMPAIGN/code"
if [ -d "$CODE" ]; then
  git -C "$CODE" checkout -q --detach "$(git -C "$ROOT" rev-parse HEAD)"
else
  git -C "$ROOT" worktree add -q --detach "$CODE" HEAD
fi
cd "$CODE"
export PYTHONPATH="$CODE"
export B3DGS_SHARED="${B3DGS_SHARED:-$(cd "$ROOT/.." && pwd)/shared}"  # the data beside this checkout, not the copy's
log="$CAMPAIGN/log.txt"
echo "=== $(date -u +%FT%TZ) campaign $what at $(git rev-parse --short HEAD)" | tee -a "$log"
R="$ROOT/bench/results"
if [ "$what" = canonical ] || [ "$what" = all ]; then
  # seed by seed, so that each finished seed gives seven paired units; the UQ regimes, the ensembles and the report last
  for seed in $SEEDS; do
    nice -n 19 python bench/studies.py --studies canonical --uq --seeds "$seed" --jobs "$JOBS" --threads 1 \
      --out "$CAMPAIGN/out" --archive "$R/runs" --report "$CAMPAIGN/report" 2>&1 | tee -a "$log"
  done
  # shellcheck disable=SC2086
  nice -n 19 python bench/studies.py --studies canonical --uq --seeds $SEEDS --jobs "$JOBS" --threads 1 \
    --out "$CAMPAIGN/out" --archive "$R/runs" --report "$R/report" 2>&1 | tee -a "$log"
  (cd "$ROOT" && python bench/claims.py > /dev/null)
fi
if [ "$what" = compression ] || [ "$what" = all ]; then
  # shellcheck disable=SC2086
  nice -n 19 python bench/compression.py --scenes $SCENES --seeds 0 --jobs "$JOBS" --bench "$CAMPAIGN/out" \
    --out "$CAMPAIGN/compression" --archive "$R/compression_runs" 2>&1 | tee -a "$log"
  cp bench/results/compression.json bench/results/compression.md "$R/" && rm -rf "$R/compression" && cp -r bench/results/compression "$R/"
fi
if [ "$what" = active ] || [ "$what" = all ]; then
  # shellcheck disable=SC2086
  nice -n 19 python bench/active_view.py --scenes $SCENES --seeds 0 --jobs "$JOBS" --study-out "$CAMPAIGN/study" \
    --archive "$R/active_view_runs" 2>&1 | tee -a "$log"
  for f in active_view.json active_view.md active_view_8to16.json active_view_8to16.md; do
    [ -f "bench/results/$f" ] && cp "bench/results/$f" "$R/"
  done
  rm -rf "$R/active_view" && cp -r bench/results/active_view "$R/"
fi
(cd "$ROOT" && python bench/claims.py > /dev/null)
echo "=== $(date -u +%FT%TZ) campaign $what done; commit bench/results/ in $ROOT" | tee -a "$log"
