#!/usr/bin/env bash
# Commit what a running campaign archived, then its tables rebuilt from exactly the committed records:
#   bash scripts/commit_results.sh ["commit message"]
# A campaign keeps archiving while this runs, so the tables are rebuilt (python -m bench.reproduce --only ...) from a
# clean snapshot of HEAD, never from the working tree; tests/test_bench_reproduce.py fails on a results commit whose
# tables do not follow from its records. Archives and their tables (override with ARCHIVES / TABLES):
set -euo pipefail
{
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
cd "$ROOT"
ARCHIVES="${ARCHIVES:-bench/results/active_view_ig_runs bench/results/ood_sector_runs}"
TABLES="${TABLES:-active_view_ig ood_sector}"
msg="${1:-Results (partial): the records the campaigns archived since the last commit}"
# shellcheck disable=SC2086
git add $ARCHIVES
git commit -qm "$msg" || echo "no new records"
snap="$(mktemp -d)"; out="$(mktemp -d)"
trap 'git worktree remove --force "$snap/tree" >/dev/null 2>&1 || true; rm -rf "$snap" "$out"' EXIT
rebuild() {  # the tables "$@" rebuilt from a snapshot of HEAD, copied into bench/results
  git worktree remove --force "$snap/tree" >/dev/null 2>&1 || true
  rm -rf "$out"/*
  git worktree add -q --detach "$snap/tree" HEAD
  python -m bench.reproduce --results "$snap/tree/bench/results" --out "$out" --only "$@" | tail -n 4 || true
  for t in "$@"; do for ext in md json; do
    if [ -f "$out/$t.$ext" ]; then cp "$out/$t.$ext" "bench/results/$t.$ext"; fi
  done; done
}
# shellcheck disable=SC2086
rebuild $TABLES
git add bench/results/*.md bench/results/*.json
git commit -qm "Results: tables rebuilt from the committed records (python -m bench.reproduce --only $TABLES)" \
  || echo "tables unchanged"
rebuild claims claims_two_scenes  # the claims read the tables just committed
git add bench/results/claims*.md bench/results/claims*.json
git commit -qm "Results: claims rebuilt from the committed tables (python -m bench.reproduce --only claims)" \
  || echo "claims unchanged"
git log --oneline | head -n 3
exit 0
}
