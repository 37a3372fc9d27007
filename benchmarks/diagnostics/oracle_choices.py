"""The scripted oracle chooses, a run's learners act: is a MiniGrid run stuck in its choices or in its skills?

Loads a trained model (a ``.zip``, or a run folder's newest checkpoint) and plays fresh episodes twice: once as the
model plays them (``predict``), and once with every sub-goal chosen by the scripted oracle: its plan from the state
(the privileged facts its answers read, boxes' contents included) ranks every sub-goal as an answer does, and the
first milestone of the plan among the sub-goals choosable in the state is chosen, under the rules ``predict``
settles its choices by (not the sub-goal that just gave up; with ``break_cycles`` none chosen before in the same
observation this episode). Everything else is ``predict``'s: the learners act for the chosen sub-goal as they do
there (greedy with its cycle-breaking, or with ``--stochastic`` epsilon-greedy, choices too); a walk ends where
training ends it (reached, or given up after ``max_subgoal_steps``). Where the plan names none of the choosable
sub-goals, the model's own meta-controller chooses (counted).

Solved with the oracle's choices and not with the model's: the meta-controller (or the predictor it follows) is
what is missing. Unsolved either way: the learners cannot carry out the plan with the sub-goals found; the
per-sub-goal table shows which walk fails.

    python benchmarks/diagnostics/oracle_choices.py RUN --env MiniGrid-ObstructedMaze-1Q-v1 --episodes 20 \\
        --out benchmarks/results/diagnostics/oracle_choices.json
"""

import argparse
import json
import pathlib
import sys
from collections import Counter
from typing import Any, Callable, Optional

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2]))
from benchmarks.diagnostics.key_skills import model_file  # noqa: E402
from sb3_hhp import HhP  # noqa: E402
from sb3_hhp.goals import register_minigrid_tasks, wrap_env  # noqa: E402
from sb3_hhp.goals.minigrid import EMPTY  # noqa: E402
from sb3_hhp.hierarchy.options import option_terminal  # noqa: E402
from sb3_hhp.oracles import make_oracle  # noqa: E402

import gymnasium as gym  # noqa: E402


def oracle_chooser(model: HhP, oracle: Any, env: gym.Env, planned: list, agree: Counter,
                   records: Optional[list] = None) -> Callable:
    """A stand-in for ``model._other_choices`` (where ``predict`` settles each greedy choice, ruling out the
    sub-goal that just gave up and, with ``break_cycles``, those chosen before in the same observation): the
    first milestone of the oracle's plan from the env's state among the choosable sub-goals not ruled out; the
    model's own choice where the plan names none of them. Appends to ``planned`` whether the plan chose, and counts
    in ``agree`` the plan's choices (``choices``) and those the meta-controller's choice (``meta``) and the
    predictor's best-scored sub-goal (``predictor``), among the same ones (the plan's or not), would have matched (a
    tie on the plan counts); appends to ``records`` (where given), for each choice the plan made, what the predictor
    reads of the state, the plan's ranks of every sub-goal (inf: not choosable, or off the plan), the choosable
    sub-goals (on the plan or off it), the plan's best ones, the state's description (:func:`feature_ceiling` reads
    them) and the predictor's and the meta-controller's choices (:func:`departures`)."""
    keys = [goal.key for goal in model.subgoals]
    goal_inputs = model.predictor_inputs(model.goal_obs)  # the sub-goals stay the same while the model plays

    def choose(batch: np.ndarray, chosen: np.ndarray, excluded: np.ndarray) -> np.ndarray:
        own = HhP._other_choices(model, batch, chosen, excluded)
        state = model.goal_space.privileged(env)
        plan = oracle.plan(state)
        carried = state["carrying"][0] if state.get("carrying") is not None else EMPTY
        ranks = np.array([oracle.rank(plan, key, carried) for key in keys])
        mask = model.action_mask(batch)
        allowed = ~excluded[0, : len(ranks)]  # the choices predict may make here, on the plan or off it
        if mask is not None:
            allowed &= np.broadcast_to(mask, (len(batch), mask.shape[-1]))[0, : len(ranks)]
        ranks[~allowed] = np.inf
        planned.append(bool(np.isfinite(ranks).any()))
        if planned[-1]:  # would the meta-controller, or the predictor's best score, have chosen as the plan does?
            reads = model.predictor_inputs(batch)[0]
            scores = model.predictor.score_matrix(reads[None], goal_inputs)[0]
            scores[~allowed] = -np.inf  # among the same choices as the meta-controller: off the plan too
            agree["meta"] += int(ranks[own[0]] == ranks.min())
            agree["predictor"] += int(ranks[scores.argmax()] == ranks.min())
            agree["choices"] += 1
            if records is not None:
                records.append(dict(inputs=reads, ranks=ranks.copy(),
                                    choosable=tuple(np.flatnonzero(allowed).tolist()),
                                    best=tuple(np.flatnonzero(ranks == ranks.min()).tolist()),
                                    state=model.goal_space.describe(model.goal_space.key(batch[0])),
                                    predictor=int(scores.argmax()), meta=int(own[0])))
        return np.array([ranks.argmin()]) if planned[-1] else own

    return choose


