"""Any SB3 algorithm as the meta-controller over HhP's skills, through :class:`sb3_hhp.HierarchicalEnv`.

Trains HhP briefly, then hands its sub-goals and their (frozen) learners to SB3's DQN: each of DQN's actions runs one
sub-goal until it is reached, gives up or the episode ends, and pays the extrinsic reward of those primitive steps.
Also shows SB3's own loop over ``model.get_env()``, whose actions are the primitive ones ``predict`` returns.

    python examples/sb3_meta_controller.py                      # Empty-Random-5x5, about a minute
    python examples/sb3_meta_controller.py --algo PPO --meta-steps 5000
"""

import argparse

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import torch as th
from stable_baselines3 import DQN, PPO
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_hhp import HhP, HierarchicalEnv
from small_settings import SMALL_ENV, SMALL_SETTINGS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default=SMALL_ENV)
    parser.add_argument("--steps", type=int, default=8_000, help="HhP's primitive steps")
    parser.add_argument("--algo", choices=("DQN", "PPO"), default="DQN")
    parser.add_argument("--meta-steps", type=int, default=3_000, help="sub-goal choices the SB3 algorithm trains on")
    args = parser.parse_args()
    th.set_num_threads(1)

    model = HhP("MlpPolicy", gym.make(args.env), query_budget=20, seed=0, **SMALL_SETTINGS)
    model.learn(args.steps)
    print("sub-goals:", [model.goal_space.describe(goal.key) for goal in model.subgoals])

    # SB3's README loop on the model's env: primitive actions, one new sub-goal choice per call without state
    vec_env = model.get_env()
    obs = vec_env.reset()
    for _ in range(200):
        action, _ = model.predict(obs, deterministic=False)
        obs, reward, done, info = vec_env.step(action)
    mean, std = evaluate_policy(model, model.get_env(), n_eval_episodes=20, deterministic=False)
    print(f"HhP on its own env: mean return {mean:.3f} +- {std:.3f}")

    env = HierarchicalEnv.from_model(model, args.env)  # Discrete(K): K sub-goals, the learners frozen
    algo = {"DQN": (DQN, dict(learning_starts=200)), "PPO": (PPO, dict(n_steps=256, batch_size=64))}[args.algo]
    meta = algo[0]("MlpPolicy", env, seed=0, **algo[1]).learn(args.meta_steps)
    returns = []
    for seed in range(1_000, 1_020):
        obs, _ = env.reset(seed=seed)
        done, total = False, 0.0
        while not done:
            choice, _ = meta.predict(obs, deterministic=False)
            obs, reward, terminated, truncated, info = env.step(int(choice))
            total, done = total + reward, terminated or truncated
        returns.append(total)
    print(f"{args.algo} over HhP's skills: success {np.mean(np.array(returns) > 0):.2f}, mean return {np.mean(returns):.3f}")


if __name__ == "__main__":
    main()
