"""One sub-goal learner's settings tried alone: can a DQN with them learn to walk to an object of a MiniGrid room?

HhP's sub-goal learners must walk across a room to reach sub-goals such as "carrying nothing, facing key". Here one
SB3 DQN does only that: from the env's own start, a reward of 1 (and the end of the try) when the agent, empty
handed, faces an object of the given kind, a try cut after ``--max-steps`` steps (a sub-goal's give-up). It reads
the egocentric canvas the learners read and has their network, learning rate, batch, update rate, n-step returns,
discount and target interval (``sb3_hhp.hierarchy.learners.DEFAULT_SUBPOLICY_KWARGS``, then ``--gamma`` and
``--kwargs``), its epsilon falling to 0.05 over ``--exploration-steps`` steps; it has none of the shared replay's
prioritization, Double DQN or lower bound, and acts every step where a learner acts for part of them. So it tells
which settings let the skill be learned at all within a number of steps, cheaply (a few minutes a run), not how a
learner fares inside HhP.

At every quarter of ``--steps`` the greedy policy and the policy with epsilon 0.05 are evaluated on fresh layouts
(seeds 50,000+): the fraction of tries that reach the object.

    python benchmarks/diagnostics/learner_proxy.py --env MiniGrid-DoorKey-16x16-v0 --gamma 0.99 \\
        --kwargs '{"target_update_interval": 1000}' --seed 0 --out benchmarks/results/diagnostics/proxy.json
"""

import argparse
import json
import pathlib
import sys
import time
from typing import Any

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import torch as th
from minigrid.core.world_object import Ball, Box, Door, Key
from stable_baselines3 import DQN

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2]))
from sb3_hhp.goals import register_minigrid_tasks, wrap_env  # noqa: E402
from sb3_hhp.hierarchy.learners import DEFAULT_SUBPOLICY_KWARGS  # noqa: E402

OBJECTS = {"key": Key, "door": Door, "ball": Ball, "box": Box}


class FaceObject(gym.Wrapper):
    """Reward 1 and the end of the try where the agent, carrying nothing, faces an object of class ``kind``; the try
    is cut after ``max_steps`` steps. ``info["is_success"]``: whether it was reached."""

    def __init__(self, env: gym.Env, kind: type, max_steps: int) -> None:
        super().__init__(env)
        self.kind, self.max_steps, self.steps = kind, int(max_steps), 0

    def reset(self, **kwargs: Any) -> Any:
        self.steps = 0
        return self.env.reset(**kwargs)

    def step(self, action: int) -> Any:
        obs, _, terminated, truncated, info = self.env.step(action)
        self.steps += 1
        base = self.env.unwrapped
        reached = base.carrying is None and isinstance(base.grid.get(*base.front_pos), self.kind)
        info["is_success"] = bool(reached)
        return obs, float(reached), bool(reached or terminated), bool(truncated or self.steps >= self.max_steps), info


def make_env(env_id: str, kind: str, max_steps: int) -> gym.Env:
    return FaceObject(wrap_env(gym.make(env_id)), OBJECTS[kind], max_steps)


def success_rate(model: DQN, env: gym.Env, episodes: int, epsilon: float, seed: int = 50_000) -> float:
    """The fraction of ``episodes`` fresh tries (seeds ``seed``, ``seed + 1``, ...) that reach the object."""
    rng, reached = np.random.default_rng(seed), 0
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        done, info = False, {}
        while not done:
            explore = rng.random() < epsilon
            action = int(rng.integers(env.action_space.n)) if explore else int(model.predict(obs, deterministic=True)[0])
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        reached += int(info["is_success"])
    return reached / episodes


def learner_settings(steps: int, exploration_steps: int, gamma: float, overrides: dict[str, Any]) -> dict[str, Any]:
    """SB3 DQN's keyword arguments with the sub-goal learners' defaults, ``gamma`` and ``overrides``."""
    defaults = {key: value for key, value in DEFAULT_SUBPOLICY_KWARGS.items() if key != "replay_buffer_kwargs"}
    settings = {**defaults, "gamma": gamma, "exploration_fraction": min(1.0, exploration_steps / steps),
                "exploration_final_eps": 0.05}
    settings.update(overrides)
    return settings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MiniGrid-DoorKey-16x16-v0")
    parser.add_argument("--object", default="key", choices=sorted(OBJECTS), help="what the agent must face")
    parser.add_argument("--steps", type=int, default=200_000)
    parser.add_argument("--max-steps", type=int, default=100, help="steps a try gets (a sub-goal's give-up)")
    parser.add_argument("--exploration-steps", type=int, default=20_000)
    parser.add_argument("--gamma", type=float, default=0.9)
    parser.add_argument("--kwargs", default="{}", help="SB3 DQN arguments over the learners' defaults (JSON)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-episodes", type=int, default=50)
    parser.add_argument("--out", default=None, help="write the settings and the curve as JSON here")
    args = parser.parse_args()
    register_minigrid_tasks()
    th.set_num_threads(1)
    settings = learner_settings(args.steps, args.exploration_steps, args.gamma, json.loads(args.kwargs))
    env, eval_env = (make_env(args.env, args.object, args.max_steps) for _ in range(2))
    model = DQN("MlpPolicy", env, seed=args.seed, **settings)
    begin, curve = time.perf_counter(), []
    for quarter in range(4):
        model.learn(args.steps // 4, reset_num_timesteps=False)
        curve.append(dict(steps=model.num_timesteps, greedy=success_rate(model, eval_env, args.eval_episodes, 0.0),
                          epsilon_0_05=success_rate(model, eval_env, args.eval_episodes, 0.05),
                          seconds=round(time.perf_counter() - begin, 1)))
        print(json.dumps(curve[-1]), flush=True)
    result = dict(env=args.env, object=args.object, seed=args.seed, max_steps=args.max_steps,
                  settings={key: (value if isinstance(value, (int, float, str)) else str(value)) for key, value in settings.items()},
                  curve=curve, command="benchmarks/diagnostics/learner_proxy.py " + " ".join(sys.argv[1:]))
    if args.out:
        pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
