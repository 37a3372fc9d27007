"""Does the scripted Fetch oracle prefer, along real episodes, the state a person would?

Scripted controllers that read the privileged flat observation (:class:`~sb3_hhp.goals.fetch.FetchFlatObs`: the
gripper's place, the object's, the target) solve Pick & Place and Push: over the block with the fingers open, down,
closed, to the target (:func:`pick_and_place`); behind the block on the line to the target, down, pushing it along
that line and going back behind it where it slips aside (:func:`push`). Along each episode a controller solved, a
later state is further along the way than an earlier one, and a person shown the two as sub-goals prefers the later.
Every pair of states ``every`` steps apart or more of those episodes is asked of
:class:`~sb3_hhp.oracles.fetch.FetchScriptedOracle` as HhP asks it (:meth:`~sb3_hhp.goals.fetch.FetchGoalSpace.query_info`
of the episode's first state and the two states as the sub-goals), split by what happened between them:

- ``reach``: the block had not moved yet in either state (the gripper on its way to it): a person prefers the later,
  the gripper nearer the block. The goal space keys the block's cell and whether the gripper is at the block
  (within 5 cm): ``same_key`` counts the pairs it keys alike, ``gripper_arrives`` those where the gripper is at the
  block in the later state only (the oracle should prefer the later: ``gripper_arrives_later``); elsewhere the
  oracle, which reads the block's place and that flag, can only answer "equal";
- ``carry``: the block moved nearer the target between the two (by more than ``--moved`` metres): the oracle should
  prefer the later.

One JSON file::

    python benchmarks/diagnostics/fetch_oracle.py --seeds 0 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16 17 18 19
"""

import argparse
import json
import os
import pathlib

import gymnasium as gym
import numpy as np

from sb3_hhp.extras import register_fetch_envs
from sb3_hhp.goals import wrap_env
from sb3_hhp.goals.fetch import FetchGoalSpace
from sb3_hhp.oracles.fetch import FetchScriptedOracle
from sb3_hhp.preferences.types import Label, Query

#: how far (metres) the block may lie from where it started and still count as not moved yet
STILL = 0.005


