"""Where must a question be asked for the predictor to learn a plan? Labels placed on the states a plan goes through.

``oracle_choices.py`` showed that on ObstructedMaze-1Q a run's predictor made the scripted oracle's plan's choice in
fewer than half of the plan's choices while what it reads allowed about 0.9 of them (its feature ceiling), and that it
fitted every label it had (``predictor_labels.py``). This asks whether a hundred labels can bring a predictor of the
same kind near that ceiling when the questions are asked where the plan goes, and which pair of sub-goals a question
should name there.

A run's model plays ``--train-episodes`` fresh episodes with the scripted oracle's plan choosing (its learners
acting, as in ``oracle_choices.py``; seeds from ``--train-seed``) and ``--test-episodes`` more (seeds from
``--seed``, the diagnostics' evaluation seeds). Every choice the plan made is a state where a question can be asked;
the oracle answers it as it ranks sub-goals (the one earlier in its plan preferred; two of equal rank teach nothing,
the label is spent). For each way of naming a question's pair, a fresh predictor with the run's settings trains as
runs train it (after every label) on ``--labels`` questions in states drawn at random from the training
episodes' choices, and is scored on the test episodes' choices: how often its best-scored choosable sub-goal is
among the plan's best (the agreement ``oracle_choices.py`` reports). The pairs:

- ``plan``: the plan's choice against another choosable sub-goal (the paper's rule, choice against second choice,
  had the meta-controller chosen as the plan does);
- ``random``: two choosable sub-goals at random;
- ``top2``: the predictor's own two best-scored choosable sub-goals (where its choice would change).

``--predictor-kwargs`` changes the fresh predictors' settings, ``--goal-input change`` has them read a sub-goal as the
change it would make to the state's features instead of its features; ``--records`` keeps the plan's choices in a
file, so that a second comparison plays no episodes::

    python benchmarks/diagnostics/predictor_placement.py RUN/MiniGrid-ObstructedMaze-1Q-v1.zip --labels 25 50 100 200 \\
        --out benchmarks/results/diagnostics/predictor_placement.json
"""

import argparse
import json
import pathlib
import pickle
import sys
import time
from collections import Counter
from typing import Any, Callable

import numpy as np
import torch as th

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2]))
from benchmarks.diagnostics.key_skills import model_file  # noqa: E402
from benchmarks.diagnostics.oracle_choices import feature_ceiling, oracle_chooser, play  # noqa: E402
from sb3_hhp import HhP  # noqa: E402
from sb3_hhp.goals import register_minigrid_tasks, wrap_env  # noqa: E402
from sb3_hhp.oracles import make_oracle  # noqa: E402
from sb3_hhp.preferences.predictor import PreferencePredictor  # noqa: E402
from sb3_hhp.preferences.types import Label  # noqa: E402

import gymnasium as gym  # noqa: E402

PAIRS = ("plan", "random", "top2")


def plan_records(model: HhP, oracle: Any, env: gym.Env, seeds: range) -> list[dict]:
    """The plan's choices (``oracle_chooser``'s records) over fresh episodes of ``seeds``, the model's learners
    acting greedily."""
    records: list = []
    planned: list = []
    model._other_choices = oracle_chooser(model, oracle, env, planned, Counter(), records)
    for seed in seeds:
        play(model, env, seed, True, planned)
    return records


def answer(ranks: np.ndarray, goal1: int, goal2: int) -> Label:
    """The scripted oracle's label of ``(goal1, goal2)`` from its plan's ranks (lower: earlier in the plan)."""
    if ranks[goal1] == ranks[goal2]:
        return Label.INCOMPARABLE
    return Label.FIRST if ranks[goal1] < ranks[goal2] else Label.SECOND


def pair_of(rule: str, record: dict, scores: Callable[[dict], np.ndarray], rng: np.random.Generator) -> tuple[int, int]:
    """The two sub-goals a question names in ``record``'s state under ``rule`` (:data:`PAIRS`); ``scores`` gives the
    current predictor's scores of every sub-goal there."""
    choosable = np.asarray(record["choosable"])
    if rule == "plan":
        first = int(rng.choice(record["best"]))
        others = choosable[choosable != first]
        return first, int(rng.choice(others))
    if rule == "random":
        first, second = rng.choice(choosable, size=2, replace=False)
        return int(first), int(second)
    if rule == "top2":
        values = scores(record)[choosable]
        order = np.argsort(-values, kind="stable")
        return int(choosable[order[0]]), int(choosable[order[1]])
    raise ValueError(f"unknown pair rule {rule!r}: one of {PAIRS}")


