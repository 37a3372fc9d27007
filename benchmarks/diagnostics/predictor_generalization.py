"""Does the preference predictor learn the scripted oracle's ranking from a hundred labels, in layouts it never saw?

The sub-goal set is every sub-goal key of DoorKey met in random play (with the key handed to the agent, and the
door opened, in a third of the episodes each, so that every phase of the task shows up). Labels: the scripted
oracle's answers about ``--labels`` (state, g1, g2) tuples in states drawn on training seeds; the predictor trains
as HhP trains it (its ``n_epochs`` after every new label). Test: on states drawn on other seeds, how often the
predictor's best choosable sub-goal is the oracle's (the next milestone of an optimal plan). Compared: what the
predictor reads (the observation, or the goal space's features) and how the pair of a query is drawn (any two
sub-goals, or two sub-goals choosable in the state, as with ``mask_subgoals``).

    python benchmarks/diagnostics/predictor_generalization.py --out benchmarks/results/predictor_generalization.json
"""

import argparse
import itertools
import json
import pathlib
import time

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces

from sb3_hhp.goals import MiniGridGoalSpace, wrap_env
from sb3_hhp.goals.minigrid import egocentric_grid
from sb3_hhp.oracles import MiniGridScriptedOracle, Query
from sb3_hhp.preferences.predictor import PreferencePredictor


def draw_state(env: gym.Env, seed: int, rng: np.random.Generator) -> np.ndarray:
    """A state of one of the task's three phases: no key, carrying the key, the door open; then a few random moves."""
    env.reset(seed=seed)
    base, phase = env.unwrapped, int(rng.integers(3))
    if phase:
        for x, y in itertools.product(range(base.width), range(base.height)):
            cell = base.grid.get(x, y)
            if cell is not None and cell.type == "key":
                base.grid.set(x, y, None)
                base.carrying = cell
            if cell is not None and cell.type == "door" and phase == 2:
                cell.is_locked, cell.is_open = False, True
    obs = egocentric_grid(base)  # the observation after the change
    for _ in range(int(rng.integers(0, 12))):
        obs, _, terminated, _, _ = env.step(int(rng.choice([0, 1, 2, 2])))
        if terminated:
            return draw_state(env, seed + 100_000, rng)
    return obs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MiniGrid-DoorKey-5x5-v0")
    parser.add_argument("--labels", type=int, default=100)
    parser.add_argument("--test-states", type=int, default=300)
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(10)), help="predictor seeds (and label draws)")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    th.set_num_threads(1)
    env = wrap_env(gym.make(args.env))
    space, oracle = MiniGridGoalSpace(), MiniGridScriptedOracle()
    rng = np.random.default_rng(12345)

    goal_obs: dict = {}
    for seed in range(200):  # the sub-goal set: one observation per key met
        obs = draw_state(env, 40_000 + seed, rng)
        for _ in range(30):
            goal_obs.setdefault(space.key(obs), obs)
            obs, _, terminated, _, _ = env.step(int(rng.integers(6)))
            if terminated:
                break
    keys = list(goal_obs)
    goals = np.stack([goal_obs[key] for key in keys])

    def best(obs: np.ndarray) -> tuple:
        info = space.privileged(env)
        steps = oracle.plan(info) or []
        carried = space.key(obs)[0]
        milestones = [k for k, acts in steps if k in keys and oracle.milestone(k, acts, carried)
                      and space.choosable(space.key(obs), k)]  # the oracle's own rule: where its plan acts
        return info, (keys.index(milestones[0]) if milestones else None)

    test = []
    for seed in range(args.test_states):
        obs = draw_state(env, 90_000 + seed, rng)
        _, target = best(obs)
        if target is not None:
            test.append((obs, target, np.array([space.choosable(space.key(obs), k) for k in keys])))

    results = []
    for reads, pairs, seed in itertools.product(("observation", "features"), ("any", "choosable"), args.seeds):
        began = time.perf_counter()
        transform = space.features if reads == "features" else (lambda batch: batch)
        input_space = spaces.Box(0, 1, (space.features(goals[:1]).shape[1],), np.float32) if reads == "features" else env.observation_space
        predictor = PreferencePredictor(input_space, hidden_dim=256, dropout=0.1, n_masks=20, buffer_size=args.labels, seed=seed)
        draw = np.random.default_rng(seed)
        n, label_seed = 0, 50_000 + 1_000 * seed
        while n < args.labels:
            obs = draw_state(env, label_seed, draw)
            label_seed += 1
            info, _ = best(obs)
            allowed = np.flatnonzero([space.choosable(space.key(obs), k) for k in keys]) if pairs == "choosable" else np.arange(len(keys))
            if len(allowed) < 2:
                continue
            g1, g2 = (int(g) for g in draw.choice(allowed, 2, replace=False))
            query = Query(state=obs, goal1=g1, goal2=g2, goal1_obs=goals[g1], goal2_obs=goals[g2],
                          info={"state": info, "goal1_key": list(keys[g1]), "goal2_key": list(keys[g2])})
            if predictor.add(transform(obs[None])[0], transform(goals[g1][None])[0], transform(goals[g2][None])[0], oracle.answer(query)):
                n += 1
                predictor.train()
        goal_inputs = transform(goals)
        hits = []
        for obs, target, mask in test:
            scores = predictor.score(np.repeat(transform(obs[None]), len(keys), axis=0), goal_inputs)
            scores[~mask] = -np.inf
            hits.append(int(np.argmax(scores)) == target)
        results.append(dict(reads=reads, pairs=pairs, seed=seed, labels=args.labels, agreement=float(np.mean(hits)),
                            test_states=len(test), train_accuracy=predictor.accuracy(), seconds=round(time.perf_counter() - began, 1)))
        print(json.dumps(results[-1]), flush=True)
    summary = {}
    for reads, pairs in itertools.product(("observation", "features"), ("any", "choosable")):
        values = [r["agreement"] for r in results if r["reads"] == reads and r["pairs"] == pairs]
        summary[f"{reads}/{pairs}"] = dict(mean=float(np.mean(values)), per_seed=values)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    chance = float(np.mean([1.0 / mask.sum() for _, _, mask in test]))  # a random choosable sub-goal
    summary["chance"] = dict(mean=chance)
    out.write_text(json.dumps(dict(env=args.env, subgoals=[space.describe(k) for k in keys], runs=results, summary=summary), indent=2))
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