def _parts(obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The gripper's place, the block's and the target of a flat Fetch observation of a task with an object."""
    return obs[0:3], obs[3:6], obs[-3:]


def _counts() -> dict[str, dict[str, int]]:
    """Empty counts of the oracle's answers by kind of pair (:func:`pair_readings`)."""
    return {"reach": {"later": 0, "equal": 0, "earlier": 0, "same_key": 0, "gripper_arrives": 0,
                      "gripper_arrives_later": 0},
            "carry": {"later": 0, "equal": 0, "earlier": 0}}


def _still(obs: np.ndarray, block_start: np.ndarray) -> bool:
    """Whether the block lies within :data:`STILL` of where it started."""
    return bool(np.linalg.norm(_parts(obs)[1] - block_start) <= STILL)


def _towards(grip: np.ndarray, aim: np.ndarray, fingers: float) -> np.ndarray:
    action = np.zeros(4, np.float32)
    action[:3] = np.clip(10.0 * (aim - grip), -1.0, 1.0)
    action[3] = fingers
    return action


def pick_and_place(obs: np.ndarray, stage: dict) -> np.ndarray:
    """The next action of a scripted pick and place; ``stage`` carries the controller's state between steps."""
    grip, block, target = _parts(obs)
    phase = stage.setdefault("phase", "over")
    if phase == "over":
        if np.linalg.norm(grip[:2] - block[:2]) < 0.01:
            stage["phase"] = phase = "down"
        else:
            return _towards(grip, block + [0.0, 0.0, 0.05], 1.0)
    if phase == "down":
        if abs(grip[2] - block[2]) < 0.005:
            stage["phase"], stage["closing"] = "close", 0
        else:
            return _towards(grip, block, 1.0)
    if stage["phase"] == "close" and stage["closing"] < 4:
        stage["closing"] += 1
        return _towards(grip, block, -1.0)
    stage["phase"] = "carry"
    return _towards(grip, target, -1.0)


def push(obs: np.ndarray, stage: dict) -> np.ndarray:
    """The next action of a scripted push (the fingers are blocked closed in FetchPush)."""
    grip, block, target = _parts(obs)
    way = target[:2] - block[:2]
    left = float(np.linalg.norm(way))
    unit = way / max(left, 1e-6)
    behind = np.r_[block[:2] - 0.06 * unit, block[2]]
    phase = stage.setdefault("phase", "over")
    if phase == "push":
        offset = grip[:2] - block[:2]
        aside, along = abs(offset[0] * unit[1] - offset[1] * unit[0]), float(offset @ unit)
        if aside > 0.035 or along > -0.01:  # slipped aside or past it: up, and behind it again
            stage["phase"] = "over"
            return _towards(grip, np.r_[grip[:2], block[2] + 0.08], -1.0)
        return _towards(grip, np.r_[block[:2] + min(0.03, left) * unit, block[2]] if left > 0.015 else grip, -1.0)
    if phase == "over":
        if np.linalg.norm(grip[:2] - behind[:2]) < 0.02:
            stage["phase"] = phase = "down"
        else:
            return _towards(grip, np.r_[behind[:2], block[2] + 0.08], -1.0)
    if abs(grip[2] - block[2]) < 0.01:
        stage["phase"] = "push"
    return _towards(grip, behind, -1.0)


CONTROLLERS = {"FetchPickAndPlace-v4": pick_and_place, "FetchPush-v4": push}


def episode(env_id: str, seed: int) -> tuple[list[np.ndarray], bool]:
    """The flat observations of one episode of the task's controller (the reset's first) and whether it was solved."""
    env = wrap_env(gym.make(env_id))
    obs, _ = env.reset(seed=seed)
    states, stage, info, done = [obs], {}, {}, False
    while not done:
        obs, _, terminated, truncated, info = env.step(CONTROLLERS[env_id](obs, stage))
        states.append(obs)
        done = terminated or truncated
    env.close()
    return states, bool(info.get("is_success", False))


def pair_readings(states: list[np.ndarray], every: int, moved: float, space: FetchGoalSpace,
                  oracle: FetchScriptedOracle) -> dict[str, dict[str, int]]:
    """The oracle's answers to every pair (earlier, later) of ``states`` (one solved episode) ``every`` steps apart or
    more, as counts of "later" (the later state preferred), "equal" and "earlier", for the ``reach`` pairs (the block
    not moved yet in either state: within :data:`STILL` of its start) and the ``carry`` pairs (the block at least
    ``moved`` metres nearer the target in the later state); ``same_key``: how many ``reach`` pairs the goal space keys
    alike."""
    start = states[0]
    block_start = _parts(start)[1]
    counts = _counts()
    for i in range(len(states)):
        for j in range(i + every, len(states)):
            first, second = states[i], states[j]
            _, block1, target = _parts(first)
            block2 = _parts(second)[1]
            if _still(first, block_start) and _still(second, block_start):
                kind = "reach"
            elif np.linalg.norm(block1 - target) - np.linalg.norm(block2 - target) > moved:
                kind = "carry"
            else:
                continue
            query = Query(state=start, goal1=0, goal2=1, goal1_obs=first, goal2_obs=second,
                          info=space.query_info(start, first, second))
            label = oracle.answer(query)
            counts[kind][{Label.SECOND: "later", Label.EQUAL: "equal", Label.FIRST: "earlier"}[label]] += 1
            if kind == "reach":
                counts["reach"]["same_key"] += int(space.key(first) == space.key(second))
                if space.gripper_at_object(second) and not space.gripper_at_object(first):
                    counts["reach"]["gripper_arrives"] += 1
                    counts["reach"]["gripper_arrives_later"] += int(label == Label.SECOND)
    return counts


def measure(env_id: str, seeds: list[int], every: int, moved: float) -> dict:
    space, oracle = FetchGoalSpace(), FetchScriptedOracle()
    space.bind(gym.make(env_id))  # as HhP binds it: keys with the gripper's flag
    solved, reach_steps, lengths = [], [], []
    totals = _counts()
    for seed in seeds:
        states, success = episode(env_id, seed)
        if not success:
            continue
        solved.append(seed)
        still = [_still(obs, _parts(states[0])[1]) for obs in states]
        reach_steps.append(int(still.index(False)) if False in still else len(still))
        lengths.append(len(states) - 1)
        for kind, counts in pair_readings(states, every, moved, space, oracle).items():
            for name, count in counts.items():
                totals[kind][name] += count
    shares = {kind: {name: round(count / max(1, sum(counts[k] for k in ("later", "equal", "earlier"))), 4)
                     for name, count in counts.items()} for kind, counts in totals.items()}
    return {"episodes": len(seeds), "solved_seeds": solved, "steps_before_the_block_moves": reach_steps,
            "episode_steps": lengths, "pairs": totals, "shares": shares}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=list(CONTROLLERS), choices=list(CONTROLLERS))
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(20)))
    parser.add_argument("--every", type=int, default=3, help="pairs of states at least this many steps apart")
    parser.add_argument("--moved", type=float, default=0.01,
                        help="metres the block must have come nearer the target for a carry pair")
    parser.add_argument("--out", default="benchmarks/results/fetch_oracle.json")
    args = parser.parse_args()
    register_fetch_envs()
    results = {}
    for env_id in args.tasks:
        results[env_id] = measure(env_id, args.seeds, args.every, args.moved)
        print(env_id, json.dumps(results[env_id]["shares"]), flush=True)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "seeds": args.seeds, "every": args.every, "moved": args.moved, "still": STILL, "tasks": results,
        "load_average": round(os.getloadavg()[0], 2),
        "command": "python benchmarks/diagnostics/fetch_oracle.py " + " ".join(
            ["--seeds", *map(str, args.seeds), "--every", str(args.every), "--moved", str(args.moved)]),
    }, indent=2))


if __name__ == "__main__":
    main()
