"""Is an unspent query budget a pacing fault, or were there no new questions to ask?

Trains HhP with the env's YAML entry (8 envs, the scripted oracle, the adaptive mode) and records, at every
question round (one per finished episode): the episode's distinct (state as the predictor reads it, chosen
sub-goal) tuples, how many of them have a second choosable sub-goal, how many of those are still askable (the pair
not asked before: no question is asked twice), the adaptive quota and the tuples selected (a pair selected twice in
one episode is asked once).

    python benchmarks/diagnostics/query_supply.py --env MiniGrid-MultiRoom-N12-S10-v0 --steps 20000 --out benchmarks/results/query_supply.json

When ``selected`` equals ``askable`` in every round while the quota stays above 0, the budget went unspent because every
question the run could ask had been asked.
"""

import argparse
import json
import pathlib
import sys
import tempfile

import numpy as np
import torch as th

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2]))
from benchmarks.speed import as_trained, entry_kwargs, make_envs  # noqa: E402
from sb3_hhp import HhP  # noqa: E402
from sb3_hhp.goals import register_minigrid_tasks  # noqa: E402


def record_rounds(model: HhP) -> list[dict]:
    """Wrap ``model.query_selector.select`` so each call records what it was offered and what it asked."""
    selector, rounds = model.query_selector, []
    select = selector.select

    def recorded(confidences, goals, q_values, num_timesteps=0, exclude=None):
        others = np.where(np.isnan(q_values), -np.inf, np.asarray(q_values, dtype=np.float64))
        others[np.arange(len(goals)), goals] = -np.inf
        with_second = (others > -np.inf).any(axis=1)
        if exclude is not None:
            others[np.asarray(exclude, dtype=bool)] = -np.inf
        askable = (others > -np.inf).any(axis=1)
        quota = selector.allowance(num_timesteps) - selector.used if selector.mode == "adaptive" else selector.remaining
        chosen = select(confidences, goals, q_values, num_timesteps=num_timesteps, exclude=exclude)
        rounds.append(dict(step=int(num_timesteps), tuples=len(goals), with_second=int(with_second.sum()),
                           askable=int(askable.sum()), quota=int(quota), selected=len(chosen),
                           subgoals=int(q_values.shape[1])))
        return chosen

    selector.select = recorded
    return rounds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="MiniGrid-MultiRoom-N12-S10-v0")
    parser.add_argument("--steps", type=int, default=20_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n-envs", type=int, default=8)
    parser.add_argument("--out", default="benchmarks/results/query_supply.json")
    args = parser.parse_args()
    th.set_num_threads(1)
    register_minigrid_tasks()
    entry, kwargs = entry_kwargs(args.env)
    folder = pathlib.Path(tempfile.mkdtemp(prefix="hhp_query_supply_"))  # as sb3_hhp.train builds it: a preference file
    model = HhP("MlpPolicy", make_envs(args.env, args.n_envs, args.seed), seed=args.seed, **as_trained(kwargs, folder))
    rounds = record_rounds(model)
    model.learn(args.steps)
    totals = {key: int(sum(r[key] for r in rounds)) for key in ("tuples", "with_second", "askable", "selected")}
    result = dict(env=args.env, entry=entry, steps=model.num_timesteps, seed=args.seed, n_envs=args.n_envs,
                  query_budget=model.query_selector.budget, queries_used=model.query_selector.used,
                  num_subgoals=len(model.subgoals), rounds=len(rounds), totals=totals,
                  rounds_with_quota_and_nothing_askable=sum(r["quota"] > 0 and r["askable"] == 0 for r in rounds),
                  rounds_selecting_less_than_askable_and_quota=sum(r["selected"] < min(r["askable"], r["quota"]) for r in rounds),
                  final_quota=rounds[-1]["quota"] if rounds else None, per_round=rounds)
    pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    pathlib.Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({key: value for key, value in result.items() if key != "per_round"}, indent=1))


if __name__ == "__main__":
    main()
