"""The paper's ablations side by side (Table 1), on a short run.

- ``HhP``: preferences and curiosity, curiosity-driven sub-goal discovery (CSD);
- ``Cur``: no preferences (``query_budget=0``: no label), the meta-controller's reward is R_e alone;
- ``Pref``: no curiosity (``use_curiosity=False``): no RND, no intrinsic reward, alpha = 0;
- ``random``: sub-goals discovered at random (``discovery_kwargs=dict(strategy="random")``) instead of by CSD.

Each variant trains with the same seed and settings, then is evaluated on the same episodes. Short
runs only show that the switches work; compare learning curves on long runs (see benchmarks/).

    python examples/ablations.py                     # Empty-Random-5x5, 6,000 steps a variant, 4 envs
    python examples/ablations.py --env MiniGrid-DoorKey-8x8-v0 --steps 300000 --n-envs 8 --variants HhP Cur
"""

import argparse
import time
from typing import Any

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env
from small_settings import SMALL_ENV, SMALL_SETTINGS

VARIANTS: dict[str, dict[str, Any]] = {
    "HhP": {},
    "Cur": dict(query_budget=0),
    "Pref": dict(use_curiosity=False),
    "random": dict(discovery_kwargs=dict(strategy="random")),
}


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default=SMALL_ENV, help="a MiniGrid env id")
    parser.add_argument("--steps", type=int, default=6_000, help="training length of each variant, in primitive env steps")
    parser.add_argument("--budget", type=int, default=20, help="questions per run (variants with preferences)")
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    parser.add_argument("--eval-episodes", type=int, default=20, help="episodes of each evaluation (stochastic policy)")
    parser.add_argument("--n-envs", type=int, default=4, help="envs stepped together")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    th.set_num_threads(args.threads)
    print(f"{'variant':8s} {'success':>8s} {'return':>8s} {'sub-goals':>9s} {'queries':>8s} {'labels':>7s} {'seconds':>8s}")
    for name in args.variants:
        start = time.perf_counter()
        model = HhP(
            "MlpPolicy",
            make_vec_env(args.env, n_envs=args.n_envs, wrapper_class=wrap_env, seed=args.seed),
            oracle="scripted",
            query_budget=args.budget,
            **SMALL_SETTINGS,
            seed=args.seed,
            **VARIANTS[name],
        )
        model.learn(args.steps)
        rewards, _ = evaluate_policy(model, wrap_env(gym.make(args.env)), n_eval_episodes=args.eval_episodes,
                                     deterministic=False, return_episode_rewards=True, warn=False)
        seconds = time.perf_counter() - start
        print(f"{name:8s} {np.mean(np.asarray(rewards) > 0):8.2f} {np.mean(rewards):8.3f} {len(model.subgoals):9d} "
              f"{model.query_selector.used:8d} {len(model.predictor):7d} {seconds:8.1f}")


if __name__ == "__main__":
    main()
