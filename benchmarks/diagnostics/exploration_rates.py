"""Where a run's stochastic policy is random: each sub-goal learner's own steps and exploration rate, and the
stochastic success with the rates as trained against the same model with every learner at its final rate.

A sub-goal learner's epsilon falls from its initial to its final value over its own first ``exploration_steps``
steps (``StackedDQN.exploration_rate``), so a sub-goal the meta-controller seldom chooses (the last walk of a long
plan, found late) keeps acting almost at random late in a run, and the stochastic policy (``predict`` with
``deterministic=False``, as in training) inherits that rate. Printed per learner: its own steps, its epsilon, its
share of reached tries among its last 100; then the stochastic success on ``--episodes`` fresh episodes (seeds from
``--first-seed``, not the runs' evaluation seeds) as the model is, and again on the same episodes with every
learner's own steps set past ``exploration_steps`` (its final epsilon; nothing else of the model changes).

    python benchmarks/diagnostics/exploration_rates.py RUN/checkpoints/1000000/model.zip \\
        --env MiniGrid-DoorKey-16x16-v0 --episodes 20 --out benchmarks/results/diagnostics/F.json
"""

import argparse
import json
import pathlib
import sys

import numpy as np
import torch as th

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2]))
from benchmarks.evaluate import run_episodes  # noqa: E402
from sb3_hhp import HhP  # noqa: E402
from sb3_hhp.goals import register_minigrid_tasks  # noqa: E402


def learners_table(model: HhP) -> list[dict]:
    """Per sub-goal: its name, own steps, current epsilon and recent success rate."""
    learners = model.subpolicies
    return [
        dict(subgoal=model.goal_space.describe(goal.key), own_steps=int(learners.own_steps[g]),
             epsilon=round(learners.exploration_rate(g), 3), success_rate=learners.success_rate(g))
        for g, goal in enumerate(model.subgoals)
    ]


def stochastic_success(model: HhP, env_id: str, seeds: list[int]) -> dict:
    results = run_episodes(model, env_id, seeds, deterministic=False)
    return dict(success=float(np.mean(results["successes"])), mean_length=float(np.mean(results["lengths"])))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model")
    parser.add_argument("--env", required=True)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=20_000, help="fresh episodes from this seed on")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    th.set_num_threads(1)
    register_minigrid_tasks()
    model = HhP.load(args.model, device="cpu")
    table = learners_table(model)
    for row in table:
        print(f"{row['subgoal']:45s} own steps {row['own_steps']:8d}  epsilon {row['epsilon']:.3f}  "
              f"reached {row['success_rate'] if row['success_rate'] is None else round(row['success_rate'], 2)}")
    seeds = list(range(args.first_seed, args.first_seed + args.episodes))
    np.random.seed(args.first_seed)
    as_trained = stochastic_success(model, args.env, seeds)
    print(f"stochastic, epsilons as trained: {as_trained}")
    learners = model.subpolicies
    learners.own_steps[:] = np.maximum(learners.own_steps, learners.exploration_steps)
    np.random.seed(args.first_seed)
    final = stochastic_success(model, args.env, seeds)
    print(f"stochastic, every learner at its final epsilon: {final}")
    result = dict(model=args.model, env=args.env, episodes=args.episodes, first_seed=args.first_seed,
                  learners=table, stochastic_as_trained=as_trained, stochastic_final_epsilon=final)
    if args.out:
        pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
