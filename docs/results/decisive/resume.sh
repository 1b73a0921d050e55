#!/usr/bin/env bash
# The decisive experiment's runs (PREREGISTRATION.md beside this file): start, resume, save.
#
#   docs/results/decisive/resume.sh start    # start, or resume, every chain of runs, in the background
#   docs/results/decisive/resume.sh status   # epochs done per run, pace and time left, running chains
#   docs/results/decisive/resume.sh save     # copy the runs' small files and resume kits here,
#                                             # and rewrite RESULTS.md's interim tables
#   docs/results/decisive/resume.sh save --files   # the same without RESULTS.md
#
# `start` also starts an autosaver: every $SAVE_EVERY seconds (default 1800) while a chain runs,
# and once after the last one ends, it runs `save --files`, so that a machine lost before the
# next commit loses at most that stretch of the runs wherever the working tree's uncommitted
# files are recovered. Saves take a lock: a manual save waits for an automatic one to finish.
#
# The runs use the pre-registered commit (the one that added PREREGISTRATION.md), from a
# worktree of it ($DECISIVE_TREE, default: ../decisive beside this checkout) with a virtual
# environment of its own, never the tree being edited. On a fresh machine `start` rebuilds the
# worktree and restores every unfinished run directory from the resume kit `save` left here
# (resume/: the last checkpoint, batches.csv and steps.csv exactly as the run wrote them), so
# the re-run sweeps continue each run where its checkpoint stopped; finished runs are skipped.
set -euo pipefail

HERE=$(cd "$(dirname "$0")" && pwd)
MAIN=$(git -C "$HERE" rev-parse --show-toplevel)
COMMIT=$(git -C "$MAIN" log --diff-filter=A --format=%H -- docs/results/decisive/PREREGISTRATION.md | tail -n 1)
TREE=${DECISIVE_TREE:-$(dirname "$MAIN")/decisive}
OUT=$TREE/outputs/decisive
PY=$TREE/.venv/bin/python
TORCH_VERSION=${TORCH_VERSION:-2.13.0}
SAVE_EVERY=${SAVE_EVERY:-1800}

# One chain of sweeps per core, each stage a population (PREREGISTRATION.md, section 2). Arm C
# (the thesis' HMepol) takes the cores that arms A and B free: seeds 0-3 after B's exact trust
# region (the cheaper arm, done first), seeds 4-7 after A's Mepol.
COMMON="progress=false diagnostics=true threads=1 checkpoint.keep_every=50 hydra/launcher=population"
# Mepol's seeds 4-7 ran as one population of 4 to epoch 352; from there (2026-12-03, arm B
# done) they run as two populations of 2, one per chain, so that arm A has both cores before
# arm C takes them, the order section 2 sets. A member computes the same numbers in any
# population (on a CPU each member is its own loop of ordinary calls; tests/test_sweep.py
# checks a population's curves equal separate runs' exactly), so the split changes only the pace.
CHAIN_A=(
  "mepol experiment=corridor_mepol seed=0,1,2,3"
  "mepol experiment=corridor_mepol seed=4,5"
  "hmepol experiment=corridor_hmepol seed=4,5,6,7"
)
CHAIN_B=(
  "mepol experiment=corridor_mepol seed=6,7"
  "exact experiment=corridor_hmepol_exact seed=0,1,2,3"
  "exact experiment=corridor_hmepol_exact seed=4,5,6,7"
  "hmepol experiment=corridor_hmepol seed=0,1,2,3"
)
CHAIN_M=(
  "multigrid experiment=quick_multigrid algo=alphamepol,hmepol seed=0,1,2,3"
)

worktree() {
  [ -n "$COMMIT" ] || { echo "PREREGISTRATION.md is not committed yet" >&2; exit 1; }
  if [ ! -e "$TREE/.git" ]; then
    git -C "$MAIN" worktree prune
    git -C "$MAIN" worktree add --detach "$TREE" "$COMMIT"
  fi
  [ "$(git -C "$TREE" rev-parse HEAD)" = "$COMMIT" ] || {
    echo "$TREE is not at the pre-registered commit $COMMIT" >&2; exit 1; }
  if [ ! -x "$TREE/.venv/bin/hmepol" ]; then
    python3 -m venv "$TREE/.venv"
    "$PY" -m pip install --quiet "torch==$TORCH_VERSION"
    "$PY" -m pip install --quiet -e "$TREE"
  fi
}

