#!/usr/bin/env bash
# The geometry rows of acquisition=info_gain (issue 42's centre term) on the issue-42 campaign's phase-1 models:
#   bash scripts/geometry_rows.sh            (resumable: finished rows are never retrained; run it again to continue)
#
# Each scene-seed's study folder is seeded with a COPY of the campaign's phase-1 model ($IG_STUDY/<scene>/phase1/
# niw_s<seed>, checkpoint + phase1.json + oracle.json) and its protocol.json, so phase 1 is not retrained (the study
# reuses a phase-1 folder that has phase1.json and checkpoints/last.ckpt, and refuses a protocol.json that differs
# from its settings); $IG_STUDY is only read. Then only the new rows are trained (bench.active_view --extra, as
# scripts/campaign.sh active_ig), archived into bench/results/active_view_geo_runs as they finish, and paired with
#   the committed campaign's rows   -> bench/results/active_view_geo.{md,json}
#   issue 42's info_gain/cover rows -> bench/results/active_view_geo_ig.{md,json} (their archive, same phase-1 models)
# by bench.active_view_extra (which checks every phase-1 oracle error against the archive's: a copy passes).
#   IG_STUDY     the campaign's study folder with the phase-1 models (default /work/campaign/study_ig; read only)
#   GEO_OUT      this study's folder (default /tmp/geo_study; checkpoints, logs, a frozen code worktree; not committed)
#   GEO_POLICIES the rows (default info_gain_geometry,info_gain_geometry+greedy_conditioned)
#   GEO_SCENES / GEO_SEEDS  default the seven scenes / "0" (the seeds whose phase-1 models $IG_STUDY holds)
#   JOBS         scene-seeds at once, one thread each (default 2)
#   GEO_ARCHIVE / GEO_TABLES  the archive / the tables' folder instead of bench/results/active_view_geo_runs /
#                bench/results (a trial run that must not touch the committed results)
#   GEO_COMMIT   the code commit to run; default the one pinned in the archive (CODE_COMMIT, written at the first
#                run), else HEAD: every row of the study comes from the same code
#   B3DGS_SHARED the shared data folder (default: ../shared beside this checkout)
set -euo pipefail
{
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
IG_STUDY="${IG_STUDY:-/work/campaign/study_ig}"
OUT="${GEO_OUT:-/tmp/geo_study}"
GEO_POLICIES="${GEO_POLICIES:-info_gain_geometry,info_gain_geometry+greedy_conditioned}"
GEO_SCENES="${GEO_SCENES:-ethiopian_head fox lego fern flower dtu_scan24 dtu_scan65}"
GEO_SEEDS="${GEO_SEEDS:-0}"
JOBS="${JOBS:-2}"
R="$ROOT/bench/results"
ARCH="${GEO_ARCHIVE:-$R/active_view_geo_runs}"
TABLES="${GEO_TABLES:-$R}"
mkdir -p "$OUT" "$ARCH" "$TABLES"
log="$OUT/log.txt"
for scene in $GEO_SCENES; do
  for seed in $GEO_SEEDS; do
    src="$IG_STUDY/$scene/phase1/niw_s$seed" dst="$OUT/$scene/phase1/niw_s$seed"
    [ -f "$dst/phase1.json" ] && [ -f "$dst/checkpoints/last.ckpt" ] && continue
    if ! { [ -f "$src/phase1.json" ] && [ -f "$src/checkpoints/last.ckpt" ]; }; then
      echo "scripts/geometry_rows.sh: no finished phase-1 model in $src (fix: set IG_STUDY to the issue-42 study folder)" >&2
      exit 2
    fi
    rm -rf "$dst.part" && mkdir -p "$(dirname "$dst")" && cp -r "$src" "$dst.part" && rm -rf "$dst" && mv "$dst.part" "$dst"
  done
  [ -f "$OUT/$scene/protocol.json" ] || cp "$IG_STUDY/$scene/protocol.json" "$OUT/$scene/protocol.json"
done
CODE="$OUT/code"
[ -d "$CODE" ] || git -C "$ROOT" worktree add -q --detach "$CODE" HEAD
if [ -n "${GEO_COMMIT:-}" ]; then commit="$GEO_COMMIT"
elif [ -f "$ARCH/CODE_COMMIT" ]; then commit="$(cat "$ARCH/CODE_COMMIT")"
else commit="$(git -C "$ROOT" rev-parse HEAD)"; fi
git -C "$CODE" checkout -q -f --detach "$commit"
[ -f "$ARCH/CODE_COMMIT" ] || echo "$commit" > "$ARCH/CODE_COMMIT"
export B3DGS_SHARED="${B3DGS_SHARED:-$(cd "$ROOT/.." && pwd)/shared}"
echo "=== $(date -u +%FT%TZ) geometry rows $GEO_POLICIES on $GEO_SCENES seeds $GEO_SEEDS," \
  "code $(git -C "$CODE" rev-parse --short HEAD)" | tee -a "$log"
# shellcheck disable=SC2086
(cd "$CODE" && PYTHONPATH="$CODE" nice -n 19 python -m bench.active_view --scenes $GEO_SCENES --seeds $GEO_SEEDS \
  --jobs "$JOBS" --study-out "$OUT" --batches topk --extra "policies=[$GEO_POLICIES]" "family_baselines=[]" \
  --archive "$ARCH" 2>&1 | tee -a "$log")
pols="$(echo "$GEO_POLICIES" | tr , ' ' | sed 's/+topk//g')"
# shellcheck disable=SC2086
(cd "$ROOT" && PYTHONPATH="$ROOT" python -m bench.active_view_extra --new "$ARCH" --policies $pols \
  --within $pols --results-root "$TABLES" --name active_view_geo 2>&1 | tee -a "$log")
# shellcheck disable=SC2086
(cd "$ROOT" && PYTHONPATH="$ROOT" python -m bench.active_view_extra --new "$ARCH" --policies $pols \
  --archive "$R/active_view_ig_runs" --against info_gain info_gain+greedy_conditioned info_gain+diverse \
  info_gain_params+greedy_conditioned cover --results-root "$TABLES" --name active_view_geo_ig 2>&1 | tee -a "$log")
echo "=== $(date -u +%FT%TZ) geometry rows done; commit bench/results/active_view_geo* in $ROOT" | tee -a "$log"
exit 0
}