def feature_ceiling(records: list, describe: Callable[[int], str] = str, top: int = 10) -> dict:
    """The most of the plan's choices ``records`` (:func:`oracle_chooser`'s) that any chooser reading only what the
    predictor reads could match: choices whose state reads alike and whose choosable sub-goals are the same must get
    the same sub-goal, so each such group is matched at most as often as its most often best sub-goal is best. Below
    1, the features cannot tell apart states where the plan chooses differently (no label can mend it); near 1 and
    the predictor far below it, the labels (or the predictor's generalisation) are what is missing. Also the
    ``top`` groups that lose the most, with the states they held and the plan's choices there (``describe``
    names a sub-goal index)."""
    groups: dict = {}
    for record in records:
        groups.setdefault((record["inputs"].tobytes(), record["choosable"]), []).append(record)
    matched, conflicts = 0, []
    for group in groups.values():
        best = Counter(goal for record in group for goal in record["best"])
        most = best.most_common(1)[0][1]
        matched += most
        if most < len(group):
            plans = Counter(" / ".join(describe(goal) for goal in record["best"]) for record in group)
            conflicts.append(dict(choices=len(group), matched=most, states=sorted({r["state"] for r in group}),
                                  plan=dict(plans.most_common())))
    conflicts.sort(key=lambda c: c["matched"] - c["choices"])
    return dict(choices=len(records), groups=len(groups), ceiling=matched, conflicts=conflicts[:top])


def departures(records: list, chooser: str, describe: Callable[[int], str] = str, top: int = 10) -> list:
    """Where ``chooser`` ("predictor": its best score; "meta": the meta-controller) chose other than the plan, in
    :func:`oracle_chooser`'s ``records``: the ``top`` most frequent (state, the plan's best, the chooser's choice),
    each with its count, most frequent first."""
    counts = Counter((record["state"], " / ".join(describe(goal) for goal in record["best"]), describe(record[chooser]))
                     for record in records if record[chooser] not in record["best"])
    return [dict(state=state, plan=plan, chosen=chosen, count=count)
            for (state, plan, chosen), count in counts.most_common(top)]


def predictor_chooser(model: HhP, planned: list) -> Callable:
    """A stand-in for ``model._other_choices`` that chooses the predictor's best-scored sub-goal among the choosable
    ones not ruled out (the meta-controller's reward without its learned values, eq. 3 with beta 0)."""
    goal_inputs = model.predictor_inputs(model.goal_obs)  # the sub-goals stay the same while the model plays

    def choose(batch: np.ndarray, chosen: np.ndarray, excluded: np.ndarray) -> np.ndarray:
        scores = model.predictor.score_matrix(model.predictor_inputs(batch), goal_inputs)
        mask = model.action_mask(batch)
        if mask is not None:
            scores[~np.broadcast_to(mask, (len(batch), mask.shape[-1]))[:, : scores.shape[1]]] = -np.inf
        scores[excluded[:, : scores.shape[1]]] = -np.inf
        left = np.isfinite(scores).any(axis=1)
        planned.append(bool(left.all()))
        return np.where(left, scores.argmax(axis=1), chosen)

    return choose


