"""HhP on a MiniGrid task, evaluated after each of CHUNKS equal `learn` calls (deterministic and stochastic,
30 episodes on the tuning seeds 20_000 + i), with the paper's sigma(R_p) ("paper") or the bonus divided by the
running std of the bonus itself ("bonusstd"):

    python benchmarks/bonus_scale_nstep.py paper MiniGrid-DoorKey-5x5-v0 40000 101 2 '{"subpolicy_kwargs": {"n_steps": 8}}'
    python benchmarks/bonus_scale_nstep.py bonusstd MiniGrid-DoorKey-5x5-v0 40000 101 2 '{"subpolicy_kwargs": {"n_steps": 8}}'

The last argument is a JSON dict of HhP keyword arguments.
"""
import json
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th

sys.path.insert(0, str(Path(__file__).parent))
from doorkey import evaluate  # noqa: E402

from sb3_hhp import HhP  # noqa: E402
from sb3_hhp.goals import wrap_env  # noqa: E402


class BonusStd:
    """sigma = running std of the per-step bonus itself (not of its discounted returns)."""

    def __init__(self) -> None:
        self.n, self.mean, self.m2 = 0, 0.0, 0.0

    def update(self, bonuses) -> None:
        for x in np.ravel(bonuses):
            self.n += 1
            delta = x - self.mean
            self.mean += delta / self.n
            self.m2 += delta * (x - self.mean)

    @property
    def sigma(self) -> float:
        return float(np.sqrt(self.m2 / self.n)) if self.n > 1 and self.m2 > 0 else 1.0

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


def main() -> None:
    variant, env_id, steps, seed, chunks = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
    kwargs = json.loads(sys.argv[6]) if len(sys.argv) > 6 else {}
    th.set_num_threads(1)
    model = HhP("MlpPolicy", gym.make(env_id), oracle="scripted", query_budget=100, seed=seed, query_horizon=steps,
                n_masks=100, **kwargs)
    if variant == "bonusstd":
        model.return_normalizer = BonusStd()
    env = wrap_env(gym.make(env_id))
    start = time.time()
    for chunk in range(chunks):
        model.learn(steps // chunks, reset_num_timesteps=(chunk == 0))
        det = evaluate(model, env, 30, True, 20_000)["success_rate"]
        stoch = evaluate(model, env, 30, True, 20_000, deterministic=False)["success_rate"]
        print(variant, dict(t=model.num_timesteps, det=det, stoch=stoch, sigma=round(model.return_normalizer.sigma, 3),
                            queries=model.query_selector.used, seconds=round(time.time() - start)), flush=True)
    print({model.goal_space.describe(goal.key): (model.subpolicies.success_rate(i), model.subpolicies.attempts[i])
           for i, goal in enumerate(model.subgoals)})


if __name__ == "__main__":
    main()
