"""Does a Fetch model's gripper reach the object and move it? Fresh episodes of a saved HhP model on a task with an
object (Push, Pick & Place, Slide), and what its sub-goals ask.

Before a Fetch task with an object is solved at all, its learning shows in two earlier things: the gripper coming to
the object (within 5 cm of it, the goal space's flag) and the object moving (more than ``--moved`` metres from where
it started). For each of ``--episodes`` fresh episodes (seeds ``--seed``, ``--seed + 1``, ...) of the model's own
policy (its meta-controller and learners, stochastic unless ``--deterministic``) this counts whether either happened,
and the env's ``is_success`` at the end; it lists the model's sub-goals by name (with or without the gripper at the
object) and each one's success rate as its learner pursued it in training. One JSON file::

    python benchmarks/diagnostics/fetch_contact.py --model RUN/model.zip --env FetchPush-v4 --out contact.json
"""

import argparse
import json
import pathlib
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th

from sb3_hhp import HhP
from sb3_hhp.extras import register_fetch_envs
from sb3_hhp.goals import wrap_env
from sb3_hhp.goals.fetch import FetchGoalSpace


def contact(model: HhP, env_id: str, seeds: list[int], deterministic: bool = False, moved: float = 0.01) -> dict[str, Any]:
    """Share of the episodes (one per seed) where the gripper came within the goal space's distance of the object,
    where the object moved more than ``moved`` metres, and where the task was solved at the end."""
    env = wrap_env(gym.make(env_id))
    space = FetchGoalSpace()  # its rule for "the gripper at the object", whatever keys the model's goal space has
    space.bind(env)
    reached, shifted, solved = [], [], []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        start, state, first, done, info = obs[3:6].copy(), None, True, False, {}
        at, away = False, False
        while not done:
            action, state = model.predict(obs, state=state, episode_start=np.array([first]), deterministic=deterministic)
            obs, _, terminated, truncated, info = env.step(action)
            first, done = False, terminated or truncated
            at |= bool(space.gripper_at_object(obs))
            away |= bool(np.linalg.norm(obs[3:6] - start) > moved)
        reached.append(at)
        shifted.append(away)
        solved.append(bool(info.get("is_success", False)))
    env.close()
    return {"episodes": len(seeds), "gripper_at_object": float(np.mean(reached)), "object_moved": float(np.mean(shifted)),
            "success": float(np.mean(solved))}


def subgoals(model: HhP) -> list[dict[str, Any]]:
    """Each sub-goal's name and its learner's success rate when pursued in training (None: never pursued)."""
    rates = [model.subpolicies.success_rate(goal) for goal in range(len(model.subgoals))]
    return [{"name": model.goal_space.describe(goal.key), "success_rate": None if rate is None else round(rate, 3)}
            for goal, rate in zip(model.subgoals, rates)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True, help="a saved HhP model (a benchmark run's model.zip)")
    parser.add_argument("--env", default="FetchPush-v4")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=10_000, help="the first episode's seed (the evaluation's)")
    parser.add_argument("--moved", type=float, default=0.01, help="metres from its start the object must have moved")
    parser.add_argument("--deterministic", action="store_true")
    parser.add_argument("--out", default=None, help="the JSON file (default: print only)")
    args = parser.parse_args()
    th.set_num_threads(1)
    register_fetch_envs()
    model = HhP.load(args.model, env=gym.make(args.env), device="cpu")
    model.oracle = None  # no questions: the model is only played
    seeds = list(range(args.seed, args.seed + args.episodes))
    result = {"model": args.model, "env": args.env, "num_timesteps": model.num_timesteps,
              "deterministic": args.deterministic, **contact(model, args.env, seeds, args.deterministic, args.moved),
              "subgoals": subgoals(model)}
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
