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

Calibration: the class defaults (stacked sub-goal learners of ``DEFAULT_SUBPOLICY_KWARGS`` training on every step,
the max-centred preference bonus, the meta-controller on the goal space's features, MiniGrid's 7x7 canvas without its
empty outer ring), 8,000 primitive steps, 30 evaluation episodes on seeds 10,000-10,029, training seeds 0-9, one torch
thread, the CPU kernels pinned to their AVX2 paths as the test session pins them (``tests/conftest.py``), on a 2-core
AMD EPYC machine of this kind, one seed at a time beside two training runs:
``python benchmarks/calibrate_learning_test.py --seeds 0 1 2 3 4 5 6 7 8 9 --jobs 1``
(``benchmarks/results/learning_test_calibration_pinned.json``, 61-75 s of training each under that load; the
calibration before the kernels were pinned, on another machine: ``learning_test_calibration.json``, every seed
1.00 and 0.923-0.968; on 16 Intel Xeon cores with torch 2.11, seeds 0-15: every seed 1.00 and 0.850-0.968, seed 0
0.887, ``learning_test_calibration_xeon.json``). Alone on a machine of this kind the test takes about 30-60 s.
The random policy scores success 0.60, mean return 0.354 on these seeds.

==========  ============  ===========
train seed  success rate  mean return
==========  ============  ===========
0 (test)    1.00          0.968
1           1.00          0.951
2           1.00          0.958
3           1.00          0.967
4           1.00          0.902
5           1.00          0.968
6           1.00          0.959
7           1.00          0.966
8           1.00          0.966
9           1.00          0.962
==========  ============  ===========

Every seed clears both bars (success 0.9; mean return 0.3 above the random policy's, i.e. 0.654), the lowest by
0.25, so the test does not hinge on the seed; it trains seed 0 only. A run is deterministic given its seed on
one machine (``tests/test_hhp.py::test_same_seed_same_run``, ``tests/test_vec_envs.py::test_a_run_repeats_given_its_seed``);
on another CPU the libraries' kernels may take other floating-point paths (other vectorised code), and training
amplifies last-bit differences: the test session pins them to their AVX2 paths for that reason, and the bars are
still set where every calibration seed clears them, not at one seed's figure. (An earlier learner scored 0.00 on
another machine of this kind with seed 0, and 0.67 on seed 3 here. The README's first command, same code, seed and
machine, gave mean return 0.863 with MKL's own choice of path and 0.965 with its AVX2 path.)
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
TRAIN_STEPS = 8_000  # primitive env steps
EVAL_SEEDS = [10_000 + i for i in range(30)]  # never a training seed
MIN_SUCCESS_RATE = 0.9
MIN_RETURN_MARGIN = 0.3  # mean return above the random policy's, on the same seeds

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
        predictor_kwargs=dict(n_masks=20),
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
