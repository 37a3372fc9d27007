"""Imperfect teachers: a noisy oracle and several experts, handed to HhP as Oracle instances.

Any :class:`sb3_hhp.oracles.Oracle` can answer HhP's questions. This script wraps the scripted
MiniGrid oracle (the "expert" that plans on the real grid) in two ways:

- :class:`~sb3_hhp.oracles.NoisyOracle`: each answer is wrong with probability ``rho`` (the paper's
  varrho in {0.05, 0.1, 0.2});
- :class:`~sb3_hhp.oracles.MultiExpertOracle`: several experts who do not talk to each other (here
  two scripted experts with different error rates), one drawn per query or per run.

It trains one short run with each and prints who answered what, read back from the preference store.

    python examples/noisy_and_experts.py --rho 0.2   # Empty-Random-5x5, 6,000 steps a run, 4 envs
"""

import argparse
from collections import Counter

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env
from sb3_hhp.oracles import MiniGridScriptedOracle, MultiExpertOracle, NoisyOracle, Oracle
from small_settings import SMALL_ENV, SMALL_SETTINGS


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default=SMALL_ENV, help="a MiniGrid env id")
    parser.add_argument("--steps", type=int, default=6_000, help="training length of each run, in primitive env steps")
    parser.add_argument("--budget", type=int, default=20, help="questions per run")
    parser.add_argument("--rho", type=float, default=0.1, help="error probability of the noisy oracle, in [0, 1]")
    parser.add_argument("--expert-rhos", type=float, nargs="+", default=[0.05, 0.2],
                        help="error probability of each expert (one expert per value)")
    parser.add_argument("--assignment", choices=["query", "run"], default="query",
                        help="experts drawn per query, or one expert for the whole run (the paper's setting)")
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--n-envs", type=int, default=4, help="envs stepped together")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    return parser.parse_args()


def train(args: argparse.Namespace, oracle: Oracle) -> HhP:
    model = HhP(
        "MlpPolicy",
        make_vec_env(args.env, n_envs=args.n_envs, wrapper_class=wrap_env, seed=args.seed),
        oracle=oracle,  # an Oracle instance instead of a name
        query_budget=args.budget,
        **SMALL_SETTINGS,
        seed=args.seed,
    )
    model.learn(args.steps)
    return model


def report(title: str, args: argparse.Namespace, model: HhP) -> None:
    rewards, _ = evaluate_policy(model, wrap_env(gym.make(args.env)), n_eval_episodes=args.eval_episodes,
                                 deterministic=False, return_episode_rewards=True, warn=False)
    by_annotator: dict[str, Counter] = {}
    for _, _, answer in model.store.answers_since(0):
        by_annotator.setdefault(answer.annotator, Counter())[answer.label.name] += 1
    print(f"== {title}")
    print(f"   success rate {np.mean(np.asarray(rewards) > 0):.2f}, {len(model.subgoals)} sub-goals, "
          f"{model.query_selector.used}/{model.query_selector.budget} questions, {len(model.predictor)} labels learnt")
    for annotator, labels in sorted(by_annotator.items()):
        print(f"   {annotator:28s} {dict(labels)}")


def main() -> None:
    args = parse_args()
    th.set_num_threads(args.threads)

    noisy = NoisyOracle(MiniGridScriptedOracle(), rho=args.rho, seed=args.seed)
    model = train(args, noisy)
    report(f"noisy scripted oracle, rho = {args.rho}", args, model)
    print(f"   {noisy.n_corrupted} of {noisy.n_answers} answers were made wrong")

    experts = [
        NoisyOracle(MiniGridScriptedOracle(name=f"expert-{i}"), rho=rho, seed=args.seed + i)
        for i, rho in enumerate(args.expert_rhos)
    ]
    team = MultiExpertOracle(experts, assignment=args.assignment, seed=args.seed)
    model = train(args, team)
    report(f"{len(experts)} experts (rho {args.expert_rhos}), assignment per {args.assignment}", args, model)
    for expert, rho in zip(experts, args.expert_rhos):
        print(f"   {expert.name}: rho {rho}, {expert.n_corrupted} of {expert.n_answers} answers wrong")


if __name__ == "__main__":
    main()
