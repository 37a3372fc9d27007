"""Are the subpolicies or the meta-controller the bottleneck? Train HhP, then let the scripted plan choose
the sub-goals (the first milestone of an optimal plan that is in the sub-goal set) and run HhP's own
subpolicies: the episode success says what the subpolicies can do under a perfect meta-controller.

    python benchmarks/scripted_meta.py --env MiniGrid-DoorKey-5x5-v0 --steps 30000 --seed 101

Evaluation seeds 20_000 + i (the tuning range; the final benchmark evaluates on 10_000 + i).
"""

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env
from sb3_hhp.goals.minigrid import EMPTY
from sb3_hhp.oracles.scripted import plan_keys

sys.path.insert(0, str(Path(__file__).parent))
from doorkey import evaluate  # noqa: E402


def scripted_meta(model: HhP, env_id: str, episodes: int, deterministic: bool) -> dict:
    goal_space, keys = model.goal_space, [goal.key for goal in model.subgoals]
    env = wrap_env(gym.make(env_id))
    chosen, reached, successes = Counter(), Counter(), 0
    for episode in range(episodes):
        obs, _ = env.reset(seed=20_000 + episode)
        done, total = False, 0.0
        while not done:
            info = goal_space.privileged(env)
            plan = plan_keys(info, goal_space) or []
            carried = info["carrying"][0] if info["carrying"] else EMPTY
            milestones = [key for key in plan if key in keys and goal_space.is_milestone(key, carried)]
            goal = keys.index(milestones[0]) if milestones else 0
            name = goal_space.describe(keys[goal])
            chosen[name] += 1
            for _ in range(model.max_subgoal_steps):
                obs, reward, terminated, truncated, _ = env.step(model.subpolicies.act([goal], obs[None], deterministic=deterministic)[0])
                total += float(reward)
                done = terminated or truncated
                if goal_space.achieved(goal_space.terminal_key(obs, float(reward), terminated), keys[goal]):
                    reached[name] += 1
                    break
                if done:
                    break
        successes += total > 0
    return dict(success_rate=successes / episodes, subgoals={name: f"{reached[name]}/{n}" for name, n in chosen.items()})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MiniGrid-DoorKey-5x5-v0")
    parser.add_argument("--steps", type=int, default=30_000)
    parser.add_argument("--seed", type=int, default=101)
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--hhp-kwargs", default="{}", help="JSON dict of HhP keyword arguments")
    args = parser.parse_args()
    th.set_num_threads(1)
    kwargs = {"query_horizon": 200_000, **json.loads(args.hhp_kwargs)}
    model = HhP("MlpPolicy", gym.make(args.env), oracle="scripted", query_budget=100, seed=args.seed, n_masks=100, **kwargs)
    model.learn(args.steps)
    env = wrap_env(gym.make(args.env))
    result = dict(
        env=args.env, seed=args.seed, steps=model.num_timesteps, hhp_kwargs=json.loads(args.hhp_kwargs),
        hhp_deterministic=evaluate(model, env, args.episodes, True, 20_000)["success_rate"],
        hhp_stochastic=evaluate(model, env, args.episodes, True, 20_000, deterministic=False)["success_rate"],
        scripted_meta_stochastic=scripted_meta(model, args.env, args.episodes, deterministic=False),
        scripted_meta_deterministic=scripted_meta(model, args.env, args.episodes, deterministic=True),
        subgoal_success={model.goal_space.describe(goal.key): sub.success_rate
                         for goal, sub in zip(model.subgoals, model.subpolicies.policies)},
    )
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
