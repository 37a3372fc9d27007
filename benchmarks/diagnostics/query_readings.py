"""How often does each reading of the confidence threshold (eq. 4 against t_qry) ask on a real run?

Trains HhP with the fixed threshold t_qry under three readings (linear head + std, sigmoid head +
std, sigmoid head + variance as eq. 4 is written) and the adaptive mode, and records the queries asked
and the spread of the confidences seen.

    python benchmarks/diagnostics/query_readings.py --env MiniGrid-DoorKey-5x5-v0 --steps 8000 --out benchmarks/results/query_readings.json
"""

import argparse
import json
import pathlib

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_hhp import HhP

#: each reading: the query mode, and the predictor's head and spread
READINGS = {
    "fixed, linear head, std": ("fixed", dict(head="linear", spread="std")),
    "fixed, sigmoid head, std": ("fixed", dict(head="sigmoid", spread="std")),
    "fixed, sigmoid head, var (eq. 4 as written)": ("fixed", dict(head="sigmoid", spread="var")),
    "adaptive, linear head, std (default)": ("adaptive", dict(head="linear", spread="std")),
}


class ConfidenceRecorder(BaseCallback):
    """Keeps every confidence the query callback computed."""

    def __init__(self) -> None:
        super().__init__()
        self.values: list[float] = []
        self._last = None

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        current = self.model.last_confidences
        if current is not self._last and len(current):
            self.values.extend(float(c) for c in current)
            self._last = current


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MiniGrid-DoorKey-5x5-v0")
    parser.add_argument("--steps", type=int, default=8000)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--t-qry", type=float, default=0.26)
    parser.add_argument("--budget", type=int, default=100)
    parser.add_argument("--out", default="benchmarks/results/query_readings.json")
    args = parser.parse_args()
    th.set_num_threads(1)
    rows = []
    for name, (mode, predictor) in READINGS.items():
        model = HhP("MlpPolicy", gym.make(args.env), oracle="scripted", query_budget=args.budget, seed=args.seed,
                    query_kwargs=dict(mode=mode, threshold=args.t_qry), predictor_kwargs=dict(n_masks=100, **predictor))
        recorder = ConfidenceRecorder()
        model.learn(args.steps, callback=recorder)
        values = np.asarray(recorder.values) if recorder.values else np.zeros(1)
        rows.append(dict(reading=name, steps=int(model.num_timesteps), queries=model.query_selector.used,
                         budget=args.budget, t_qry=args.t_qry, confidence_median=float(np.median(values)),
                         confidence_p95=float(np.quantile(values, 0.95)), confidence_max=float(values.max())))
        print(json.dumps(rows[-1]), flush=True)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(env=args.env, seed=args.seed, rows=rows), indent=2))


if __name__ == "__main__":
    main()
