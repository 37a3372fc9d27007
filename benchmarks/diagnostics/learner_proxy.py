"""One sub-goal learner's settings tried alone: can a DQN with them learn to walk to an object of a MiniGrid room?

HhP's sub-goal learners must walk across a room to reach sub-goals such as "carrying nothing, facing key". Here one
SB3 DQN does only that: from the env's own start, a reward of 1 (and the end of the try) when the agent, empty
handed, faces an object of the given kind, a try cut after ``--max-steps`` steps (a sub-goal's give-up). It reads
the egocentric canvas the learners read and has their network, learning rate, batch, update rate, n-step returns,
discount and target interval (``sb3_hhp.hierarchy.learners.DEFAULT_SUBPOLICY_KWARGS``, then ``--gamma`` and
``--kwargs``), its epsilon falling to 0.05 over ``--exploration-steps`` steps; it has none of the shared replay's
prioritization, Double DQN or lower bound, and acts every step where a learner acts for part of them. So it tells
which settings let the skill be learned at all within a number of steps, cheaply (a few minutes a run), not how a
learner fares inside HhP. With ``--learner stacked`` the learner is HhP's own (``StackedDQN``, one sub-goal: its
prioritized shared replay, Double DQN, n-step returns and lower bound, ``--view``), acting on every step, so that
each of its parts can be switched off in ``--kwargs`` (``prioritized_replay_alpha: 0`` draws uniformly,
``double_q: false``, ``replay_buffer_kwargs: {"off_policy_lower_bound": false}``). With ``--learner hhp`` it is HhP
itself, the env's YAML entry with ``--hhp-kwargs`` over it, ``--n-envs`` envs (8), the one sub-goal "empty handed, facing the
object" handed in (``discovery="none"``, no preferences): the same learner inside the option loop, where a try that
reaches the object is followed by the next try from there, not from a fresh layout; ``--train-max-steps`` shortens
the training envs' episodes (MiniGrid's ``max_steps``). Its evaluation: HhP's ``predict`` (stochastic) from fresh
layouts, reached within ``--max-steps``.

At every quarter of ``--steps`` the greedy policy and the policy with epsilon 0.05 are evaluated on fresh layouts
(seeds 50,000+): the fraction of tries that reach the object; the greedy policy's also split by where the object was
at the try's start (within ``--radius`` cells of the agent, the larger of the two axes, or beyond).

    python benchmarks/diagnostics/learner_proxy.py --env MiniGrid-DoorKey-16x16-v0 --gamma 0.99 \\
        --kwargs '{"target_update_interval": 1000}' --seed 0 --out benchmarks/results/diagnostics/proxy.json
"""

import argparse
import json
import pathlib
import sys
import time
from typing import Any, Optional

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import torch as th
from minigrid.core.world_object import Ball, Box, Door, Key
from stable_baselines3 import DQN

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2]))
from benchmarks.diagnostics.choice_trace import nearest_distance  # noqa: E402
from benchmarks.speed import entry_kwargs  # noqa: E402
from sb3_hhp.goals import register_minigrid_tasks, wrap_env  # noqa: E402
from sb3_hhp.hierarchy.encoders import OneHotCodes, view_cells  # noqa: E402
from sb3_hhp.hierarchy.learners import DEFAULT_SUBPOLICY_KWARGS, StackedDQN  # noqa: E402

OBJECTS = {"key": Key, "door": Door, "ball": Ball, "box": Box}
#: the exploration schedule of SB3's DQN, which HhP's learners set with their own exploration_steps
SB3_SCHEDULE = ("exploration_fraction", "exploration_final_eps")


def faces(env: gym.Env, kind: type) -> bool:
    """Whether the agent of a MiniGrid env, carrying nothing, faces an object of class ``kind``."""
    base = env.unwrapped
    return base.carrying is None and isinstance(base.grid.get(*base.front_pos), kind)


class FaceObject(gym.Wrapper):
    """Reward 1 and the end of the try where the agent, carrying nothing, faces an object of class ``kind``; the try
    is cut after ``max_steps`` steps. ``info["is_success"]``: whether it was reached."""

    def __init__(self, env: gym.Env, kind: type, max_steps: int) -> None:
        super().__init__(env)
        self.kind, self.max_steps, self.steps = kind, int(max_steps), 0

    def reset(self, **kwargs: Any) -> Any:
        self.steps = 0
        return self.env.reset(**kwargs)

    def step(self, action: int) -> Any:
        obs, _, terminated, truncated, info = self.env.step(action)
        self.steps += 1
        reached = faces(self.env, self.kind)
        info["is_success"] = reached
        return obs, float(reached), bool(reached or terminated), bool(truncated or self.steps >= self.max_steps), info


