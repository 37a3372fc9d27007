#!/usr/bin/env bash
# CI: an installed package trains. Builds the wheel, installs it (its own dependencies, torch's CPU build pinned by
# constraints.txt) into a fresh virtual environment in a temporary folder, and from there, away from the source
# tree, trains 2,000 steps with the default hyperparameter file (package data). pip's cache makes a second run
# light. Usage: bash scripts/check_wheel.sh [PYTHON]   (default: python3.11, else python3)
set -euo pipefail
cd "$(dirname "$0")/.."
REPO="$PWD"
PYTHON="${1:-$(command -v python3.11 || command -v python3)}"
WORK="$(mktemp -d /tmp/sb3_hhp_wheel.XXXXXX)"
trap 'rm -rf "$WORK"' EXIT
start=$SECONDS
"$PYTHON" -m pip wheel -q --no-deps -w "$WORK/wheel" "$REPO"
"$PYTHON" -m venv "$WORK/venv"
"$WORK/venv/bin/python" -m pip install -q torch==2.13.0
"$WORK/venv/bin/python" -m pip install -q -c "$REPO/constraints.txt" "$WORK"/wheel/sb3_hhp-*.whl
echo "check_wheel: built and installed in $((SECONDS - start)) s"
mkdir "$WORK/run"
cd "$WORK/run"
"$WORK/venv/bin/python" -c "import sb3_hhp, sys; assert '$REPO' not in sb3_hhp.__file__, sb3_hhp.__file__"
"$WORK/venv/bin/python" -m sb3_hhp.train --env MiniGrid-Empty-Random-5x5-v0 --oracle scripted -n 2000 \
  --num-threads 1 --eval-episodes 5 --eval-freq -1 --verbose 0 -f "$WORK/run/logs" --summary-json summary.json >train.log 2>&1 \
  || { tail -40 train.log; exit 1; }
"$WORK/venv/bin/python" - <<'PY'
import json

summary = json.load(open("summary.json"))
assert summary["total_timesteps"] >= 2000, summary["total_timesteps"]
assert summary["config"].endswith("sb3_hhp/hyperparams/hhp.yml") and "site-packages" in summary["config"], summary["config"]
print(f"check_wheel: trained {summary['total_timesteps']} steps at {summary['fps']} steps/s from {summary['config']}")
PY
echo "check_wheel: passed in $((SECONDS - start)) s"
