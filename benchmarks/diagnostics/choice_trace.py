"""What a trained HhP agent does, choice by choice: the sub-goals its meta-controller picks and which are reached.

Loads a model (a ``.zip``, or a run folder's newest checkpoint, ``sb3_hhp.train --checkpoint-freq``) and plays
fresh episodes with ``predict``, as ``evaluate_policy`` does. Every choice is recorded with the sub-goal key of the
state it was made in, whether it was reached, and in how many primitive steps. Printed: the first episodes as
chains of choices, then for every (state, chosen sub-goal) pair how often it was chosen and reached. A chain that
loops (picking the key up, dropping it) or a choice that never succeeds shows where a run is stuck. On MiniGrid, each
walk also records how far (in cells, the larger of the two axes) the nearest object the sub-goal faces was at its start
(e.g. the locked door, for "carrying key, facing locked door"), and whether that object was within the cells the
sub-goal learners read (``subgoal_learner_kwargs`` ``view``; every cell without one); printed per sub-goal: chosen and
reached with the object in view and out of it. Each walk also counts its idle steps (actions that left the env as it
was: a turn back and forth is not one, picking up nothing, toggling a wall or ``done`` are) and the acting learner's
action gap at each step (its best Q-value minus its second best): a greedy learner whose gap is smaller than its
values' error picks its actions by that error. Printed last: the acting learner's mean best Q-value over all steps, and
the share of steps where it was above 1, more than any return of eq. 5 (with ``alpha`` 0) can be.

    python benchmarks/diagnostics/choice_trace.py logs/hhp/MiniGrid-KeyCorridorS4R3-v0_1 \\
        --env MiniGrid-KeyCorridorS4R3-v0 --episodes 20 --out trace.json
"""

import argparse
import json
import pathlib
import sys
from collections import Counter
from typing import Any, Optional

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2]))
from benchmarks.diagnostics.key_skills import model_file  # noqa: E402
from sb3_hhp import HhP  # noqa: E402
from sb3_hhp.goals import SUCCESS_KEY, MiniGridGoalSpace, register_minigrid_tasks, wrap_env  # noqa: E402
from sb3_hhp.goals.minigrid import INTERACTIVE  # noqa: E402
from sb3_hhp.hierarchy.options import option_terminal  # noqa: E402

import gymnasium as gym  # noqa: E402


def env_state(env: gym.Env) -> bytes:
    """The whole state of a MiniGrid env (the grid, the agent's cell, direction and what it carries) as bytes: under a
    deterministic policy a sub-goal whose walk comes back to a state it was in goes round that cycle until it gives up."""
    grid = env.unwrapped
    carrying = grid.carrying.encode() if grid.carrying is not None else ()
    return grid.grid.encode().tobytes() + bytes([*grid.agent_pos, grid.agent_dir, *carrying])


def target_distance(env: gym.Env, goal_space: Any, goal_key: Any) -> Optional[int]:
    """How many cells (the larger of the two axes) lie between the agent and the nearest object a MiniGrid sub-goal
    ``goal_key`` faces (its kind and state, and colour in a key that has it); None for "task solved", a sub-goal that
    faces nothing to interact with, another goal space, or no such object in the grid."""
    if not isinstance(goal_space, MiniGridGoalSpace) or not isinstance(goal_key, tuple) or goal_key == SUCCESS_KEY:
        return None
    if goal_space.use_color:  # a colour relation (use_color "relative") names no colour
        front, colour, state = goal_key[2], (None if goal_space.relative_color else goal_key[3]), goal_key[4]
    else:
        front, colour, state = goal_key[1], None, goal_key[2]
    if front not in INTERACTIVE:
        return None
    cells = env.unwrapped.grid.encode()  # (width, height, 3): kind, colour, state
    match = (cells[..., 0] == front) & (cells[..., 2] == state)
    if colour is not None:
        match &= cells[..., 1] == colour
    return nearest_distance(env, match)


def nearest_distance(env: gym.Env, match: np.ndarray) -> Optional[int]:
    """Cells (the larger of the two axes) from the agent of a MiniGrid env to the nearest cell where ``match``
    (``(width, height)``, boolean) holds; None where it holds nowhere."""
    if not match.any():
        return None
    xs, ys = np.nonzero(match)
    agent_x, agent_y = env.unwrapped.agent_pos
    return int(np.maximum(np.abs(xs - agent_x), np.abs(ys - agent_y)).min())


