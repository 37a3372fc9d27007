"""Does the scripted MiniGrid oracle plan the paper's four tasks within its time per question?

For each task and seed, the states of one episode of uniformly random actions (the first state and every
``--every``-th after it) are given to :meth:`MiniGridScriptedOracle.plan` with its default bound (1 s per
question): the share planned, which search found the plan (a shortest one, or the weighted fallback), the plan's
length and the seconds taken. One JSON file under ``--out``.

    python benchmarks/diagnostics/oracle_planning.py --seeds 0 1 2 3 4 5 6 7 8 9
"""

import argparse
import json
import os
import pathlib
import time

import gymnasium as gym
import numpy as np

from sb3_hhp.goals import wrap_env
from sb3_hhp.goals.minigrid import MiniGridGoalSpace, register_minigrid_tasks
from sb3_hhp.oracles.scripted import MiniGridScriptedOracle

TASKS = ("MiniGrid-DoorKey-16x16-v0", "MiniGrid-KeyCorridorS4R3-v0", "MiniGrid-ObstructedMaze-1Q-v1",
         "MiniGrid-MultiRoom-N12-S10-v0")
#: the tasks whose goal space tells colours apart (sb3_hhp/hyperparams/hhp.yml: goal_space minigrid_color)
COLORED = ("MiniGrid-ObstructedMaze-1Q-v1",)


def states(env_id: str, seed: int, every: int) -> list[dict]:
    """The privileged facts of every ``every``-th state of one random episode (the first included)."""
    goal_space = MiniGridGoalSpace(use_color=env_id in COLORED)
    env = wrap_env(gym.make(env_id))
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    facts, step, done = [], 0, False
    while not done:
        if step % every == 0:
            facts.append(goal_space.privileged(env))
        _, _, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
        done, step = terminated or truncated, step + 1
    return facts


def measure(env_id: str, seeds: list[int], every: int) -> dict:
    oracle = MiniGridScriptedOracle(use_color=env_id in COLORED)
    seconds, lengths, weights, unplanned = [], [], [], []
    for seed in seeds:
        for index, state in enumerate(states(env_id, seed, every)):
            start = time.perf_counter()
            keys = oracle.plan(state)
            seconds.append(time.perf_counter() - start)
            if keys is None:
                unplanned.append([seed, index * every])
            else:
                lengths.append(len(keys))
                weights.append(oracle.last_plan_weight)
    seconds_arr = np.asarray(seconds)
    return {
        "states": len(seconds), "planned": len(lengths), "planned_share": round(len(lengths) / len(seconds), 4),
        "shortest": int(sum(weight == 1.0 for weight in weights)),
        "fallback": int(sum(weight != 1.0 for weight in weights)),
        "unplanned_seed_step": unplanned,
        "plan_length_median": float(np.median(lengths)) if lengths else None,
        "seconds_median": round(float(np.median(seconds_arr)), 4),
        "seconds_p95": round(float(np.quantile(seconds_arr, 0.95)), 4),
        "seconds_max": round(float(seconds_arr.max()), 4),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=list(TASKS))
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    parser.add_argument("--every", type=int, default=25, help="a state every this many random steps")
    parser.add_argument("--out", default="benchmarks/results/oracle_planning.json")
    args = parser.parse_args()
    register_minigrid_tasks()
    load_start = os.getloadavg()[0]
    results = {}
    for env_id in args.tasks:
        results[env_id] = measure(env_id, args.seeds, args.every)
        print(env_id, json.dumps(results[env_id]), flush=True)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "seeds": args.seeds, "every": args.every, "max_seconds": MiniGridScriptedOracle().max_seconds,
        "fallback_weight": MiniGridScriptedOracle().fallback_weight, "tasks": results,
        "load_average_start": round(load_start, 2), "load_average_end": round(os.getloadavg()[0], 2),
        "command": "python benchmarks/diagnostics/oracle_planning.py " + " ".join(
            ["--seeds", *map(str, args.seeds), "--every", str(args.every)]),
    }, indent=2))


if __name__ == "__main__":
    main()
