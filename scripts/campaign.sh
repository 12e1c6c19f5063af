#!/usr/bin/env bash
# The seven-scene evidence campaign (issue 21), resumable across sessions and machines:
#   bash scripts/campaign.sh [canonical|compression|active|all]     (default: all, in that order)
#   bash scripts/campaign.sh active_ig      issue 42's rows (info_gain, cover) against the archived campaign, own archive
#   bash scripts/campaign.sh ood_sector     issue 42's OOD split (bench.ood_sector: sector against interleaved views)
#
# Runs from a frozen copy of the current commit (a git worktree under $CAMPAIGN/code), so editing this checkout
# while it runs changes nothing in flight. Every finished unit is archived into THIS checkout's bench/results/
# (runs/, compression_runs/, active_view_runs/) as it finishes: commit those folders to keep the progress. Already
# archived units are skipped, so a new session on a new machine just runs this again.
#   CAMPAIGN   work folder for checkpoints and logs (default /work/campaign; never committed)
#   JOBS       parallel jobs, one thread each (default 2: the two cores)
#   SEEDS      seeds of the canonical grid (default "0 1 2"); compression uses seed 0
#   ACTIVE_SEEDS / ACTIVE_SCENES  seeds and scenes of the active-view study (default "0" and all seven)
#   IG_POLICIES  active_ig's rows (default: info_gain +greedy_conditioned, cover, info_gain_params+greedy_conditioned,
#              info_gain top-k, +diverse; info_gain@standard is left out: NIW trains bit for bit like standard and the
#              SH posterior ignores the NIW block, so its rows equal info_gain's); archived in
#              bench/results/active_view_ig_runs, paired with the campaign's rows in bench/results/active_view_ig.md
#   ACTIVE_POLICIES  only these rows (e.g. "uniform,farthest,ensemble,fisher,native,ensemble+diverse,native+diverse",
#              the rows that decide issue 29, with --batches topk and no uniform@niw); default: every row
#   CAMPAIGN_COMMIT  the code commit to run; default: the one pinned in the step's archive (<archive>/CODE_COMMIT,
#              written at the step's first run), else HEAD. A pinned step keeps its code when this checkout's code
#              changes (e.g. kernels that change results bitwise), so every row of a study comes from the same code.
#   B3DGS_SHARED  the shared data folder (default: ../shared beside this checkout)
set -euo pipefail
# The whole script is one brace group ending in exit: bash parses it completely before running anything, so a
# git pull or an edit of this file while a campaign runs (hours) cannot change the commands still to come.
{
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
CAMPAIGN="${CAMPAIGN:-/work/campaign}"
JOBS="${JOBS:-2}"
SEEDS="${SEEDS:-0 1 2}"
SCENES="ethiopian_head fox lego fern flower dtu_scan24 dtu_scan65"
what="${1:-all}"
case "$what" in canonical|compression|active|active_ig|ood_sector|all) ;; *)
  echo "scripts/campaign.sh: unknown step '$what' (fix: one of canonical, compression, active, active_ig, ood_sector, all)" >&2
  exit 2;;
esac
mkdir -p "$CAMPAIGN"
CODE="$CAMPAIGN/code"
[ -d "$CODE" ] || git -C "$ROOT" worktree add -q --detach "$CODE" HEAD
ACTIVE_SEEDS="${ACTIVE_SEEDS:-0}"
ACTIVE_SCENES="${ACTIVE_SCENES:-$SCENES}"
use_code() {  # check out the step's pinned commit in the frozen worktree (results copied out earlier: -f)
  local pin="$1/CODE_COMMIT" commit
  if [ -n "${CAMPAIGN_COMMIT:-}" ]; then commit="$CAMPAIGN_COMMIT"
  elif [ -f "$pin" ]; then commit="$(cat "$pin")"
  else commit="$(git -C "$ROOT" rev-parse HEAD)"; fi
  git -C "$CODE" checkout -q -f --detach "$commit" || {
    echo "scripts/campaign.sh: cannot check out $commit (pinned in $pin; fix: git fetch, or set CAMPAIGN_COMMIT)" >&2; exit 2; }
  mkdir -p "$1"
  [ -f "$pin" ] || echo "$commit" > "$pin"
  echo "=== $(date -u +%FT%TZ) $(basename "$1") with code $(git -C "$CODE" rev-parse --short HEAD)" | tee -a "$log"
}
cd "$CODE"
export PYTHONPATH="$CODE"
export B3DGS_SHARED="${B3DGS_SHARED:-$(cd "$ROOT/.." && pwd)/shared}"  # the data beside this checkout, not the copy's
log="$CAMPAIGN/log.txt"
echo "=== $(date -u +%FT%TZ) campaign $what (checkout at $(git -C "$ROOT" rev-parse --short HEAD))" | tee -a "$log"
R="$ROOT/bench/results"
if [ "$what" = canonical ] || [ "$what" = all ]; then
  # seed by seed, so that each finished seed gives seven paired units; the UQ regimes, the ensembles and the report last
  use_code "$R/runs"
  for seed in $SEEDS; do
    nice -n 19 python -m bench.studies --studies canonical --uq --seeds "$seed" --jobs "$JOBS" --threads 1 \
      --out "$CAMPAIGN/out" --archive "$R/runs" --report "$CAMPAIGN/report" 2>&1 | tee -a "$log"
  done
  # shellcheck disable=SC2086
  nice -n 19 python -m bench.studies --studies canonical --uq --seeds $SEEDS --jobs "$JOBS" --threads 1 \
    --out "$CAMPAIGN/out" --archive "$R/runs" --report "$R/report" 2>&1 | tee -a "$log"
  (cd "$ROOT" && PYTHONPATH="$ROOT" python -m bench.claims > /dev/null)
