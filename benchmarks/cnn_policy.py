"""``HhP("CnnPolicy", gym.make(ENV)).learn(STEPS)`` with the class defaults, then the stochastic and the deterministic
policy on fresh episodes: does the small grid CNN (``GridCNN``) learn a MiniGrid task as users would first try it?

    python benchmarks/cnn_policy.py --env MiniGrid-DoorKey-5x5-v0 --steps 60000 --seeds 0 1 2

One torch thread; one JSON file per seed under ``--out`` (success rates, mean returns, questions, sub-goals, training
time, the machine's load average at the start and end). Evaluation episodes use seeds ``seed + 10000 + i``, never a
training seed.
"""

import argparse
import json
import os
import pathlib
import time

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env
from sb3_hhp.train import eval_seeds, evaluate


def run(env_id: str, steps: int, seed: int, episodes: int) -> dict:
    th.set_num_threads(1)
    load_start = os.getloadavg()[0]
    model = HhP("CnnPolicy", gym.make(env_id), seed=seed, device="cpu")
    start = time.perf_counter()
    model.learn(steps, progress_bar=True)
    train_seconds = time.perf_counter() - start
    seeds = eval_seeds(seed, episodes)
    result = {
        "env": env_id, "policy": "CnnPolicy", "steps": int(model.num_timesteps), "seed": seed,
        "train_seconds": round(train_seconds, 1), "fps": round(model.num_timesteps / train_seconds, 1),
        "eval_episodes": episodes, "queries_used": int(model.query_selector.used),
        "subgoals": [model.goal_space.describe(goal.key) for goal in model.subgoals],
    }
    for name, deterministic in (("stochastic", False), ("deterministic", True)):
        outcome = evaluate(model, lambda n: make_vec_env(env_id, n_envs=n, wrapper_class=wrap_env), seeds,
                           deterministic=deterministic)
        result[f"success_rate_{name}"] = float(np.mean(outcome["successes"]))
        result[f"mean_return_{name}"] = round(float(np.mean(outcome["returns"])), 3)
    result["load_average_start"], result["load_average_end"] = round(load_start, 2), round(os.getloadavg()[0], 2)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MiniGrid-DoorKey-5x5-v0")
    parser.add_argument("--steps", type=int, default=60_000, help="primitive env steps of training")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--episodes", type=int, default=50, help="fresh evaluation episodes")
    parser.add_argument("--out", default="benchmarks/results/cnn_policy")
    args = parser.parse_args()
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for seed in args.seeds:
        result = run(args.env, args.steps, seed, args.episodes)
        result["command"] = (f"python benchmarks/cnn_policy.py --env {args.env} --steps {args.steps} "
                             f"--seeds {' '.join(map(str, args.seeds))} --episodes {args.episodes}")
        path = out / f"{args.env}_s{seed}.json"
        path.write_text(json.dumps(result, indent=2) + "\n")
        print(json.dumps({k: v for k, v in result.items() if k != "subgoals"}))


if __name__ == "__main__":
    main()