def play(model: HhP, env: gym.Env, seed: int, deterministic: bool, planned: list) -> dict:
    """One episode with ``predict`` (as ``evaluate_policy`` plays it): whether it was solved and its walks
    ``(state, sub-goal, reached, steps, planned)``; ``planned`` is filled by :func:`oracle_chooser` where it chooses."""
    obs, _ = env.reset(seed=seed)
    describe, keys = model.goal_space.describe, [goal.key for goal in model.subgoals]
    state, start, walks = None, True, []
    del planned[:]
    while True:
        action, state = model.predict(obs, state=state, episode_start=np.array([start]), deterministic=deterministic)
        goal, steps = int(state[0][0]), int(state[1][0])
        if steps == 1:  # a new choice was made in this state
            walks.append(dict(state=describe(model.goal_space.key(obs)), goal=describe(keys[goal]), reached=False,
                              steps=0, planned=bool(planned[-1]) if planned else False))
            del planned[:]
        obs, reward, terminated, truncated, _ = env.step(action)
        start = False
        walks[-1]["steps"] += 1
        key = model.goal_space.terminal_key(obs, float(reward), bool(terminated))
        reached, _ = option_terminal(model.goal_space, key, keys[goal], steps, model.max_subgoal_steps)
        walks[-1]["reached"] = walks[-1]["reached"] or bool(reached)
        if terminated or truncated:
            return dict(seed=seed, solved=bool(terminated and reward > 0), steps=sum(w["steps"] for w in walks),
                        walks=walks)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help="a model .zip, or a run's log folder (its newest checkpoint is loaded)")
    parser.add_argument("--env", default="MiniGrid-ObstructedMaze-1Q-v1")
    parser.add_argument("--episodes", type=int, default=20, help="fresh episodes (seeds --seed, --seed + 1, ...)")
    parser.add_argument("--seed", type=int, default=20_000)
    parser.add_argument("--stochastic", action="store_true", help="learners act epsilon-greedy (default: greedy)")
    parser.add_argument("--chooser", choices=["oracle", "predictor"], default="oracle",
                        help="who chooses in the second play: the oracle's plan, or the predictor's best score")
    parser.add_argument("--out", default=None, help="write every episode's walks as JSON here")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    model_path = model_file(args.model)
    register_minigrid_tasks()
    model = HhP.load(model_path, device="cpu")
    if model.goal_space.name != "minigrid":
        raise SystemExit(f"the scripted oracle plans MiniGrid goal spaces only; this model's is {model.goal_space.name!r}")
    oracle = make_oracle("scripted", model.goal_space, model.primitive_observation_space)
    env = wrap_env(gym.make(args.env))
    deterministic = not args.stochastic
    planned: list = []
    own = [play(model, env, args.seed + i, deterministic, planned)["solved"] for i in range(args.episodes)]
    agree: Counter = Counter()
    records: list = []
    if args.chooser == "oracle":
        model._other_choices = oracle_chooser(model, oracle, env, planned, agree, records)
    else:
        model._other_choices = predictor_chooser(model, planned)
    episodes = [play(model, env, args.seed + i, deterministic, planned) for i in range(args.episodes)]
    chosen, reached = Counter(), Counter()
    for episode in episodes:
        for walk in episode["walks"]:
            chosen[walk["state"], walk["goal"]] += 1
            reached[walk["state"], walk["goal"]] += int(walk["reached"])
    solved = sum(e["solved"] for e in episodes)
    unplanned = sum(not w["planned"] for e in episodes for w in e["walks"])
    print(f"{model_path}: {len(model.subgoals)} sub-goals; {args.episodes} episodes from seed {args.seed}, learners "
          f"{'greedy' if deterministic else 'epsilon-greedy'}")
    who = "the oracle's plan" if args.chooser == "oracle" else "the predictor's best score"
    print(f"solved with {who} choosing: {solved} of {args.episodes}; with the model's own choices: {sum(own)}; "
          f"choices {who} left to the model (none of its choices choosable): {unplanned}")
    if args.chooser == "oracle":
        print(f"of the {agree['choices']} choices the plan made, the meta-controller would have made the same in "
              f"{agree['meta']}, the predictor's best score in {agree['predictor']}")
        describe = lambda goal: model.goal_space.describe(model.subgoals[goal].key)  # noqa: E731
        ceiling = feature_ceiling(records, describe)
        print(f"the most any chooser reading the predictor's input could match: {ceiling['ceiling']} of "
              f"{ceiling['choices']} ({ceiling['groups']} distinct inputs with their choosable sub-goals); where "
              f"states that read alike got different plan choices:")
        for conflict in ceiling["conflicts"]:
            print(f"  {conflict['matched']} of {conflict['choices']} at best; states {conflict['states']}; "
                  f"plan {conflict['plan']}")
        departed = {chooser: departures(records, chooser, describe) for chooser in ("predictor", "meta")}
        for chooser, name in (("predictor", "the predictor's best score"), ("meta", "the meta-controller")):
            print(f"where {name} chose other than the plan (most frequent first): count, state: plan's -> its")
            for row in departed[chooser]:
                print(f"  {row['count']:4d}  {row['state']}: {row['plan']} -> {row['chosen']}")
    print(f"{'chosen':>7} {'reached':>7}  in state -> sub-goal (the second play's choices)")
    for (state_key, goal), count in chosen.most_common(30):
        print(f"{count:7d} {reached[state_key, goal]:7d}  {state_key} -> {goal}")
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(dict(
            model=model_path, env=args.env, deterministic=deterministic, seed=args.seed, chooser=args.chooser,
            solved_chooser=solved, solved_model=int(sum(own)), agreement=dict(agree),
            ceiling=ceiling if args.chooser == "oracle" else None,
            departures=departed if args.chooser == "oracle" else None, episodes=episodes), indent=1))


if __name__ == "__main__":
    main()