def ask(usable: list[dict], rule: str, scores: Callable[[dict], np.ndarray], rng: np.random.Generator
        ) -> tuple[dict, int, int, Label]:
    """One question: a state drawn from ``usable`` (records with two or more choosable sub-goals), the pair ``rule``
    names there (:func:`pair_of`) and the oracle's label of it (:func:`answer`)."""
    record = usable[int(rng.integers(len(usable)))]
    goal1, goal2 = pair_of(rule, record, scores, rng)
    return record, goal1, goal2, answer(record["ranks"], goal1, goal2)


GOAL_INPUTS = ("features", "change")


def goal_input(goals: np.ndarray, state: np.ndarray, how: str) -> np.ndarray:
    """What the predictor reads of sub-goals ``goals`` ``(G, D)`` in ``state`` ``(D,)``: their features as the run
    reads them (``features``), or the change each would make to the state's (``change``: ``goal - state``)."""
    return goals if how == "features" else goals - state[None]


def scores_of(predictor: PreferencePredictor, goals: np.ndarray, states: np.ndarray, how: str = "features") -> np.ndarray:
    """The predictor's scores ``(N, G)`` of every sub-goal in each of ``states`` ``(N, D)``."""
    if how == "features":
        return predictor.score_matrix(states, goals)
    n, g = len(states), len(goals)
    pairs = np.repeat(states, g, axis=0)
    return predictor.score(pairs, (goals[None] - states[:, None]).reshape(n * g, -1)).reshape(n, g)


def agreement(predictor: PreferencePredictor, goals: np.ndarray, records: list[dict], how: str = "features") -> float:
    """The fraction of ``records`` whose best-scored choosable sub-goal is among the plan's best (``how``: what the
    predictor reads of a sub-goal, :func:`goal_input`)."""
    if not records:
        return float("nan")
    return matched(scores_of(predictor, goals, np.stack([r["inputs"] for r in records]), how), records)


def matched(scores: np.ndarray, records: list[dict]) -> float:
    """The fraction of ``records`` whose best-scored choosable sub-goal, by their rows of ``scores`` ``(N, G)``, is
    among the plan's best."""
    hits = 0
    for row, record in zip(scores, records):
        choosable = np.asarray(record["choosable"])
        hits += int(choosable[row[choosable].argmax()] in record["best"])
    return hits / len(records) if records else float("nan")


