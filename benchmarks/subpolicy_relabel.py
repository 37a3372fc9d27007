"""One HhP subpolicy learning one walk, "carrying nothing, facing key" on DoorKey-8x8, outside HhP, with the
ingredients HhP adds one at a time: relabelled experience from another behaviour, the lower bound on it, and
the curiosity bonus of eq. 6.

The subpolicy is built by :class:`~sb3_hhp.hierarchy.subpolicies.SubpolicySet` with the ``minigrid`` YAML entry's
``subpolicy_kwargs``. Its own tries start from fresh resets and give up after 50 steps, as in HhP. After each
own try, ``--relabel`` times as many steps of another behaviour (a random walk, forward three times as often as
each turn, reset every 200 steps) are stored as relabelled, off-policy transitions in one contiguous block, as
``HierarchicalEnv`` stores the steps of the other subpolicies, each counted as a learning tick
(``train_shared``). ``--alpha`` > 0 adds ``alpha`` times an RND bonus (one RND, updated after each block) to every
stored reward. Every 10,000 own steps the greedy subpolicy tries 50 fresh layouts (seeds 10,000+):

    python benchmarks/subpolicy_relabel.py --relabel 3 --seed 1 --alpha 0.5 --out result.json
"""

import argparse
import json
import pathlib
import time

import gymnasium as gym
import numpy as np
import torch as th
from minigrid.core.world_object import Key

from sb3_hhp.curiosity.rnd import RND
from sb3_hhp.goals.minigrid import MiniGridEgocentricObs
from sb3_hhp.hierarchy.subpolicies import SubpolicySet

GIVE_UP = 50
OTHER_EPISODE = 200


def facing_key(env: gym.Env) -> bool:
    base = env.unwrapped
    return isinstance(base.grid.get(*base.front_pos), Key) and base.carrying is None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--relabel", type=int, default=3, help="relabelled steps per own step")
    parser.add_argument("--steps", type=int, default=30_000, help="own steps")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--no-lower-bound", action="store_true")
    parser.add_argument("--alpha", type=float, default=0.0, help="weight of the RND bonus (eq. 6)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    th.set_num_threads(1)
    kwargs = {"gamma": 0.9, "n_steps": 8, "learning_rate": 1e-4, "batch_size": 32, "train_freq": 4,
              "target_update_interval": 10000, "learning_starts": 100, "policy_kwargs": {"net_arch": [64, 64]},
              "replay_buffer_kwargs": {"off_policy_lower_bound": not args.no_lower_bound}}
    own, other = (MiniGridEgocentricObs(gym.make("MiniGrid-DoorKey-8x8-v0")) for _ in range(2))
    subpolicy = SubpolicySet(own.observation_space, own.action_space, "MlpPolicy", kwargs, exploration_steps=5000,
                             seed=args.seed, device="cpu").add()
    rnd = RND(own.observation_space, device="cpu", seed=0) if args.alpha > 0 else None
    seen: list = []
    bonuses: list = []

    def bonus(obs: np.ndarray) -> float:
        if rnd is None:
            return 0.0
        seen.append(obs)
        value = float(rnd.intrinsic_reward(obs[None])[0])
        rnd.on_steps(1)
        bonuses.append(value)
        return args.alpha * value

    def evaluate(episodes: int = 50) -> float:
        reached = 0
        for episode in range(episodes):
            obs, _ = own.reset(seed=10_000 + episode)
            for _ in range(GIVE_UP):
                obs, _, terminated, truncated, _ = own.step(int(subpolicy.act(obs, deterministic=True)))
                if facing_key(own):
                    reached += 1
                    break
                if terminated or truncated:
                    break
        return reached / episodes

    rng = np.random.default_rng(0)
    other_obs, _ = other.reset(seed=999)
    other_steps = 0
    obs, _ = own.reset(seed=1)
    steps_in_try, episode, try_length = 0, 1, 0
    result: dict = dict(vars(args), evaluations=[])
    started = time.perf_counter()
    for step in range(1, args.steps + 1):
        action = subpolicy.act(obs)
        next_obs, _, terminated, truncated, _ = own.step(int(action))
        steps_in_try += 1
        done = facing_key(own)
        cut = (steps_in_try >= GIVE_UP or truncated) and not done and not terminated
        subpolicy.observe(obs, next_obs, action, float(done) + bonus(next_obs), done or terminated, timeout=cut)
        obs = next_obs
        try_length += 1
        if done or terminated or cut:
            episode += 1
            obs, _ = own.reset(seed=episode)
            steps_in_try = 0
            block = args.relabel * try_length
            for k in range(block):  # another behaviour's steps, contiguous, as HierarchicalEnv relabels them
                other_action = rng.choice([0, 1, 2, 2, 2])
                other_next, _, other_terminated, other_truncated, _ = other.step(int(other_action))
                other_steps += 1
                reached = facing_key(other)
                end = other_truncated or other_steps >= OTHER_EPISODE or k == block - 1
                subpolicy.store(other_obs, other_next, np.asarray(other_action), float(reached) + bonus(other_next),
                                reached or other_terminated, timeout=end and not reached, off_policy=True)
                subpolicy.learn_step()
                other_obs = other_next
                if reached or other_terminated or other_truncated or other_steps >= OTHER_EPISODE:
                    other_obs, _ = other.reset(seed=int(rng.integers(1 << 30)))
                    other_steps = 0
            try_length = 0
            if rnd is not None and seen:
                rnd.update(np.stack(seen))
                seen.clear()
        if step % 10_000 == 0:
            evaluation = dict(own_steps=step, greedy_success=evaluate(),
                              mean_bonus=float(args.alpha * np.mean(bonuses[-5000:])) if bonuses else 0.0,
                              seconds=round(time.perf_counter() - started, 1))
            result["evaluations"].append(evaluation)
            print(json.dumps(evaluation), flush=True)
    if args.out:
        pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.out).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
