"""SB3's own algorithms as meta-controllers over a trained HhP model's skills (:class:`sb3_hhp.HierarchicalEnv`).

Trains HhP with its YAML entry on a MiniGrid task, freezes its sub-goal learners, then trains SB3's DQN and PPO on
the semi-MDP whose ``Discrete(K)`` actions are the model's K sub-goals, and evaluates each on fresh episodes
(seeds from 1,000 on, which no training run used): success is a positive return. Writes one JSON file::

    python benchmarks/hierarchical_env.py --env MiniGrid-DoorKey-5x5-v0 --hhp-steps 50000 --meta-steps 20000 \\
        --out benchmarks/results/hierarchical_env/doorkey5x5_s0.json
"""

import argparse
import json
import pathlib
import time
from typing import Any

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import torch as th
import yaml
from stable_baselines3 import DQN, PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_hhp import HhP, HierarchicalEnv
from sb3_hhp.goals import wrap_env
from sb3_hhp.zoo.config import ZOO_KEYS, default_config_path, select_entry


def entry(env_id: str) -> dict[str, Any]:
    """The HhP arguments of ``env_id``'s entry in the package's YAML, as ``sb3_hhp.train`` picks it (the keys RL Zoo
    reads itself left out)."""
    table = yaml.safe_load(default_config_path().read_text())
    return {key: value for key, value in table[select_entry(table, env_id)].items() if key not in ZOO_KEYS}


def success(model: Any, env: gym.Env, episodes: int, seed: int) -> dict[str, float]:
    returns = []
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        done, total = False, 0.0
        while not done:
            action, _ = model.predict(obs, deterministic=False)
            obs, reward, terminated, truncated, _ = env.step(int(action))
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
    return dict(success_rate=float(np.mean(np.array(returns) > 0)), mean_return=float(np.mean(returns)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MiniGrid-DoorKey-5x5-v0")
    parser.add_argument("--hhp-steps", type=int, default=50_000, help="HhP's primitive steps")
    parser.add_argument("--meta-steps", type=int, default=20_000, help="sub-goal choices each SB3 algorithm trains on")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="benchmarks/results/hierarchical_env/results.json")
    args = parser.parse_args()
    th.set_num_threads(1)
    start = time.time()
    model = HhP("MlpPolicy", make_vec_env(args.env, n_envs=1, wrapper_class=wrap_env, seed=args.seed), seed=args.seed,
                **entry(args.env))
    model.learn(args.hhp_steps)
    returns, _ = evaluate_policy(model, make_vec_env(args.env, n_envs=1, wrapper_class=wrap_env, seed=1_000),
                                 n_eval_episodes=args.episodes, deterministic=False, return_episode_rewards=True)
    result: dict[str, Any] = dict(
        env=args.env, seed=args.seed, hhp_steps=args.hhp_steps, meta_steps=args.meta_steps, episodes=args.episodes,
        subgoals=[model.goal_space.describe(goal.key) for goal in model.subgoals],
        labels=int(model.query_selector.used), hhp=dict(success_rate=float(np.mean(np.array(returns) > 0)),
                                                        mean_return=float(np.mean(returns)),
                                                        seconds=round(time.time() - start, 1)))
    print(json.dumps(result["hhp"]), len(result["subgoals"]), "sub-goals", flush=True)
    for name, algo, kwargs in (("DQN", DQN, dict(learning_starts=500, exploration_fraction=0.3)),
                               ("PPO", PPO, dict(n_steps=256, batch_size=64))):
        start = time.time()
        meta = algo("MlpPolicy", HierarchicalEnv.from_model(model, args.env), seed=args.seed, **kwargs)
        meta.learn(args.meta_steps)
        result[name] = dict(**success(meta, HierarchicalEnv.from_model(model, args.env), args.episodes, 1_000),
                            seconds=round(time.time() - start, 1))
        print(name, json.dumps(result[name]), flush=True)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