def placement_curve(make_predictor: Callable[[], PreferencePredictor], goals: np.ndarray, train: list[dict],
                    test: list[dict], rule: str, labels: list[int], seed: int, how: str = "features") -> list[dict]:
    """A fresh predictor trained after every label on ``max(labels)`` questions under ``rule`` in random states of
    ``train`` (those with two or more choosable sub-goals); its agreement on ``test`` (and ``train``) at each count
    of ``labels`` spent."""
    rng = np.random.default_rng(seed)
    predictor = make_predictor()
    usable = [r for r in train if len(r["choosable"]) >= 2]
    scores = lambda record: scores_of(predictor, goals, record["inputs"][None], how)[0]  # noqa: E731
    points, taught = [], 0
    for spent in range(1, max(labels) + 1):
        record, goal1, goal2, label = ask(usable, rule, scores, rng)
        read = goal_input(goals[[goal1, goal2]], record["inputs"], how)
        if predictor.add(record["inputs"], read[0], read[1], label):
            predictor.train()
            taught += 1
        if spent in labels:
            points.append(dict(labels=spent, taught=taught, test=agreement(predictor, goals, test, how),
                               train=agreement(predictor, goals, train, how)))
    return points


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help="a model .zip, or a run's log folder (its newest checkpoint is loaded)")
    parser.add_argument("--env", default="MiniGrid-ObstructedMaze-1Q-v1")
    parser.add_argument("--train-episodes", type=int, default=30)
    parser.add_argument("--train-seed", type=int, default=30_000, help="the training episodes' first seed")
    parser.add_argument("--test-episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=20_000, help="the test episodes' first seed")
    parser.add_argument("--labels", type=int, nargs="+", default=[25, 50, 100, 200], help="label counts scored")
    parser.add_argument("--pairs", nargs="+", default=list(PAIRS), choices=PAIRS)
    parser.add_argument("--repeats", type=int, default=3, help="predictors per rule (seeds 0, 1, ...)")
    parser.add_argument("--records", default=None,
                        help="a pickle of the plan's choices for this model and these seeds: read if it exists (no episodes "
                             "played), else written")
    parser.add_argument("--predictor-kwargs", type=json.loads, default={},
                        help="JSON: settings of the fresh predictors over the run's (e.g. '{\"hidden_dim\": 64}')")
    parser.add_argument("--goal-input", choices=GOAL_INPUTS, default="features",
                        help="what the fresh predictors read of a sub-goal: its features (as runs), or the change it "
                             "would make to the state's features")
    parser.add_argument("--state-dims", type=int, default=None,
                        help="the fresh predictors read only the first N features of a state, the rest zeroed (MiniGrid: "
                             "the one-hots of what is carried and faced, and the goal space's flags, come first; "
                             "the grid's (object, state) presence flags last)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    for name in ("train_episodes", "test_episodes", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.state_dims is not None and args.state_dims < 0:
        parser.error(f"--state-dims must be >= 0, got {args.state_dims}")
    if min(args.labels) < 1:
        parser.error(f"--labels must be >= 1, got {args.labels}")
    model_path = model_file(args.model)
    register_minigrid_tasks()
    model = HhP.load(model_path, device="cpu")
    oracle = make_oracle("scripted", model.goal_space, model.primitive_observation_space)
    env = wrap_env(gym.make(args.env))
    th.set_num_threads(1)  # a small network trained after every label: more threads only contend (seconds -> minutes)
    start = time.perf_counter()
    cached = pathlib.Path(args.records) if args.records else None
    if cached is not None and cached.exists():
        train, test = pickle.loads(cached.read_bytes())
    else:
        train = plan_records(model, oracle, env, range(args.train_seed, args.train_seed + args.train_episodes))
        test = plan_records(model, oracle, env, range(args.seed, args.seed + args.test_episodes))
        if cached is not None:
            cached.write_bytes(pickle.dumps((train, test)))
    goals = model.predictor_inputs(model.goal_obs)
    ceiling = feature_ceiling(test)
    run_predictor = agreement(model.predictor, goals, test)  # the run's own predictor reads a state whole
    if args.state_dims is not None:  # what the fresh predictors read of a state
        kept = np.arange(goals.shape[1]) < args.state_dims
        train, test = ([dict(record, inputs=np.where(kept, record["inputs"], 0).astype(record["inputs"].dtype))
                        for record in records] for records in (train, test))
    print(f"{model_path}: {len(model.subgoals)} sub-goals; the plan's choices: {len(train)} in {args.train_episodes} "
          f"training episodes, {len(test)} in {args.test_episodes} test episodes ({time.perf_counter() - start:.0f} s)")
    print(f"test choices: the run's own predictor matches {run_predictor:.2f}; the feature ceiling "
          f"{ceiling['ceiling'] / max(ceiling['choices'], 1):.2f}")
    settings = {**model.predictor_settings, "buffer_size": max(args.labels), **args.predictor_kwargs}
    space = model.predictor.observation_space
    curves: dict = {}
    for rule in args.pairs:
        curves[rule] = []
        for repeat in range(args.repeats):
            make = lambda: PreferencePredictor(space, **{**settings, "seed": repeat})  # noqa: E731
            curves[rule].append(placement_curve(make, goals, train, test, rule, sorted(args.labels), seed=repeat,
                                               how=args.goal_input))
        for i, count in enumerate(sorted(args.labels)):
            tests = [curve[i]["test"] for curve in curves[rule]]
            taught = [curve[i]["taught"] for curve in curves[rule]]
            print(f"  {rule:>6}, {count:4d} labels ({min(taught)}-{max(taught)} taught): test agreement "
                  f"{np.mean(tests):.2f} (" + ", ".join(f"{t:.2f}" for t in tests) + ")")
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(dict(
            model=model_path, env=args.env, train_seeds=[args.train_seed, args.train_episodes],
            test_seeds=[args.seed, args.test_episodes], train_choices=len(train), test_choices=len(test),
            run_predictor=run_predictor, ceiling=ceiling["ceiling"] / max(ceiling["choices"], 1),
            settings={k: v for k, v in settings.items() if not callable(v)}, goal_input=args.goal_input,
            state_dims=args.state_dims,
            curves=curves), indent=1, default=str))


if __name__ == "__main__":
    main()
