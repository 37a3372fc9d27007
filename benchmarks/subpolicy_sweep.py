"""Subpolicy learner variants on one sub-goal task ("carrying nothing, facing the key", DoorKey-8x8,
eq. 5's reward, 50-step give-up): which learner settings make a subpolicy competent, before HhP as a
whole is run. Each call trains one variant on one (tuning) seed and appends its evaluations (greedy and
epsilon-greedy success on seeds 30_000 + i, beside a random policy) to a JSON-lines file:

    python benchmarks/subpolicy_sweep.py --variant n8 --steps 40000 --out benchmarks/results/subpolicy/sweep.jsonl
    python benchmarks/subpolicy_sweep.py --report benchmarks/results/subpolicy/sweep.jsonl --plot sweep.png

``--variant`` names an entry of :data:`VARIANTS` (learner keyword arguments over the subpolicy defaults,
an observation encoding, and how a give-up is stored).
"""

import argparse
import json
import pathlib
import sys
import time
from collections import defaultdict
from typing import Optional

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3 import DQN
from stable_baselines3.common.callbacks import BaseCallback

from sb3_hhp.dqn.dqn import DoubleDQN
from sb3_hhp.goals import wrap_env
from sb3_hhp.goals.minigrid import MAX_ENCODING
from sb3_hhp.hierarchy.subpolicies import default_subpolicy_kwargs

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from subpolicy_nstep import FACING_KEY, RandomPolicy, ReachSubgoal, success_rate  # noqa: E402

SB3_LIKE = dict(n_steps=1, learning_rate=1e-4, batch_size=32, train_freq=4, target_update_interval=10_000,
                learning_starts=100, policy_kwargs=dict(net_arch=[64, 64]))
#: name -> (learner kwargs over the defaults, observation encoding, give-up stored as a timeout)
VARIANTS: dict[str, tuple[dict, str, bool]] = {
    "n1": (dict(n_steps=1), "raw", False),
    "n8": (dict(n_steps=8), "raw", False),
    "n8_scaled": (dict(n_steps=8), "scaled", False),
    "n8_onehot": (dict(n_steps=8), "onehot", False),
    "n8_lr1e-4": (dict(n_steps=8, learning_rate=1e-4), "raw", False),
    "n8_lr3e-4": (dict(n_steps=8, learning_rate=3e-4), "raw", False),
    "n8_uniform": (dict(n_steps=8, prioritized_replay=False), "raw", False),
    "n8_target1000": (dict(n_steps=8, target_update_interval=1000), "raw", False),
    "n8_batch32": (dict(n_steps=8, batch_size=32), "raw", False),
    "n8_eps0.2": (dict(n_steps=8, exploration_final_eps=0.2), "raw", False),
    "n8_giveup_timeout": (dict(n_steps=8), "raw", True),
    "n8_gamma0.95": (dict(n_steps=8, gamma=0.95), "raw", False),
    "n8_net64": (dict(n_steps=8, policy_kwargs=dict(net_arch=[64, 64])), "raw", False),
    "n8_grad2": (dict(n_steps=8, gradient_steps=2), "raw", False),
    "n8_scaled_lr3e-4_timeout": (dict(n_steps=8, learning_rate=3e-4), "scaled", True),
    "sb3_dqn": (dict(), "raw", False),  # SB3's DQN with its own defaults, for reference
    "sb3_dqn_gamma0.95": (dict(gamma=0.95), "raw", False),
    # the subpolicy learner (Double DQN + PER) with SB3 DQN's defaults: fewer, smaller, slower updates
    "sb3like": (SB3_LIKE, "raw", False),
    "sb3like_uniform": ({**SB3_LIKE, "prioritized_replay": False}, "raw", False),
    "sb3like_n8": ({**SB3_LIKE, "n_steps": 8}, "raw", False),
    "sb3like_target1000": ({**SB3_LIKE, "target_update_interval": 1000}, "raw", False),
    "sb3like_net256": ({**SB3_LIKE, "policy_kwargs": dict(net_arch=[256, 256])}, "raw", False),
    "sb3like_gamma0.95": ({**SB3_LIKE, "gamma": 0.95}, "raw", False),
}


class Encode(gym.ObservationWrapper):
    """The egocentric grid as floats: ``scaled`` divides the codes by their maximum, ``onehot`` gives
    one channel per object, colour and state value."""

    def __init__(self, env: gym.Env, how: str) -> None:
        super().__init__(env)
        self.how = how
        shape = env.observation_space.shape
        depth = 3 if how == "scaled" else 3 * (MAX_ENCODING + 1)
        self.observation_space = gym.spaces.Box(0.0, 1.0, (shape[0], shape[1], depth), np.float32)

    def observation(self, obs: np.ndarray) -> np.ndarray:
        if self.how == "scaled":
            return obs.astype(np.float32) / MAX_ENCODING
        eye = np.eye(MAX_ENCODING + 1, dtype=np.float32)
        return eye[obs].reshape(obs.shape[0], obs.shape[1], -1)


