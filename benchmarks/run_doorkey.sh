#!/usr/bin/env bash
# The DoorKey-8x8 benchmark, every run in parallel (one core each): HhP on 3 seeds (evaluation seeds
# 10_000+), flat SB3 DQN and PPO with the same step budget, and HhP variants on a tuning seed (100,
# evaluation seeds 20_000+, never the final ones). Results land in $1 (default benchmarks/results).
#   bash benchmarks/run_doorkey.sh benchmarks/results 500000
set -u
out=${1:-benchmarks/results}; steps=${2:-500000}; env=${ENV_ID:-MiniGrid-DoorKey-8x8-v0}
mkdir -p "$out"
# small MLPs stepped one observation at a time run faster on the CPU: on a GPU every step is a kernel launch
export CUDA_VISIBLE_DEVICES=""
run() { local name=$1; shift; nohup python benchmarks/doorkey.py --env "$env" --steps "$steps" --out "$out/$name.json" "$@" > "$out/$name.log" 2>&1 & }
for seed in 0 1 2; do run "hhp_s$seed" --algo hhp --seed "$seed" --eval-every 50000; done
run dqn_s0 --algo dqn --seed 0
run ppo_s0 --algo ppo --seed 0
tune="--eval-every 50000 --algo hhp --seed 100 --eval-seed-offset 20000 --eval-episodes 50"
run v_cur $tune --tag cur --hhp-kwargs '{"use_preferences": false}'
run v_noshare $tune --tag noshare --hhp-kwargs '{"share_experience": false}'
run v_nopt32 $tune --tag nopt32 --hhp-kwargs '{"n_opt": 32}'
run v_msteps100 $tune --tag msteps100 --hhp-kwargs '{"max_subgoal_steps": 100}'
run v_beta03 $tune --tag beta03 --hhp-kwargs '{"beta": 0.3}'
run v_random $tune --tag random_discovery --hhp-kwargs '{"discovery": "random"}'
run v_fixed_linear_std $tune --tag fixed_linear_std --hhp-kwargs '{"query_mode": "fixed"}'
run v_fixed_sigmoid_std $tune --tag fixed_sigmoid_std --hhp-kwargs '{"query_mode": "fixed", "predictor_head": "sigmoid"}'
run v_fixed_sigmoid_var $tune --tag fixed_sigmoid_var --hhp-kwargs '{"query_mode": "fixed", "predictor_head": "sigmoid", "confidence_spread": "var"}'
wait
