"""Which level's greed breaks a saved HhP model's deterministic policy: the meta-controller greedy or
stochastic, crossed with the subpolicies greedy or epsilon-greedy, on fresh layouts (seeds 10,000+); then the
greedy policy's first choices in a few episodes, with the meta-controller's Q-values of the choosable sub-goals:

    python benchmarks/greedy_levels.py PATH.zip --env MiniGrid-DoorKey-8x8-v0 --episodes 50 --out result.json
"""

import argparse
import json
import pathlib

import gymnasium as gym
import numpy as np
import torch as th

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env
from sb3_hhp.hierarchy.subpolicies import Subpolicy


def run_episode(model: HhP, env: gym.Env, seed: int, meta_deterministic: bool, trace: list | None = None) -> float:
    obs, _ = env.reset(seed=seed)
    state, start, done, total = None, np.ones(1, dtype=bool), False, 0.0
    while not done:
        action, state = model.predict(obs, state=state, episode_start=start, deterministic=meta_deterministic)
        if trace is not None and state[1][0] == 1 and len(trace) < 12:  # a choice was just made
            with th.no_grad():
                q_values = model.q_net(model.policy.obs_to_tensor(obs[None])[0]).cpu().numpy()[0]
            mask = model.action_mask(obs[None])[0]
            describe = model.goal_space.describe
            trace.append(dict(
                state=describe(model.goal_space.key(obs)), chosen=describe(model.subgoals[int(state[0][0])].key),
                q_values={describe(goal.key): round(float(q_values[i]), 3) for i, goal in enumerate(model.subgoals) if mask[i]},
            ))
        obs, reward, terminated, truncated, _ = env.step(action)
        start = np.zeros(1, dtype=bool)
        total += float(reward)
        done = terminated or truncated
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("path")
    parser.add_argument("--env", default="MiniGrid-DoorKey-8x8-v0")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--traces", type=int, default=2, help="greedy episodes whose first choices are written out")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    th.set_num_threads(1)
    model = HhP.load(args.path)
    env = wrap_env(gym.make(args.env))
    act = Subpolicy.act
    result: dict = dict(path=args.path, env=args.env, episodes=args.episodes, total_timesteps=int(model.num_timesteps),
                        success={})
    try:
        for meta_greedy in (True, False):
            for sub_greedy in (True, False):
                Subpolicy.act = lambda self, obs, deterministic=False, _greedy=sub_greedy: act(self, obs, deterministic=_greedy)
                wins = [run_episode(model, env, 10_000 + i, meta_greedy) > 0 for i in range(args.episodes)]
                name = f"meta {'greedy' if meta_greedy else 'stochastic'}, subpolicies {'greedy' if sub_greedy else 'epsilon-greedy'}"
                result["success"][name] = float(np.mean(wins))
                print(name, result["success"][name], flush=True)
    finally:
        Subpolicy.act = act
    result["greedy_traces"] = []
    for i in range(args.traces):
        trace: list = []
        solved = run_episode(model, env, 10_000 + i, True, trace) > 0
        result["greedy_traces"].append(dict(seed=10_000 + i, solved=bool(solved), choices=trace))
    print(json.dumps(result["greedy_traces"], indent=1))
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