class GiveUpAsTimeout(gym.Wrapper):
    """Store the 50-step give-up as a time limit (bootstrapped) rather than a terminal state."""

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if terminated and not info["is_success"] and self.env.t >= self.env.max_steps:
            terminated, truncated = False, True
        return obs, reward, terminated, truncated, info


def report(path: str, plot: Optional[str]) -> None:
    """A Markdown table (greedy / epsilon-greedy success, mean over seeds, at each evaluation) and a plot."""
    rows = [json.loads(line) for line in pathlib.Path(path).read_text().splitlines() if line.strip()]
    runs: dict[str, dict[int, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for row in rows:
        runs[row["variant"]][row["timesteps"]].append(row)
    steps = sorted({row["timesteps"] for row in rows})
    print("| variant | seeds | " + " | ".join(f"{t // 1000}k" for t in steps) + " |")
    print("| --- | --- | " + " | ".join("---" for _ in steps) + " |")
    for variant, by_step in sorted(runs.items()):
        seeds = sorted({row["seed"] for rows_at in by_step.values() for row in rows_at})
        cells = [f"{np.mean([r['greedy'] for r in by_step[t]]):.2f} / {np.mean([r['epsilon_greedy'] for r in by_step[t]]):.2f}"
                 if t in by_step else "" for t in steps]
        print(f"| {variant} | {','.join(map(str, seeds))} | " + " | ".join(cells) + " |")
    randoms = {(row["seed"], row["random"]) for row in rows}
    print(f"\nrandom policy: {np.mean([r for _, r in randoms]):.2f} (mean over seeds)")
    if plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(8, 4.5))
        for variant, by_step in sorted(runs.items()):
            xs = sorted(by_step)
            ax.plot(xs, [np.mean([r["greedy"] for r in by_step[t]]) for t in xs], marker="o", label=variant)
        ax.axhline(np.mean([r for _, r in randoms]), color="k", linestyle="--", label="random policy")
        ax.set_xlabel("subpolicy steps")
        ax.set_ylabel("greedy success (fresh seeds)")
        ax.set_title("one subpolicy: carrying nothing, facing the key (DoorKey-8x8)")
        ax.legend(fontsize=6, ncol=2)
        fig.tight_layout()
        fig.savefig(plot, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--report", default=None, help="summarise this JSON-lines file instead of training")
    parser.add_argument("--plot", default=None, help="with --report: write a plot here (PNG)")
    parser.add_argument("--variant", choices=sorted(VARIANTS))
    parser.add_argument("--env", default="MiniGrid-DoorKey-8x8-v0")
    parser.add_argument("--steps", type=int, default=40_000)
    parser.add_argument("--eval-every", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--out")
    args = parser.parse_args()
    if args.report:
        report(args.report, args.plot)
        return
    if args.variant is None or args.out is None:
        parser.error("--variant and --out are needed to train (or --report to summarise)")
    th.set_num_threads(1)
    overrides, encoding, timeout = VARIANTS[args.variant]
    reach = ReachSubgoal(wrap_env(gym.make(args.env)), FACING_KEY)
    env: gym.Env = GiveUpAsTimeout(reach) if timeout else reach
    if encoding != "raw":
        env = Encode(env, encoding)
    if args.variant.startswith("sb3_dqn"):
        model = DQN("MlpPolicy", env, seed=args.seed, device="cpu", **overrides)
    else:
        kwargs = default_subpolicy_kwargs(env.action_space)
        kwargs.update(exploration_fraction=5_000 / args.steps, **overrides)
        model = DoubleDQN("MlpPolicy", env, seed=args.seed, device="cpu", **kwargs)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    random_rate = success_rate(RandomPolicy(env.action_space, args.seed), env, args.episodes, deterministic=False)
    started = time.time()

    def record() -> None:
        row = dict(variant=args.variant, env=args.env, seed=args.seed, timesteps=int(model.num_timesteps),
                   seconds=round(time.time() - started, 1), eval_episodes=args.episodes,
                   greedy=success_rate(model, env, args.episodes, deterministic=True),
                   epsilon_greedy=success_rate(model, env, args.episodes, deterministic=False), random=random_rate)
        with out.open("a") as handle:  # one short line per write: parallel runs can share the file
            handle.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)

    class Every(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps % args.eval_every == 0:
                record()
            return True

    model.learn(args.steps, callback=Every())


if __name__ == "__main__":
    main()