def trace_episode(model: HhP, env: gym.Env, seed: int, deterministic: bool) -> dict:
    """One episode: its choices ``(state key, chosen sub-goal, reached, steps, cycled, distance, idle, gap, best,
    above_1)`` and whether the task was solved; ``cycled``: the env came back to a state it was in since the choice,
    before the sub-goal was reached; ``distance``: :func:`target_distance` at the choice; ``idle``: steps whose action
    left the env as it was; ``gap``: the mean over the walk's steps of the acting learner's best Q-value minus its
    second best; ``best``: the mean of that best Q-value; ``above_1``: the steps where it was above 1, the most any
    return of eq. 5 with ``alpha`` 0 can be."""
    obs, _ = env.reset(seed=seed)
    describe = model.goal_space.describe
    state, start, choices, current, seen = None, True, [], None, set()
    while True:
        action, state = model.predict(obs, state=state, episode_start=np.array([start]), deterministic=deterministic)
        goal, steps = int(state[0][0]), int(state[1][0])
        if steps == 1:  # a new choice was made in this state
            current = dict(state=describe(model.goal_space.key(obs)), goal=describe(model.subgoals[goal].key),
                           reached=False, steps=0, cycled=False,
                           distance=target_distance(env, model.goal_space, model.subgoals[goal].key), idle=0, gap=0.0,
                           best=0.0, above_1=0)
            choices.append(current)
            seen = set()
        here = env_state(env)
        current["cycled"] = current["cycled"] or (here in seen and not current["reached"])
        seen.add(here)
        best, gap = q_readings(model, goal, obs)
        current["gap"] += gap
        current["best"] += best
        current["above_1"] += int(best > 1.0)
        obs, reward, terminated, truncated, _ = env.step(action)
        start = False
        current["steps"] += 1
        current["idle"] += int(env_state(env) == here)
        # the key training reaches sub-goals by: "task solved" where the episode ends with a reward
        key = model.goal_space.terminal_key(obs, float(reward), bool(terminated))
        achieved, _ = option_terminal(model.goal_space, key, model.subgoals[goal].key, steps, model.max_subgoal_steps)
        current["reached"] = current["reached"] or bool(achieved)
        if terminated or truncated:
            for choice in choices:
                choice["gap"] = choice["gap"] / max(choice["steps"], 1)
                choice["best"] = choice["best"] / max(choice["steps"], 1)
            return dict(seed=seed, solved=bool(terminated and reward > 0), choices=choices)


def q_readings(model: HhP, goal: int, obs: np.ndarray) -> tuple[float, float]:
    """Sub-goal ``goal``'s learner at ``obs``: its best Q-value, and that minus its second best (the action gap);
    (nan, 0.0) for a learner without Q-values."""
    q_values = getattr(model.subpolicies, "q_values", None)
    if q_values is None:
        return float("nan"), 0.0
    top = np.sort(np.asarray(q_values(np.array([goal]), np.asarray(obs)[None]), dtype=np.float64)[0])[-2:]
    return float(top[-1]), (float(top[-1] - top[0]) if len(top) == 2 else 0.0)


def value_readings(episodes: list[dict]) -> Optional[dict]:
    """Over every step of every walk: the acting learner's mean best Q-value and the share of steps where it was above
    1; None where no choice has the readings."""
    walks = [c for e in episodes for c in e["choices"] if "best" in c and c["steps"] and np.isfinite(c["best"])]
    steps = sum(c["steps"] for c in walks)
    if not steps:
        return None
    return dict(steps=steps, mean_best=sum(c["best"] * c["steps"] for c in walks) / steps,
                share_above_1=sum(c["above_1"] for c in walks) / steps)


def walk_readings(episodes: list[dict]) -> dict[str, dict]:
    """Per chosen sub-goal: walks, steps, idle steps (their share of the steps) and the mean action gap over steps,
    from reached walks and from failed ones apart."""
    rows: dict[str, dict] = {}
    for episode in episodes:
        for choice in episode["choices"]:
            if "idle" not in choice:
                continue
            side = "reached" if choice["reached"] else "failed"
            row = rows.setdefault(choice["goal"], {f"{s}_{k}": 0 for s in ("reached", "failed")
                                                   for k in ("walks", "steps", "idle", "gap_sum")})
            row[f"{side}_walks"] += 1
            row[f"{side}_steps"] += choice["steps"]
            row[f"{side}_idle"] += choice["idle"]
            row[f"{side}_gap_sum"] += choice["gap"] * choice["steps"]
    for row in rows.values():
        for side in ("reached", "failed"):
            steps = row[f"{side}_steps"]
            row[f"{side}_idle_share"] = row[f"{side}_idle"] / steps if steps else None
            row[f"{side}_gap"] = row.pop(f"{side}_gap_sum") / steps if steps else None
    return rows


