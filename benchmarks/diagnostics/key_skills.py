"""Which skills has a run's sub-goal learners learned, from states set by hand: the key just picked up.

Loads the newest checkpoint of a run folder (``sb3_hhp.train --checkpoint-freq``) and, on fresh layouts of the env,
puts the agent on the key's cell carrying the key, facing each way in turn (the state right after a pick-up). From
there each named sub-goal's learner acts greedily for ``--steps`` primitive steps: reached or not, and in how many
steps. A learner that succeeds on its own choices (its success rate in the run) but not from here has learned
only the starts the meta-controller gave it; one that fails here and in the run has not learned the skill.

    python benchmarks/diagnostics/key_skills.py benchmarks/results/minigrid_tasks/logs/MiniGrid-KeyCorridorS4R3-v0__hhp__s0 \\
        --env MiniGrid-KeyCorridorS4R3-v0 --replay --out benchmarks/results/diagnostics/key_skills_kc_s0_800k.json

With ``--replay``, the checkpoint's shared replay is loaded too, and for every sub-goal it counts the stored
transitions that reach it (its learner's positive rewards, relabelled) and those its learner acted in: a learner
whose sub-goal is reached nowhere in the replay has nothing to learn from.

For comparison, the shortest number of steps from the same states to facing the locked door (a breadth-first search
over cells and headings: turns, moves, one more step to open a closed door) is reported too.
"""

import argparse
import json
import pathlib
import sys
from typing import Any, Optional

import gymnasium as gym
import numpy as np
import torch as th
from collections import deque

from minigrid.core.world_object import Door, Key

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2]))
from stable_baselines3.common.env_util import make_vec_env  # noqa: E402

from benchmarks.run import latest_checkpoint  # noqa: E402
from sb3_hhp import HhP  # noqa: E402
from sb3_hhp.goals import register_minigrid_tasks, wrap_env  # noqa: E402
from sb3_hhp.train import read_checkpoint  # noqa: E402


def newest_checkpoint(run: str) -> tuple[str, int, str]:
    """The model, step count and replay of a run's newest checkpoint (the runner's and the training command's readers)."""
    folder = latest_checkpoint(pathlib.Path(run))
    if folder is None:
        raise SystemExit(f"{run} holds no checkpoint.json (runs write them with --checkpoint-freq)")
    checkpoint = read_checkpoint(str(folder))
    return checkpoint["model"], checkpoint["timesteps"], checkpoint["replay"]


def model_file(model: str) -> str:
    """A diagnostic's model argument as a file: a ``.zip`` as given, else a run folder's newest checkpoint's model."""
    path = pathlib.Path(model)
    return str(path) if path.suffix == ".zip" else newest_checkpoint(str(path))[0]


def key_cell(base: Any) -> tuple[int, int]:
    """The cell of the key in an unwrapped MiniGrid env's grid."""
    return next((i, j) for i in range(base.grid.width) for j in range(base.grid.height)
                if isinstance(base.grid.get(i, j), Key))


def key_carried(env: gym.Env, seed: int, heading: int) -> np.ndarray:
    """A fresh layout with the agent on the key's cell, carrying it, facing ``heading``: its observation."""
    env.reset(seed=seed)
    base = env.unwrapped
    cell = key_cell(base)
    base.carrying = base.grid.get(*cell)
    base.grid.set(*cell, None)
    base.agent_pos, base.agent_dir = np.array(cell), heading
    return env.observation(base.gen_obs())


HEADINGS = [(1, 0), (0, 1), (-1, 0), (0, -1)]  # MiniGrid's agent_dir 0..3


def steps_to_locked_door(env: gym.Env) -> Optional[int]:
    """The fewest primitive steps from the agent's state to facing the locked door (None: no locked door or no way)."""
    base = env.unwrapped
    grid = base.grid
    locked = next(((i, j) for i in range(grid.width) for j in range(grid.height)
                   if isinstance(grid.get(i, j), Door) and grid.get(i, j).is_locked), None)
    if locked is None:
        return None
    start = (int(base.agent_pos[0]), int(base.agent_pos[1]), int(base.agent_dir))
    queue, seen = deque([(start, 0)]), {start}
    while queue:
        (x, y, heading), steps = queue.popleft()
        dx, dy = HEADINGS[heading]
        if (x + dx, y + dy) == locked:
            return steps
        moves = [((x, y, (heading + 1) % 4), 1), ((x, y, (heading - 1) % 4), 1)]
        cell = grid.get(x + dx, y + dy)
        if cell is None or (isinstance(cell, Door) and not cell.is_locked):
            moves.append(((x + dx, y + dy, heading), 1 if cell is None or cell.is_open else 2))
        for state, cost in moves:
            if state not in seen:
                seen.add(state)
                queue.append((state, steps + cost))
    return None


