"""MiniGrid DoorKey learning benchmark: HhP (scripted oracle) beside flat SB3 DQN and PPO, same step budget.

Each call trains one algorithm for one seed, then evaluates its deterministic policy on fresh
evaluation seeds (10_000 + i, never a training seed) and writes a JSON result:

    python benchmarks/doorkey.py --algo hhp --seed 0 --steps 500000 --out benchmarks/results/hhp_s0.json
    python benchmarks/doorkey.py --algo dqn --seed 0 --steps 500000 --out benchmarks/results/dqn_s0.json
    python benchmarks/doorkey.py --algo ppo --seed 0 --steps 500000 --out benchmarks/results/ppo_s0.json

HhP sees :class:`~sb3_hhp.goals.MiniGridEgocentricObs`; the flat baselines see the fully observed grid
(MiniGrid's ``FullyObsWrapper`` + ``ImgObsWrapper``) through an MLP. ``benchmarks/report.py`` gathers the
results into a table and a plot.
"""

import argparse
import json
import pathlib
import time

import gymnasium as gym
import numpy as np
import torch as th
from minigrid.wrappers import FullyObsWrapper, ImgObsWrapper
from stable_baselines3 import DQN, PPO
from stable_baselines3.common.monitor import Monitor

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env

EVAL_SEED_OFFSET = 10_000


def flat_env(env_id: str) -> gym.Env:
    return Monitor(ImgObsWrapper(FullyObsWrapper(gym.make(env_id))))


def evaluate(model, env: gym.Env, episodes: int, hierarchical: bool) -> dict:
    """Deterministic policy on seeds EVAL_SEED_OFFSET + i: success rate and mean return."""
    returns, successes = [], []
    for episode in range(episodes):
        obs, _ = env.reset(seed=EVAL_SEED_OFFSET + episode)
        state, start, done, total = None, np.ones(1, dtype=bool), False, 0.0
        while not done:
            if hierarchical:
                action, state = model.predict(obs, state=state, episode_start=start, deterministic=True)
            else:
                action, _ = model.predict(obs, deterministic=True)
            obs, reward, terminated, truncated, _ = env.step(action)
            start = np.zeros(1, dtype=bool)
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
        successes.append(total > 0)
    return dict(success_rate=float(np.mean(successes)), mean_return=float(np.mean(returns)), eval_episodes=episodes)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", choices=["hhp", "dqn", "ppo"], required=True)
    parser.add_argument("--env", default="MiniGrid-DoorKey-8x8-v0")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=500_000)
    parser.add_argument("--query-budget", type=int, default=100)
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    th.set_num_threads(1)

    start = time.perf_counter()
    if args.algo == "hhp":
        model = HhP("MlpPolicy", gym.make(args.env), oracle="scripted", query_budget=args.query_budget, seed=args.seed)
        eval_env = wrap_env(gym.make(args.env))
    elif args.algo == "dqn":
        model = DQN("MlpPolicy", flat_env(args.env), seed=args.seed)
        eval_env = flat_env(args.env)
    else:
        model = PPO("MlpPolicy", flat_env(args.env), seed=args.seed)
        eval_env = flat_env(args.env)
    model.learn(args.steps)
    seconds = time.perf_counter() - start
    result = dict(algo=args.algo, env=args.env, seed=args.seed, total_timesteps=int(model.num_timesteps),
                  train_seconds=round(seconds, 1), fps=round(model.num_timesteps / seconds, 1))
    result.update(evaluate(model, eval_env, args.eval_episodes, hierarchical=args.algo == "hhp"))
    if args.algo == "hhp":
        result.update(queries_used=model.query_selector.used, query_budget=model.query_budget,
                      num_subgoals=len(model.subgoals),
                      subgoals=[model.goal_space.describe(goal.key) for goal in model.subgoals])
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