def view_reach(episodes: list[dict], view: Optional[int]) -> Optional[dict]:
    """Per chosen sub-goal: walks chosen and reached with the object it faces within the learners' ``view`` x ``view``
    cells around the agent at the choice (``view`` None or "inner": every cell) and beyond them; None where no choice
    has a distance."""
    radius = view // 2 if isinstance(view, int) else None
    goals: dict[str, dict] = {}
    for episode in episodes:
        for choice in episode["choices"]:
            if choice.get("distance") is None:
                continue
            where = "in_view" if radius is None or choice["distance"] <= radius else "out_of_view"
            row = goals.setdefault(choice["goal"], dict(in_view=0, in_view_reached=0, out_of_view=0,
                                                        out_of_view_reached=0))
            row[where] += 1
            row[f"{where}_reached"] += int(choice["reached"])
    return dict(view=view if view is not None else "every cell", goals=goals) if goals else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help="a model .zip, or a run's log folder (its newest checkpoint is loaded)")
    parser.add_argument("--env", default="MiniGrid-KeyCorridorS4R3-v0")
    parser.add_argument("--episodes", type=int, default=20, help="fresh episodes (seeds --seed, --seed + 1, ...)")
    parser.add_argument("--seed", type=int, default=20_000)
    parser.add_argument("--stochastic", action="store_true", help="the stochastic policy (default: deterministic)")
    parser.add_argument("--show", type=int, default=3, help="episodes printed choice by choice")
    parser.add_argument("--out", default=None, help="write every episode's choices as JSON here")
    parser.add_argument("--load-options", type=json.loads, default={},
                        help="HhP.load options as a JSON object, e.g. '{\"break_cycles\": false}' (plain greedy)")
    args = parser.parse_args()
    model_path = model_file(args.model)
    register_minigrid_tasks()
    model = HhP.load(model_path, device="cpu", **args.load_options)
    env = wrap_env(gym.make(args.env))
    episodes = [trace_episode(model, env, args.seed + i, not args.stochastic) for i in range(args.episodes)]
    for episode in episodes[: args.show]:
        chain = " -> ".join(f"{c['goal']}{'' if c['reached'] else ' (failed)'}" for c in episode["choices"])
        print(f"seed {episode['seed']} ({'solved' if episode['solved'] else 'not solved'}, "
              f"{len(episode['choices'])} choices): {chain[:1500]}\n")
    chosen, reached, cycled = Counter(), Counter(), Counter()
    for episode in episodes:
        for choice in episode["choices"]:
            chosen[choice["state"], choice["goal"]] += 1
            reached[choice["state"], choice["goal"]] += int(choice["reached"])
            cycled[choice["state"], choice["goal"]] += int(choice["cycled"])
    print(f"solved {sum(e['solved'] for e in episodes)} of {len(episodes)} episodes; choices made "
          "(cycled: came back to a state it had been in, unreached):")
    print(f"{'chosen':>7} {'reached':>7} {'cycled':>7}  in state -> sub-goal")
    for (state_key, goal), count in chosen.most_common(30):
        print(f"{count:7d} {reached[state_key, goal]:7d} {cycled[state_key, goal]:7d}  {state_key} -> {goal}")
    reach = view_reach(episodes, getattr(model.subpolicies, "view", None))
    if reach:
        print("walks by where the object the sub-goal faces was at the choice (view: the cells the learners read, "
              f"{reach['view']}):")
        print(f"{'in view: chosen':>15} {'reached':>7} {'out of view: chosen':>19} {'reached':>7}  sub-goal")
        for goal, row in reach["goals"].items():
            print(f"{row['in_view']:15d} {row['in_view_reached']:7d} {row['out_of_view']:19d} "
                  f"{row['out_of_view_reached']:7d}  {goal}")
    walks = walk_readings(episodes)
    values = value_readings(episodes)
    if values:
        print(f"the acting learner's best Q-value over {values['steps']} steps: mean {values['mean_best']:.3f}, above 1 "
              f"(more than eq. 5 with alpha 0 can return) at {values['share_above_1']:.2f} of them")
    print("walks by outcome: steps, idle steps (actions that left the env as it was) and the learner's mean action "
          "gap (best Q minus second best)")
    print(f"{'reached':>7} {'steps':>6} {'idle':>5} {'gap':>6} {'failed':>7} {'steps':>6} {'idle':>5} {'gap':>6}  sub-goal")
    for goal, row in sorted(walks.items(), key=lambda item: -(item[1]["reached_walks"] + item[1]["failed_walks"])):
        cells = []
        for side in ("reached", "failed"):
            share, gap = row[f"{side}_idle_share"], row[f"{side}_gap"]
            cells += [f"{row[f'{side}_walks']:7d}", f"{row[f'{side}_steps']:6d}",
                      f"{share:5.2f}" if share is not None else f"{'-':>5}", f"{gap:6.3f}" if gap is not None else f"{'-':>6}"]
        print(" ".join(cells) + f"  {goal}")
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(dict(model=model_path, env=args.env, view_reach=reach,
                                                          walks=walks, values=values, episodes=episodes), indent=1))


if __name__ == "__main__":
    main()