class CenterCrop(gym.ObservationWrapper):
    """The ``size`` x ``size`` cells of the egocentric canvas around the agent (its centre)."""

    def __init__(self, env: gym.Env, size: int) -> None:
        super().__init__(env)
        space = env.observation_space
        self.cells = view_cells(space, size)  # the cells a sub-goal learner with view=size reads
        self.observation_space = gym.spaces.Box(0, int(space.high.max()), (size, size, space.shape[2]), space.dtype)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(observation[self.cells])


class OneHot(gym.ObservationWrapper):
    """The cells' codes as one-hot indicators of ``codes`` per channel, as the sub-goal learners read them with
    ``subgoal_learner_kwargs`` ``one_hot`` (:class:`OneHotCodes`), instead of the integer codes."""

    def __init__(self, env: gym.Env, codes: list) -> None:
        super().__init__(env)
        self.codes = OneHotCodes(env.observation_space, codes)
        shape = env.observation_space.shape
        self.observation_space = gym.spaces.Box(0.0, 1.0, (*shape[:2], self.codes.n_indicators), np.float32)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return self.codes.encode(observation)


def make_env(env_id: str, kind: str, max_steps: int, crop: int = 0, one_hot: Optional[list] = None) -> gym.Env:
    env = wrap_env(gym.make(env_id))
    env = CenterCrop(env, crop) if crop else env
    return FaceObject(OneHot(env, one_hot) if one_hot else env, OBJECTS[kind], max_steps)


def start_distance(env: gym.Env, kind: type) -> int:
    """Cells (the larger of the two axes) from the agent of a MiniGrid env to the nearest object of class ``kind``."""
    grid = env.unwrapped.grid
    return nearest_distance(env, np.array([[isinstance(grid.get(x, y), kind) for y in range(grid.height)]
                                           for x in range(grid.width)]))


def tries(env: FaceObject, episodes: int, act: Any, seed: int = 50_000) -> list[tuple[int, bool]]:
    """``episodes`` fresh tries (seeds ``seed``, ``seed + 1``, ...) acting with ``act(obs, first)`` (``first``: the
    try's first step): each one's :func:`start_distance` and whether it reached the object."""
    results = []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        distance = start_distance(env, env.kind)
        done, info, first = False, {}, True
        while not done:
            obs, _, terminated, truncated, info = env.step(act(obs, first))
            done, first = terminated or truncated, False
        results.append((distance, bool(info["is_success"])))
    return results


def reached_share(results: list[tuple[int, bool]]) -> float:
    """The fraction of :func:`tries` ``results`` that reached the object."""
    return float(np.mean([reached for _, reached in results]))


def success_rate(env: FaceObject, episodes: int, act: Any, seed: int = 50_000) -> float:
    """The fraction of :func:`tries` that reach the object."""
    return reached_share(tries(env, episodes, act, seed))


def split_at(results: list[tuple[int, bool]], radius: int) -> dict[str, Any]:
    """:func:`tries` split at ``radius`` cells (the view a learner reads: ``view // 2``): how many started with the
    object within it and beyond it, and the fraction of each that reached it (None: no such try)."""
    split: dict[str, Any] = {}
    for name, part in (("within", [t for t in results if t[0] <= radius]), ("beyond", [t for t in results if t[0] > radius])):
        split[f"tries_{name}"] = len(part)
        split[f"reached_{name}"] = reached_share(part) if part else None
    return split


def epsilon_greedy(model: Any, n_actions: int, epsilon: float, seed: int = 50_000) -> Any:
    """``act`` for :func:`success_rate`: ``model``'s greedy action, a random one with probability ``epsilon``."""
    rng = np.random.default_rng(seed)

    def act(obs: np.ndarray, first: bool) -> int:
        explore = rng.random() < epsilon
        return int(rng.integers(n_actions)) if explore else int(model.predict(obs, deterministic=True)[0])

    return act


def hhp_stochastic(model: Any) -> Any:
    """``act`` for :func:`success_rate`: HhP's ``predict`` (stochastic), its option state kept within a try."""
    state = None

    def act(obs: np.ndarray, first: bool) -> int:
        nonlocal state
        action, state = model.predict(obs, state=None if first else state, episode_start=np.array([first]),
                                      deterministic=False)
        return int(np.asarray(action).reshape(-1)[0])

    return act


