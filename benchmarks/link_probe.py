"""Each link of the DoorKey plan on its own: a saved HhP model's subpolicy for that link, started in the
situation where the plan needs it, on fresh layouts (seeds 30_000 + i), greedy and epsilon-greedy:

    python benchmarks/link_probe.py PATH.zip --env MiniGrid-DoorKey-8x8-v0 --out result.json

| link | start | subpolicy |
| --- | --- | --- |
| key | a random free cell of the first room, random direction, carrying nothing | "carrying nothing, facing key" |
| door | the same, carrying the key (taken off the floor) | "carrying key, facing locked door" |
| open | left of the locked door, facing it, with the key | "carrying key, facing open door" |
| goal | left of the opened door, facing it, with the key | "task solved" |

A try counts when the sub-goal is reached within ``max_subgoal_steps`` primitive steps. It tells the meta-controller's
choices apart from the subpolicies' skill: HhP's own sub-goal rates mix both.
"""

import argparse
import json
import pathlib

import gymnasium as gym
import numpy as np
import torch as th
from minigrid.core.world_object import Door, Key

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env

LINKS = {"key": "carrying nothing, facing key", "door": "carrying key, facing locked door",
         "open": "carrying key, facing open door", "goal": "task solved"}


def start(env: gym.Env, seed: int, link: str) -> np.ndarray:
    """Reset on ``seed`` and set up the situation where the plan needs ``link``."""
    env.reset(seed=seed)
    base = env.unwrapped
    rng = np.random.default_rng(seed)
    cells = [(x, y, base.grid.get(x, y)) for x in range(base.width) for y in range(base.height)]
    door = next((x, y, cell) for x, y, cell in cells if isinstance(cell, Door))
    if link != "key":
        x, y, key = next((x, y, cell) for x, y, cell in cells if isinstance(cell, Key))
        base.grid.set(x, y, None)
        base.carrying = key
    if link in ("open", "goal"):
        if link == "goal":
            door[2].is_locked, door[2].is_open = False, True
        base.agent_pos, base.agent_dir = (door[0] - 1, door[1]), 0
    else:
        while True:
            x, y = int(rng.integers(1, door[0])), int(rng.integers(1, base.height - 1))
            if base.grid.get(x, y) is None:
                base.agent_pos, base.agent_dir = (x, y), int(rng.integers(4))
                break
    return env.observation(None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("path")
    parser.add_argument("--env", default="MiniGrid-DoorKey-8x8-v0")
    parser.add_argument("--layouts", type=int, default=30)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    th.set_num_threads(1)
    env = wrap_env(gym.make(args.env))
    model = HhP.load(args.path, env=env, device="cpu")
    space = model.goal_space
    names = [space.describe(goal.key) for goal in model.subgoals]
    result: dict = dict(path=args.path, env=args.env, total_timesteps=int(model.num_timesteps), layouts=args.layouts,
                        links={})
    for link, name in LINKS.items():
        if name not in names:
            result["links"][link] = None
            continue
        goal_id = names.index(name)
        learners, goal_key = model.subpolicies, model.subgoals[goal_id].key
        reached = {}
        for deterministic in (True, False):
            count = 0
            for layout in range(args.layouts):
                obs = start(env, 30_000 + layout, link)
                for _ in range(model.max_subgoal_steps):
                    obs, reward, terminated, truncated, _ = env.step(int(learners.act([goal_id], obs[None], deterministic=deterministic)[0]))
                    if space.achieved(space.terminal_key(obs, float(reward), terminated), goal_key):
                        count += 1
                        break
                    if terminated or truncated:
                        break
            reached["greedy" if deterministic else "epsilon_greedy"] = count / args.layouts
        result["links"][link] = dict(subgoal=name, own_steps=int(learners.own_steps[goal_id]), **reached)
        print(link, json.dumps(result["links"][link]), flush=True)
    if args.out:
        pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.out).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