fi
if [ "$what" = compression ] || [ "$what" = all ]; then
  use_code "$R/compression_runs"
  # shellcheck disable=SC2086
  nice -n 19 python -m bench.compression --scenes $SCENES --seeds 0 --jobs "$JOBS" --bench "$CAMPAIGN/out" \
    --out "$CAMPAIGN/compression" --archive "$R/compression_runs" 2>&1 | tee -a "$log"
  cp bench/results/compression.json bench/results/compression.md "$R/" && rm -rf "$R/compression" && cp -r bench/results/compression "$R/"
fi
if [ "$what" = active ] || [ "$what" = all ]; then
  use_code "$R/active_view_runs"
  rows=()
  [ -z "${ACTIVE_POLICIES:-}" ] || rows=(--batches topk --extra "policies=[$ACTIVE_POLICIES]" "family_baselines=[]")
  # shellcheck disable=SC2086
  nice -n 19 python -m bench.active_view --scenes $ACTIVE_SCENES --seeds $ACTIVE_SEEDS --jobs "$JOBS" \
    --study-out "$CAMPAIGN/study" ${rows[@]+"${rows[@]}"} \
    --archive "$R/active_view_runs" 2>&1 | tee -a "$log"
  # an archived file is final: a later seed's run rewrites meta.json/layout.json (the pinned code lists only its own
  # policies there) and the phase-1 models it retrained (their times); the committed versions are put back
  # (walls.json accumulates and stays; a pathspec, not grep -v, which fails the pipeline when nothing was rewritten)
  git -C "$ROOT" diff --name-only -- bench/results/active_view_runs ':!bench/results/active_view_runs/walls.json' | \
    while read -r f; do git -C "$ROOT" checkout -- "$f"; cp "$ROOT/$f" "$CAMPAIGN/study/${f#bench/results/active_view_runs/}"; done
  # the tables of every scene and seed archived so far, by this checkout's code (not only the scenes just run)
  # shellcheck disable=SC2086
  (cd "$ROOT" && PYTHONPATH="$ROOT" python -m bench.active_view --aggregate-only --scenes $SCENES \
    --study-out "$CAMPAIGN/study" --archive "$R/active_view_runs" 2>&1 | tee -a "$log")
fi
if [ "$what" = active_ig ]; then
  # the new policies' rows only (their phase-1 models are retrained bit for bit like the campaign's, which
  # bench.active_view_extra checks on the oracle errors), then their paired table against the archived campaign
  use_code "$R/active_view_ig_runs"
  IG_POLICIES="${IG_POLICIES:-info_gain+greedy_conditioned,cover,info_gain_params+greedy_conditioned,info_gain+topk,info_gain+diverse}"
  # shellcheck disable=SC2086
  nice -n 19 python -m bench.active_view --scenes $ACTIVE_SCENES --seeds $ACTIVE_SEEDS --jobs "$JOBS" \
    --study-out "$CAMPAIGN/study_ig" --batches topk --extra "policies=[$IG_POLICIES]" "family_baselines=[]" \
    --archive "$R/active_view_ig_runs" 2>&1 | tee -a "$log"
  # shellcheck disable=SC2046
  (cd "$ROOT" && PYTHONPATH="$ROOT" python -m bench.active_view_extra --new "$R/active_view_ig_runs" \
    --policies $(echo "$IG_POLICIES" | tr , ' ' | sed 's/+topk//g') --within cover --name active_view_ig 2>&1 | tee -a "$log")
fi
if [ "$what" = ood_sector ]; then
  # seed 0 on the seven scenes: NIW (uq.json of every regime, held-out view scores) and the standard ensemble
  use_code "$R/ood_sector_runs"
  nice -n 19 python -m bench.ood_sector --jobs "$JOBS" --threads 1 --out "$CAMPAIGN/ood_sector" \
    --archive "$R/ood_sector_runs" --results-root "$R" 2>&1 | tee -a "$log"
fi
(cd "$ROOT" && PYTHONPATH="$ROOT" python -m bench.claims > /dev/null)
echo "=== $(date -u +%FT%TZ) campaign $what done; commit bench/results/ in $ROOT" | tee -a "$log"
exit 0
}