class StackedAgent:
    """HhP's sub-goal learners (``StackedDQN``) with one sub-goal, "reached", pursued on every step: ``learn`` and
    ``predict`` as the SB3 DQN of the default mode has them."""

    def __init__(self, env: FaceObject, settings: dict[str, Any], exploration_steps: int, view: int, seed: int,
                 fresh_after_success: bool = True) -> None:
        kwargs = {key: value for key, value in settings.items() if key not in SB3_SCHEDULE}
        self.env, self.num_timesteps, self.fresh_after_success = env, 0, fresh_after_success
        self.learners = StackedDQN(env.observation_space, env.action_space, lambda key, goal: key == goal,
                                   subpolicy_kwargs=kwargs, exploration_steps=exploration_steps, train_shared=True,
                                   seed=seed, view=view or None, alpha=0.0)
        self.learners.add("reached")
        self.obs, _ = env.reset(seed=seed)

    def learn(self, steps: int, reset_num_timesteps: bool = False) -> None:
        goal = np.zeros(1, dtype=np.int64)
        for _ in range(steps):
            action = self.learners.act(goal, self.obs[None])
            next_obs, _, terminated, truncated, info = self.env.step(int(action[0]))
            reached = info["is_success"]
            self.learners.observe(self.obs[None], action, next_obs[None], ["reached" if reached else "not"],
                                  np.array([terminated and not reached]), np.array([False]),
                                  np.array([truncated and not terminated]), goal, np.zeros(1, np.float32))
            self.num_timesteps += 1
            if terminated and reached and not self.fresh_after_success:  # the next try from where this one ended
                self.env.steps = 0
            elif terminated or truncated:
                next_obs, _ = self.env.reset()
            self.obs = next_obs

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> tuple[np.ndarray, None]:
        return self.learners.act(np.zeros(1, dtype=np.int64), obs[None], deterministic=deterministic)[0], None


def handed_in_subgoal(env: gym.Env, kind: type, seed: int = 0) -> np.ndarray:
    """An observation of the env (wrapped) in which the agent, empty handed, faces an object of class ``kind``
    (random moves until it does)."""
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    for _ in range(1_000_000):
        if faces(env, kind):
            return obs
        obs, _, terminated, truncated, _ = env.step(int(rng.integers(3)))  # turns and moves only
        if terminated or truncated:
            obs, _ = env.reset()
    raise RuntimeError(f"random moves never faced a {kind.__name__}")


def hhp_learner(args: argparse.Namespace, settings: dict[str, Any]) -> Any:
    """HhP with the env's YAML entry, ``--hhp-kwargs`` over it, and one sub-goal handed in (see the module's doc)."""
    from stable_baselines3.common.env_util import make_vec_env

    from sb3_hhp import HhP

    _, kwargs = entry_kwargs(args.env, args.hhp_kwargs)
    kwargs.pop("oracle", None)  # no preferences: nobody is asked
    sub = {key: value for key, value in settings.items() if key not in SB3_SCHEDULE}
    kwargs["subpolicy_kwargs"] = {**kwargs.get("subpolicy_kwargs", {}), **sub}
    goal = handed_in_subgoal(wrap_env(gym.make(args.env)), OBJECTS[args.object], args.seed)
    env_kwargs = {"max_steps": args.train_max_steps} if args.train_max_steps else None
    envs = make_vec_env(args.env, n_envs=args.n_envs, seed=args.seed, wrapper_class=wrap_env, env_kwargs=env_kwargs)
    kwargs.update(query_budget=0, max_subgoal_steps=args.max_steps, discovery_kwargs=dict(strategy="none", subgoals=[goal]))
    return HhP("MlpPolicy", envs, seed=args.seed, **kwargs)