def steps_to_locked_door_from(env: gym.Env, seed: int, heading: int) -> Optional[int]:
    key_carried(env, seed, heading)
    return steps_to_locked_door(env)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", help="a run's log folder (its newest checkpoint is loaded), or a model .zip")
    parser.add_argument("--env", default="MiniGrid-KeyCorridorS4R3-v0")
    parser.add_argument("--layouts", type=int, default=40, help="fresh layouts (seeds 1000, 1001, ...)")
    parser.add_argument("--steps", type=int, default=50, help="primitive steps a learner gets (a sub-goal's give-up)")
    parser.add_argument("--replay", action="store_true", help="also count each sub-goal's positives in the replay")
    parser.add_argument("--out", default=None, help="write the result as JSON here")
    args = parser.parse_args()
    th.set_num_threads(1)
    register_minigrid_tasks()
    if args.run.endswith(".zip"):  # a saved model: no replay beside it
        if args.replay:
            raise SystemExit("--replay reads a checkpoint's replay: give the run's log folder, not a model .zip")
        path, replay_path = args.run, None
        model = HhP.load(path, device="cpu")
        timesteps = model.num_timesteps
    else:
        path, timesteps, replay_path = newest_checkpoint(args.run)
        model = HhP.load(path, device="cpu")
    learners, space = model.subpolicies, model.goal_space
    names = [space.describe(goal.key) for goal in model.subgoals]
    result = {"run": args.run, "checkpoint_steps": timesteps, "env": args.env, "layouts": args.layouts,
              "steps": args.steps, "subgoals": {}}
    if args.replay:
        model.set_env(make_vec_env(args.env, n_envs=model.subpolicies.n_envs, wrapper_class=wrap_env))
        model.load_replay_buffer(replay_path)
        replay = model.subpolicies.replay
        rows = replay.size()
        result["replay"] = {"transitions": rows * replay.n_envs, "subgoals": {}}
        for goal, name in enumerate(names):
            reached = replay.done(replay.key_ids[:rows], goal)
            acted = replay.acting[:rows] == goal
            counts = {"reached": int(reached.sum()), "acted": int(acted.sum()), "reached_acting": int((reached & acted).sum())}
            result["replay"]["subgoals"][name] = counts
            print(f"replay, {name}: reached in {counts['reached']} of {rows * replay.n_envs} stored transitions, "
                  f"its learner acted in {counts['acted']}, reaching it in {counts['reached_acting']}")
    env = wrap_env(gym.make(args.env))
    shortest = [steps_to_locked_door_from(env, 1000 + layout, layout % 4) for layout in range(args.layouts)]
    known = [value for value in shortest if value is not None]
    if known:
        result["shortest_to_locked_door"] = {"median": float(np.median(known)), "max": int(max(known))}
        print(f"shortest way to facing the locked door: median {np.median(known):.0f} steps, at most {max(known)}")
    for goal, name in enumerate(names):
        if not name.startswith("carrying key"):
            continue
        lengths = []
        for layout in range(args.layouts):
            obs = key_carried(env, 1000 + layout, layout % 4)
            for step in range(args.steps + 1):
                if space.key(obs) == model.subgoals[goal].key:
                    lengths.append(step)
                    break
                obs, _, terminated, truncated, _ = env.step(learners.act(np.array([goal]), obs[None], deterministic=True)[0])
                if terminated or truncated:
                    break
        result["subgoals"][name] = {"reached": len(lengths), "median_steps": float(np.median(lengths)) if lengths else None,
                                    "success_rate_in_run": learners.success_rate(goal)}
        print(f"{name}: reached from {len(lengths)} of {args.layouts} layouts"
              + (f", median {np.median(lengths):.0f} steps" if lengths else "")
              + f" (success in the run: {learners.success_rate(goal)})")
    if args.out:
        pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
