"""Does HhP's pick-up subpolicy pick the key up when it faces it? The Q-values of the subpolicy for
"carrying key, facing empty" in states where the agent stands in front of the key, on fresh layouts.

A pick-up is one action away there, so ``Q(pickup)`` should be the largest value, by a margin of about
``1 - gamma`` over the no-op "done" (whose next state is the same state). The probe trains HhP (or loads a
model saved by ``doorkey.py --save``) and prints, per layout, the Q-values and whether pick-up is the argmax:

    python benchmarks/pickup_probe.py --steps 40000 --seed 101 --hhp-kwargs "$K" --out benchmarks/results/pickup_probe/K.json
    python benchmarks/pickup_probe.py --load path/to/model.zip --out ...

Layouts: seeds 30_000 + i (never a training or final evaluation seed).
"""

import argparse
import json
import pathlib

import gymnasium as gym
import numpy as np
import torch as th
from minigrid.core.actions import Actions

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env

PICKUP_GOAL = "carrying key, facing empty"


def facing_key(env: gym.Env, seed: int) -> np.ndarray:
    """Reset on ``seed`` and put the agent on a free cell next to the key, facing it."""
    env.reset(seed=seed)
    base = env.unwrapped
    kx, ky = next((x, y) for x in range(base.width) for y in range(base.height)
                  if base.grid.get(x, y) is not None and base.grid.get(x, y).type == "key")
    for direction, (dx, dy) in enumerate([(1, 0), (0, 1), (-1, 0), (0, -1)]):
        if base.grid.get(kx - dx, ky - dy) is None:
            base.agent_pos, base.agent_dir = (kx - dx, ky - dy), direction
            return env.observation(None)
    raise RuntimeError(f"no free cell next to the key on seed {seed}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MiniGrid-DoorKey-8x8-v0")
    parser.add_argument("--steps", type=int, default=40_000)
    parser.add_argument("--seed", type=int, default=101)
    parser.add_argument("--hhp-kwargs", default="{}", help="JSON dict of HhP keyword arguments")
    parser.add_argument("--load", default=None, help="probe a saved model instead of training one")
    parser.add_argument("--layouts", type=int, default=20)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    th.set_num_threads(1)
    if args.load:
        model = HhP.load(args.load, env=gym.make(args.env))
    else:
        model = HhP("MlpPolicy", gym.make(args.env), oracle="scripted", query_budget=100, seed=args.seed,
                    query_horizon=200_000, **json.loads(args.hhp_kwargs))
        model.learn(args.steps)
    names = [model.goal_space.describe(goal.key) for goal in model.subgoals]
    if PICKUP_GOAL not in names:
        raise SystemExit(f"no {PICKUP_GOAL!r} sub-goal was found; sub-goals: {names}")
    subpolicy = model.subpolicies.policy(names.index(PICKUP_GOAL))  # the SB3 DQNPolicy view
    env = wrap_env(gym.make(args.env))
    rows = []
    for i in range(args.layouts):
        obs = facing_key(env, 30_000 + i)
        with th.no_grad():
            q = subpolicy.q_net(th.as_tensor(obs[None], device=subpolicy.device)).detach().cpu().numpy()[0]
        rows.append(dict(seed=30_000 + i, q=[round(float(v), 3) for v in q], pickup_is_argmax=bool(q.argmax() == Actions.pickup),
                         margin_over_done=round(float(q[Actions.pickup] - q[Actions.done]), 3)))
        print(rows[-1], flush=True)
    result = dict(env=args.env, seed=args.seed, steps=int(model.num_timesteps), load=args.load,
                  hhp_kwargs=json.loads(args.hhp_kwargs), gamma=model.subpolicies.gamma,
                  pickup_is_argmax=float(np.mean([row["pickup_is_argmax"] for row in rows])),
                  mean_margin_over_done=float(np.mean([row["margin_over_done"] for row in rows])), layouts=rows)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(json.dumps({k: v for k, v in result.items() if k != "layouts"}, indent=2))


if __name__ == "__main__":
    main()