def learner_settings(steps: int, exploration_steps: int, gamma: float, overrides: dict[str, Any]) -> dict[str, Any]:
    """SB3 DQN's keyword arguments with the sub-goal learners' defaults, ``gamma`` and ``overrides``."""
    defaults = {key: value for key, value in DEFAULT_SUBPOLICY_KWARGS.items() if key != "replay_buffer_kwargs"}
    settings = {**defaults, "gamma": gamma, "exploration_fraction": min(1.0, exploration_steps / steps),
                "exploration_final_eps": 0.05}
    settings.update(overrides)
    return settings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="MiniGrid-DoorKey-16x16-v0")
    parser.add_argument("--object", default="key", choices=sorted(OBJECTS), help="what the agent must face")
    parser.add_argument("--steps", type=int, default=200_000)
    parser.add_argument("--max-steps", type=int, default=100, help="steps a try gets (a sub-goal's give-up)")
    parser.add_argument("--exploration-steps", type=int, default=20_000)
    parser.add_argument("--gamma", type=float, default=0.9)
    parser.add_argument("--kwargs", default="{}", help="SB3 DQN arguments over the learners' defaults (JSON)")
    parser.add_argument("--crop", type=int, default=0, help="read only this many cells around the agent (odd; 0: all)")
    parser.add_argument("--learner", default="dqn", choices=["dqn", "stacked", "hhp"],
                        help="SB3's DQN, HhP's StackedDQN (its --view instead of --crop), or HhP with the one sub-goal")
    parser.add_argument("--hhp-kwargs", default="{}", help="--learner hhp: HhP arguments over the YAML entry's (JSON)")
    parser.add_argument("--n-envs", type=int, default=8, help="--learner hhp: envs stepped together")
    parser.add_argument("--stay-after-success", action="store_true",
                        help="--learner stacked: a try that reached the object is followed by the next from there (as "
                             "in HhP's option loop), not by a fresh layout")
    parser.add_argument("--train-max-steps", type=int, default=0,
                        help="--learner hhp: the training envs' episode length (MiniGrid's max_steps; 0: the env's)")
    parser.add_argument("--one-hot", type=json.loads, default=None, metavar="CODES",
                        help="the cells as one-hot indicators of these codes per channel (JSON, as the learners' "
                             "one_hot: [11, 0, 3] marks every object and state), not integer codes")
    parser.add_argument("--view", type=int, default=0, help="StackedDQN's view (odd; 0: the whole canvas)")
    parser.add_argument("--radius", type=int, default=7,
                        help="the greedy evaluation also splits its tries at this many cells from the agent to the "
                             "object at the start (7: within a 15x15 view, the entries' `view: 15`, or beyond it)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-episodes", type=int, default=50)
    parser.add_argument("--out", default=None, help="write the settings and the curve as JSON here")
    args = parser.parse_args()
    register_minigrid_tasks()
    th.set_num_threads(1)
    settings = learner_settings(args.steps, args.exploration_steps, args.gamma, json.loads(args.kwargs))
    env, eval_env = (make_env(args.env, args.object, args.max_steps, args.crop, args.one_hot) for _ in range(2))
    if args.learner == "stacked":
        model = StackedAgent(env, settings, args.exploration_steps, args.view, args.seed, not args.stay_after_success)
    elif args.learner == "hhp":
        model = hhp_learner(args, settings)
    else:
        model = DQN("MlpPolicy", env, seed=args.seed, **settings)
    begin, curve = time.perf_counter(), []
    for quarter in range(4):
        model.learn((quarter + 1) * args.steps // 4 - model.num_timesteps, reset_num_timesteps=False)
        episodes, n_actions = args.eval_episodes, int(eval_env.action_space.n)
        if args.learner == "hhp":
            point = dict(stochastic=success_rate(eval_env, episodes, hhp_stochastic(model)))
        else:
            greedy = tries(eval_env, episodes, epsilon_greedy(model, n_actions, 0.0))
            point = dict(greedy=reached_share(greedy),
                         epsilon_0_05=success_rate(eval_env, episodes, epsilon_greedy(model, n_actions, 0.05)),
                         greedy_by_start=split_at(greedy, args.radius))
        curve.append(dict(steps=model.num_timesteps, **point, seconds=round(time.perf_counter() - begin, 1)))
        print(json.dumps(curve[-1]), flush=True)
    result = dict(env=args.env, object=args.object, seed=args.seed, max_steps=args.max_steps, crop=args.crop,
                  one_hot=args.one_hot, learner=args.learner, view=args.view, radius=args.radius, hhp_kwargs=json.loads(args.hhp_kwargs),
                  train_max_steps=args.train_max_steps, n_envs=args.n_envs, stay_after_success=args.stay_after_success,
                  settings={key: (value if isinstance(value, (int, float, str)) else str(value)) for key, value in settings.items()},
                  curve=curve, command="benchmarks/diagnostics/learner_proxy.py " + " ".join(sys.argv[1:]))
    if args.out:
        pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        pathlib.Path(args.out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
