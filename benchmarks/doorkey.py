"""MiniGrid DoorKey learning benchmark: HhP (scripted oracle) beside flat SB3 DQN and PPO, same step budget.

Each call trains one algorithm for one seed, then evaluates its deterministic policy on fresh
evaluation seeds (10_000 + i, never a training seed) and writes a JSON result:

    python benchmarks/doorkey.py --algo hhp --seed 0 --steps 500000 --out benchmarks/results/hhp_s0.json
    python benchmarks/doorkey.py --algo dqn --seed 0 --steps 500000 --out benchmarks/results/dqn_s0.json
    python benchmarks/doorkey.py --algo ppo --seed 0 --steps 500000 --out benchmarks/results/ppo_s0.json

HhP sees :class:`~sb3_hhp.goals.MiniGridEgocentricObs`; the flat baselines see the fully observed grid
(MiniGrid's ``FullyObsWrapper`` + ``ImgObsWrapper``) through an MLP. ``benchmarks/report.py`` gathers the
results into a table and a plot.
"""

import argparse
import json
import pathlib
import time

import gymnasium as gym
import numpy as np
import torch as th
from minigrid.wrappers import FullyObsWrapper, ImgObsWrapper
from stable_baselines3 import DQN, PPO
from stable_baselines3.common.callbacks import BaseCallback, EveryNTimesteps
from stable_baselines3.common.monitor import Monitor

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env

EVAL_SEED_OFFSET = 10_000


def flat_env(env_id: str) -> gym.Env:
    return Monitor(ImgObsWrapper(FullyObsWrapper(gym.make(env_id))))


def evaluate(model, env: gym.Env, episodes: int, hierarchical: bool, offset: int = EVAL_SEED_OFFSET,
             deterministic: bool = True) -> dict:
    """The policy (deterministic by default) on seeds offset + i: success rate and mean return."""
    returns, successes = [], []
    for episode in range(episodes):
        obs, _ = env.reset(seed=offset + episode)
        state, start, done, total = None, np.ones(1, dtype=bool), False, 0.0
        while not done:
            if hierarchical:
                action, state = model.predict(obs, state=state, episode_start=start, deterministic=deterministic)
            else:
                action, _ = model.predict(obs, deterministic=deterministic)
            obs, reward, terminated, truncated, _ = env.step(action)
            start = np.zeros(1, dtype=bool)
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
        successes.append(total > 0)
    return dict(success_rate=float(np.mean(successes)), mean_return=float(np.mean(returns)), eval_episodes=episodes)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", choices=["hhp", "dqn", "ppo"], required=True)
    parser.add_argument("--env", default="MiniGrid-DoorKey-8x8-v0")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=500_000)
    parser.add_argument("--query-budget", type=int, default=100)
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--eval-every", type=int, default=100_000, help="also evaluate every N steps (written as they come)")
    parser.add_argument("--eval-seed-offset", type=int, default=EVAL_SEED_OFFSET,
                        help="evaluation seeds start here (tuning runs use another range than the final runs)")
    parser.add_argument("--hhp-kwargs", default="{}",
                        help="JSON dict of HhP keyword arguments (variants); subpolicy_kwargs defaults to n_steps 8, as hhp.yml")
    parser.add_argument("--tag", default="", help="name of the variant in the results")
    parser.add_argument("--out", required=True)
    parser.add_argument("--save", default=None, help="also save the model here at every evaluation (HhP.load / DQN.load / PPO.load)")
    args = parser.parse_args()
    th.set_num_threads(1)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    result: dict = dict(algo=args.algo, tag=args.tag, env=args.env, seed=args.seed, eval_seed_offset=args.eval_seed_offset,
                        hhp_kwargs=json.loads(args.hhp_kwargs), evaluations=[])

    if args.algo == "hhp":
        model = HhP("MlpPolicy", gym.make(args.env), oracle="scripted", query_budget=args.query_budget, seed=args.seed,
                    query_horizon=args.steps, **{"subpolicy_kwargs": {"n_steps": 8}, **json.loads(args.hhp_kwargs)})
        eval_env = wrap_env(gym.make(args.env))
    elif args.algo == "dqn":
        model = DQN("MlpPolicy", flat_env(args.env), seed=args.seed)
        eval_env = flat_env(args.env)
    else:
        model = PPO("MlpPolicy", flat_env(args.env), seed=args.seed)
        eval_env = flat_env(args.env)
    hierarchical = args.algo == "hhp"
    started = time.perf_counter()

    def record() -> None:
        """Evaluate now and rewrite the JSON, so a run stopped early keeps what it measured."""
        train_seconds = time.perf_counter() - started - sum(e["eval_seconds"] for e in result["evaluations"])
        begin = time.perf_counter()
        evaluation = evaluate(model, eval_env, args.eval_episodes, hierarchical, args.eval_seed_offset)
        stochastic = evaluate(model, eval_env, args.eval_episodes, hierarchical, args.eval_seed_offset, deterministic=False)
        evaluation.update(stochastic_success_rate=stochastic["success_rate"], stochastic_mean_return=stochastic["mean_return"])
        result.update(total_timesteps=int(model.num_timesteps), train_seconds=round(train_seconds, 1),
                      fps=round(model.num_timesteps / max(train_seconds, 1e-9), 1), **evaluation)
        result["evaluations"].append(dict(timesteps=int(model.num_timesteps), eval_seconds=time.perf_counter() - begin,
                                          **evaluation))
        if hierarchical:  # each sub-goal: when it was found and its subpolicy's recent success rate, at this point
            result["evaluations"][-1]["subgoals"] = {
                model.goal_space.describe(goal.key): dict(found_at=goal.found_at, success=sub.success_rate)
                for goal, sub in zip(model.subgoals, model.subpolicies.policies)
            }
            result.update(queries_used=model.query_selector.used, query_budget=model.query_budget,
                          num_subgoals=len(model.subgoals),
                          subgoals=[model.goal_space.describe(goal.key) for goal in model.subgoals],
                          subgoal_success=[sub.success_rate for sub in model.subpolicies.policies])
        out.write_text(json.dumps(result, indent=2))
        if args.save:  # the model of the latest evaluation, so a run stopped early keeps it too
            model.save(args.save)
        print(json.dumps(result["evaluations"][-1]), flush=True)

    class Evaluate(BaseCallback):
        def _on_step(self) -> bool:
            record()
            return True

    # one learn call, so exploration and the query budget are paced over the whole run
    model.learn(args.steps, callback=EveryNTimesteps(args.eval_every, Evaluate()))
    if not result["evaluations"] or result["evaluations"][-1]["timesteps"] < args.steps:  # not evaluated at the end yet
        record()
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
