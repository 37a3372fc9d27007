"""HhP learns a tiny MiniGrid task: a success rate on fresh seeds, and a clear margin over a random policy.

The task is ``MiniGrid-Empty-Random-5x5-v0``: a 3x3 room whose agent start (cell and heading) changes
with the seed, so an evaluation on seeds never used in training measures a policy, not one memorised
path. (``MiniGrid-Empty-5x5-v0`` has one fixed start, so every evaluation seed replays the same episode
and a run scores all or nothing.) MiniGrid's return is ``1 - 0.9 * steps / max_steps`` on success and 0
otherwise, so a random walk that stumbles on the goal late earns little.

Evaluation is stochastic (the subpolicies act epsilon-greedily with their final epsilon, the
meta-controller with its own): a greedy subpolicy can get stuck repeating one action (turning back and
forth, or a no-op such as "pick up" in front of the goal) until its sub-goal gives up, and a greedy
meta-controller then chooses the same sub-goal again from the same state.

Calibration (2-core CPU, one torch thread, 12,000 primitive steps, ~65 s of training, 30 evaluation
episodes on seeds 10,000-10,029; the random policy: success 0.60, mean return 0.354), with the defaults
of the meta-controller's sub-goal mask and the predictor reading the goal space's features:

==========  ============  ===========
train seed  success rate  mean return
==========  ============  ===========
0 (test)    0.97          0.781
1           0.90          0.761
2           0.93          0.807
3           0.67          0.605
4           0.90          0.811
5           0.90          0.832
==========  ============  ===========

so the mean-return margin (random + 0.2) holds for every seed tried and the success threshold (0.7) for
all but seed 3; the test trains seed 0 only. (Before the mask and the features: 1.00, 0.93, 0.97, 0.90,
0.87, 0.90.)
"""

from collections.abc import Callable

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import pytest
import torch as th

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env

ENV_ID = "MiniGrid-Empty-Random-5x5-v0"
TRAIN_SEED = 0
TRAIN_STEPS = 12_000  # primitive env steps, about a minute on one CPU thread
EVAL_SEEDS = [10_000 + i for i in range(30)]  # never a training seed
MIN_SUCCESS_RATE = 0.7
MIN_RETURN_MARGIN = 0.2  # mean return above the random policy's, on the same seeds

pytestmark = pytest.mark.slow


@pytest.fixture
def one_thread():
    threads = th.get_num_threads()
    th.set_num_threads(1)
    yield
    th.set_num_threads(threads)


def episode_return(seed: int, act: Callable[[np.ndarray, bool], int], wrap: bool) -> float:
    """Play one episode of a fresh env reset with ``seed``; ``act(obs, episode_start)`` gives the action."""
    env = gym.make(ENV_ID)
    if wrap:
        env = wrap_env(env)
    obs, _ = env.reset(seed=seed)
    total, done, start = 0.0, False, True
    while not done:
        obs, reward, terminated, truncated, _ = env.step(act(obs, start))
        total += float(reward)
        start, done = False, terminated or truncated
    env.close()
    return total


def hhp_returns(model: HhP, seeds: list[int]) -> np.ndarray:
    """Returns of HhP's stochastic policy, the sub-goal carried in ``state`` as ``evaluate_policy`` does."""
    returns = []
    for seed in seeds:
        state: list = [None]

        def act(obs: np.ndarray, start: bool) -> int:
            action, state[0] = model.predict(obs, state=state[0], episode_start=np.array([start]), deterministic=False)
            return int(action)

        returns.append(episode_return(seed, act, wrap=True))
    return np.asarray(returns)


def random_returns(seeds: list[int]) -> np.ndarray:
    """Returns of the uniformly random policy over the primitive actions, on the same seeds."""
    returns = []
    for seed in seeds:
        action_space = gym.make(ENV_ID).action_space
        action_space.seed(seed)
        returns.append(episode_return(seed, lambda obs, start: int(action_space.sample()), wrap=False))
    return np.asarray(returns)


def train(seed: int) -> HhP:
    """HhP with the scripted oracle and small settings: 20 questions, 20 dropout masks, early learning starts."""
    model = HhP(
        "MlpPolicy",
        gym.make(ENV_ID),
        oracle="scripted",
        query_budget=20,
        n_masks=20,
        learning_starts=200,
        max_subgoal_steps=30,
        subpolicy_kwargs=dict(learning_starts=64),
        seed=seed,
    )
    return model.learn(TRAIN_STEPS)


def test_hhp_learns_empty_random_5x5_and_beats_a_random_policy(one_thread) -> None:
    model = train(TRAIN_SEED)
    assert model.num_timesteps >= TRAIN_STEPS
    assert model.query_selector.used > 0, "the scripted oracle was never asked"
    goal_names = [model.goal_space.describe(goal.key) for goal in model.subgoals]
    assert "task solved" in goal_names, f"CSD never admitted the solved task; sub-goals: {goal_names}"

    hhp = hhp_returns(model, EVAL_SEEDS)
    chance = random_returns(EVAL_SEEDS)
    success_rate = float(np.mean(hhp > 0))
    assert success_rate >= MIN_SUCCESS_RATE, f"success rate {success_rate:.2f} < {MIN_SUCCESS_RATE}; returns {hhp}"
    assert hhp.mean() >= chance.mean() + MIN_RETURN_MARGIN, (
        f"mean return {hhp.mean():.3f} is not {MIN_RETURN_MARGIN} above the random policy's {chance.mean():.3f}"
    )
