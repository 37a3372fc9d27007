#!/usr/bin/env bash
# Steps/s of two training runs side by side, as a user starts them (no OMP_NUM_THREADS): the training command's
# default thread count against --num-threads 1 and torch's own default (--num-threads -1).
# Usage: bash scripts/bench_threads.sh [STEPS] [OUT_FOLDER] [TORCH_DEFAULT_STEPS]
#   (default 30000 steps each, /tmp/bench_threads, 3000 for the pair on torch's default: beside each other those
#   two run at < 20 steps/s on 2 cores)
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS="${1:-30000}"
OUT="${2:-/tmp/bench_threads}"
TORCH_DEFAULT_STEPS="${3:-3000}"
PYTHON="${PYTHON:-.venv/bin/python}"
mkdir -p "$OUT"
pair() {  # pair NAME "OPTIONS OF THE FIRST RUN" "OPTIONS OF THE SECOND RUN" [STEPS]
  local name="$1" steps="${4:-$STEPS}"
  echo "$name: load before: $(cut -d' ' -f1-3 /proc/loadavg)"
  for seed in 0 1; do
    local options="$2"; [ "$seed" = 1 ] && options="$3"
    # shellcheck disable=SC2086
    env -u OMP_NUM_THREADS -u MKL_NUM_THREADS "$PYTHON" -m sb3_hhp.train --env MiniGrid-DoorKey-6x6-v0 --oracle scripted \
      -n "$steps" --seed "$seed" --eval-episodes 0 --eval-freq -1 --verbose 0 -f "$OUT/logs_$name" \
      --summary-json "$OUT/${name}_$seed.json" $options >"$OUT/${name}_$seed.log" 2>&1 &
  done
  wait
  for seed in 0 1; do
    "$PYTHON" -c "import json, sys; s = json.load(open(sys.argv[1])); print(f'  seed {sys.argv[2]}: {s[\"fps\"]} steps/s, {s[\"num_threads\"]} thread(s)')" \
      "$OUT/${name}_$seed.json" "$seed"
  done
  echo "$name: load after: $(cut -d' ' -f1-3 /proc/loadavg)"
}
pair default "" ""
pair one_beside_default "--num-threads 1" ""
pair torch_default "--num-threads -1" "--num-threads -1" "$TORCH_DEFAULT_STEPS"
