"""One subpolicy alone: learn "carrying nothing, facing the key" on MiniGrid DoorKey with eq. 5's reward,
one-step against n-step returns (the subpolicy learner: Double DQN + prioritized replay, the defaults of
``sb3_hhp.hierarchy.subpolicies``), then evaluate on fresh seeds (30_000 + i) beside a random policy.

    python benchmarks/subpolicy_nstep.py --n-steps 1 --seed 1 --out benchmarks/results/subpolicy/n1_s1.json
    python benchmarks/subpolicy_nstep.py --n-steps 8 --seed 1 --out benchmarks/results/subpolicy/n8_s1.json

A sub-goal episode ends when the key is faced (+1), or after 50 steps (-1), as in HhP.
"""

import argparse
import json
import pathlib
import sys
import time

import gymnasium as gym
import numpy as np
import torch as th

from sb3_hhp.dqn.dqn import DoubleDQN
from sb3_hhp.goals import wrap_env
from sb3_hhp.goals.minigrid import MiniGridGoalSpace
from sb3_hhp.hierarchy.subpolicies import default_subpolicy_kwargs
from sb3_hhp.preferences.rewards import pseudo_reward

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from doorkey import evaluate  # noqa: E402

FACING_KEY = (1, 5, 0)  # (carried: nothing, in front: key, state)


class ReachSubgoal(gym.Wrapper):
    """The primitive env as one sub-goal's task: eq. 5's reward, ended by reaching it or giving up."""

    def __init__(self, env: gym.Env, key, max_steps: int = 50) -> None:
        super().__init__(env)
        self.goal_space, self.goal_key, self.max_steps, self.t = MiniGridGoalSpace(), key, max_steps, 0

    def reset(self, **kwargs):
        self.t = 0
        return self.env.reset(**kwargs)

    def step(self, action):
        obs, _, terminated, truncated, info = self.env.step(action)
        self.t += 1
        reached = self.goal_space.key(obs) == self.goal_key
        give_up = self.t >= self.max_steps or terminated or truncated
        info["is_success"] = reached
        return obs, float(pseudo_reward(reached, reached or give_up)), reached or give_up, False, info


def success_rate(model, env: gym.Env, episodes: int, deterministic: bool) -> float:
    """Reached the sub-goal = a positive return (+1 on reaching it, -1 on giving up), on seeds 30_000 + i."""
    return evaluate(model, env, episodes, hierarchical=False, offset=30_000, deterministic=deterministic)["success_rate"]


class RandomPolicy:
    """Uniform random primitive actions, with ``predict`` as an SB3 model has."""

    def __init__(self, action_space: gym.spaces.Discrete, seed: int) -> None:
        self.action_space, self.rng = action_space, np.random.default_rng(seed)

    def predict(self, obs: np.ndarray, deterministic: bool = False) -> tuple[int, None]:
        return int(self.rng.integers(self.action_space.n)), None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MiniGrid-DoorKey-8x8-v0")
    parser.add_argument("--n-steps", type=int, default=8)
    parser.add_argument("--steps", type=int, default=15_000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    th.set_num_threads(1)
    env = ReachSubgoal(wrap_env(gym.make(args.env)), FACING_KEY)
    kwargs = default_subpolicy_kwargs(env.action_space)
    kwargs.update(n_steps=args.n_steps, exploration_fraction=5_000 / args.steps, train_freq=1)
    model = DoubleDQN("MlpPolicy", env, seed=args.seed, device="cpu", **kwargs)
    start = time.time()
    model.learn(args.steps)
    seconds = time.time() - start
    result = dict(
        env=args.env, subgoal="carrying nothing, facing key", n_steps=args.n_steps, train_steps=args.steps, seed=args.seed,
        eval_episodes=args.episodes, seconds=round(seconds, 1),
        greedy=success_rate(model, env, args.episodes, deterministic=True),
        epsilon_greedy=success_rate(model, env, args.episodes, deterministic=False),
        random=success_rate(RandomPolicy(env.action_space, args.seed), env, args.episodes, deterministic=False),
    )
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result))


if __name__ == "__main__":
    main()
