"""Evaluate a saved HhP model on fresh seeds, deterministic and stochastic:

    python benchmarks/evaluate_saved.py PATH.zip --env MiniGrid-DoorKey-5x5-v0 --offset 10101 --out result.json

``--offset``: the first evaluation seed (``sb3_hhp.train`` uses 10_000 + seed, ``doorkey.py`` 10_000).
"""

import argparse
import json
import pathlib
import sys

import gymnasium as gym
import torch as th

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from doorkey import evaluate  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("path")
    parser.add_argument("--env", required=True)
    parser.add_argument("--offset", type=int, default=10_000)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    th.set_num_threads(1)
    env = wrap_env(gym.make(args.env))
    model = HhP.load(args.path, env=env)
    result = dict(path=args.path, env=args.env, total_timesteps=int(model.num_timesteps), offset=args.offset,
                  deterministic=evaluate(model, env, args.episodes, True, args.offset),
                  stochastic=evaluate(model, env, args.episodes, True, args.offset, deterministic=False))
    print(json.dumps(result, indent=2))
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
