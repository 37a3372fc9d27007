"""Speed: HhP's primitive env steps per second against plain SB3 DQN (an update every step, batch 128)
on the same observations, in one run, plus a profile of where HhP's time goes.

    python benchmarks/speed.py --env MiniGrid-DoorKey-8x8-v0 --steps 20000 --out benchmarks/results/speed.json

``--hhp-kwargs`` times another HhP configuration (JSON, as ``doorkey.py``), e.g. the DoorKey benchmark's.
"""

import argparse
import cProfile
import json
import pathlib
import pstats
import time

import gymnasium as gym
import torch as th
from stable_baselines3 import DQN

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MiniGrid-DoorKey-8x8-v0")
    parser.add_argument("--steps", type=int, default=20_000, help="primitive env steps per algorithm")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="benchmarks/results/speed.json")
    parser.add_argument("--hhp-kwargs", default="{}", help="JSON dict of HhP keyword arguments (default: the class defaults)")
    args = parser.parse_args()
    th.set_num_threads(1)

    # plain SB3 DQN: an update every step, batch 128, the same 256x256 MLP, the same observations
    dqn = DQN("MlpPolicy", wrap_env(gym.make(args.env)), learning_starts=500, batch_size=128, train_freq=1,
              gradient_steps=1, buffer_size=50_000, policy_kwargs=dict(net_arch=[256, 256]), seed=args.seed)
    start = time.perf_counter()
    dqn.learn(args.steps)
    dqn_fps = args.steps / (time.perf_counter() - start)

    hhp_kwargs = json.loads(args.hhp_kwargs)
    hhp = HhP("MlpPolicy", gym.make(args.env), oracle="scripted", query_budget=100, seed=args.seed, **hhp_kwargs)
    start = time.perf_counter()
    hhp.learn(args.steps)
    hhp_fps = hhp.num_timesteps / (time.perf_counter() - start)
    num_subgoals = len(hhp.subgoals)  # at the end of the timed run

    # where the time goes: a separate, profiled continuation (the profiler slows the timed run otherwise)
    profiler = cProfile.Profile()
    profiler.enable()
    hhp.learn(args.steps // 4, reset_num_timesteps=False)
    profiler.disable()

    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.with_suffix(".profile.txt"), "w") as handle:
        pstats.Stats(profiler, stream=handle).sort_stats("cumulative").print_stats(40)
    result = dict(env=args.env, steps=args.steps, seed=args.seed, dqn_fps=round(dqn_fps, 1),
                  hhp_fps=round(hhp_fps, 1), ratio=round(hhp_fps / dqn_fps, 3), threads=1, hhp_kwargs=hhp_kwargs,
                  num_subgoals=num_subgoals)
    out.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