# A run directory saved here but absent (or behind) in the worktree: rebuilt from its resume kit.
# A finished run (no kit) gets back its small files, so that the sweep skips it, not reruns it.
restore() {
  local kit run target
  for run in "$HERE"/*/*/; do
    run=${run%/}
    grep -qs '"status": "finished"' "$run/run.json" || continue
    target=$OUT/${run#"$HERE"/}
    grep -qs '"status": "finished"' "$target/run.json" && continue
    echo "restoring the finished $target from its small files"
    rm -rf "$target"; mkdir -p "$target"
    cp "$run/config.yaml" "$run/run.json" "$run/epochs.csv" "$target/"
    [ -f "$run/steps.csv.gz" ] && gunzip -c "$run/steps.csv.gz" > "$target/steps.csv"
    [ -d "$run/eval" ] && cp -r "$run/eval" "$target/"
  done
  for kit in "$HERE"/*/*/resume; do
    [ -f "$kit/last.pt" ] || continue
    run=$(dirname "$kit")
    target=$OUT/${run#"$HERE"/}
    [ -f "$target/checkpoints/last.pt" ] && continue
    echo "restoring $target from its resume kit"
    mkdir -p "$target/checkpoints"
    cp "$run/config.yaml" "$run/run.json" "$run/epochs.csv" "$target/"
    cp "$kit/last.pt" "$target/checkpoints/last.pt"
    gunzip -c "$kit/batches.csv.gz" > "$target/batches.csv"
    gunzip -c "$run/steps.csv.gz" > "$target/steps.csv"
    [ -f "$kit/commands.log" ] && cp "$kit/commands.log" "$target/"
  done
}

chain() {  # name, then its stages: one background shell runs them one after the other
  local name=$1; shift
  if running "$name"; then echo "chain $name is running (pid $(cat "$OUT/$name.pid"))"; return; fi
  local script="cd '$TREE'"
  local stage arm overrides
  for stage in "$@"; do
    arm=${stage%% *}; overrides=${stage#* }
    script+=" && nice -n 19 .venv/bin/hmepol sweep $overrides $COMMON hydra.sweep.dir=$OUT/$arm"
  done
  mkdir -p "$OUT"
  nohup bash -c "$script" >> "$OUT/$name.log" 2>&1 &
  echo $! > "$OUT/$name.pid"
  echo "chain $name started (pid $!), log $OUT/$name.log"
}

# Per run: epochs done, status and, while it runs, its pace (median seconds of its last 10
# epochs) and the time that pace leaves to its last epoch.
status() {
  "$PY" - "$OUT" <<'PYTHON'
import csv, json, statistics, sys
from pathlib import Path
out = Path(sys.argv[1])
for run in sorted(p.parent for p in out.glob("*/*/epochs.csv")):
    with open(run / "epochs.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    info = json.loads((run / "run.json").read_text())
    line = f"{str(run.relative_to(out)) + '/':<70} {len(rows):4d} epochs  {info['status']}"
    seconds = [float(r["seconds"]) for r in rows[-10:] if r.get("seconds")]
    if info["status"] == "running" and seconds:
        pace = statistics.median(seconds)
        left = max(0, info["epochs"] - len(rows)) * pace / 3600
        line += f"  {pace:.0f} s/epoch, {left:.1f} h left at that pace"
    print(line)
PYTHON
  for name in A B M; do
    if running "$name"; then echo "chain $name running"; else echo "chain $name not running"; fi
  done
  if running S; then echo "autosaver running (every ${SAVE_EVERY}s)"; else echo "autosaver not running"; fi
  [ -f "$OUT/last_save" ] && echo "last save: $(cat "$OUT/last_save")"
  return 0
}

running() { [ -f "$OUT/$1.pid" ] && kill -0 "$(cat "$OUT/$1.pid")" 2>/dev/null; }

autosaver() {
  if running S; then echo "autosaver is running (pid $(cat "$OUT/S.pid"))"; return; fi
  nohup bash -c "
    alive() { for n in A B M; do [ -f '$OUT/'\$n.pid ] && kill -0 \$(cat '$OUT/'\$n.pid) 2>/dev/null && return 0; done; return 1; }
    while alive; do
      for _ in \$(seq $SAVE_EVERY); do alive || break; sleep 1; done
      '$HERE/resume.sh' save --files
    done" >> "$OUT/S.log" 2>&1 &
  echo $! > "$OUT/S.pid"
  echo "autosaver started (pid $!, every ${SAVE_EVERY}s), log $OUT/S.log"
}

# The checkpoint is copied first, the tables after it: they then hold at least the epochs the
# checkpoint covers (resume drops the rows past it). Finished runs need no kit.
save() {
  exec 9> "$OUT/save.lock"
  flock 9
  local run arm dest
  for run in "$OUT"/*/*/; do
    run=${run%/}
    [ -f "$run/run.json" ] || continue
    dest=$HERE/${run#"$OUT"/}
    if grep -q '"status": "finished"' "$run/run.json"; then
      rm -rf "$dest/resume"
    elif [ -f "$run/checkpoints/last.pt" ]; then
      mkdir -p "$dest/resume"
      cp "$run/checkpoints/last.pt" "$dest/resume/last.pt.tmp"
      gzip -c -n "$run/batches.csv" > "$dest/resume/batches.csv.gz.tmp"
      cp "$run/commands.log" "$dest/resume/commands.log.tmp"
      for f in last.pt batches.csv.gz commands.log; do mv "$dest/resume/$f.tmp" "$dest/resume/$f"; done
    fi
  done
  for arm in "$OUT"/*/; do
    # this checkout's export (it writes every file whole), with the runs' environment
    PYTHONPATH=$MAIN "$PY" -m hmepol_cli.report.export "$arm" "$HERE/$(basename "$arm")"
  done
  [ "${1:-}" = --files ] || "$PY" "$HERE/analysis.py" --results "$MAIN/RESULTS.md" > /dev/null
  date -u '+%Y-%m-%d %H:%M:%S UTC' > "$OUT/last_save"
  flock -u 9
}

case "${1:-}" in
  start)
    worktree; restore
    chain A "${CHAIN_A[@]}"; chain B "${CHAIN_B[@]}"; chain M "${CHAIN_M[@]}"; autosaver ;;
  status) status ;;
  save) save "${2:-}" ;;
  *) echo "usage: $0 start | status | save [--files]" >&2; exit 2 ;;
esac
