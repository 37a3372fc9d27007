"""Train HhP on a MiniGrid task with the scripted oracle, then evaluate it.

The scripted oracle knows the task (it plans a shortest way to the goal on the real grid) and
answers the questions HhP asks about its least confident sub-goal choices. The script prints the
success rate over evaluation episodes, the questions asked out of the budget, and the sub-goals
that curiosity-driven discovery found.

    python examples/train_minigrid.py                      # Empty-Random-5x5, 8,000 steps (about a minute)
    python examples/train_minigrid.py --env MiniGrid-DoorKey-8x8-v0 --steps 300000 --n-envs 8 --budget 100 --max-subgoal-steps 50
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
from small_settings import SMALL_ENV, SMALL_SETTINGS


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default=SMALL_ENV, help="a MiniGrid env id")
    parser.add_argument("--steps", type=int, default=8_000, help="training length in primitive env steps")
    parser.add_argument("--budget", type=int, default=20, help="questions the oracle may be asked over training")
    parser.add_argument("--eval-episodes", type=int, default=30, help="episodes of the final evaluation")
    parser.add_argument("--deterministic", action="store_true",
                        help="evaluate the greedy policy (default: stochastic, as RL Zoo evaluates MiniGrid)")
    parser.add_argument("--max-subgoal-steps", type=int, default=30, help="primitive steps before a sub-goal gives up")
    parser.add_argument("--n-envs", type=int, default=1, help="envs stepped together")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save", default=None, help="save the trained model to this path (.zip)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--verbose", type=int, default=0, help="1 prints SB3's training logs")
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    th.set_num_threads(args.threads)
    model = HhP(
        "MlpPolicy",
        make_vec_env(args.env, n_envs=args.n_envs, wrapper_class=wrap_env, seed=args.seed),
        oracle="scripted",
        query_budget=args.budget,
        **{**SMALL_SETTINGS, "max_subgoal_steps": args.max_subgoal_steps},
        seed=args.seed,
        verbose=args.verbose,
    )
    model.learn(args.steps)

    rewards, lengths = evaluate_policy(
        model, wrap_env(gym.make(args.env)), n_eval_episodes=args.eval_episodes, deterministic=args.deterministic,
        return_episode_rewards=True, warn=False,
    )
    successes = np.asarray(rewards) > 0
    print(f"env: {args.env}, {model.num_timesteps} primitive steps")
    print(f"success rate: {successes.mean():.2f} over {len(rewards)} episodes (mean length {np.mean(lengths):.0f})")
    answers = Counter(answer.label.name for _, _, answer in model.store.answers_since(0))
    print(f"queries: {model.query_selector.used} of {model.query_selector.budget} asked; answers {dict(answers)}")
    print(f"sub-goals ({len(model.subgoals)}):")
    for goal_id, goal in enumerate(model.subgoals):
        success_rate = model.subpolicies.success_rate(goal_id)
        rate = "n/a" if success_rate is None else f"{success_rate:.2f}"
        print(f"  {goal_id:2d}  {model.goal_space.describe(goal.key):45s} found at step {goal.found_at:6d}"
              f"  ({goal.source}), reached {rate} of recent tries")
    if args.save:
        model.save(args.save)
        print(f"saved to {args.save}")


if __name__ == "__main__":
    main()
