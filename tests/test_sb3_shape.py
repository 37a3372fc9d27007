"""HhP as an SB3 user holds it: SB3's README loop and ``evaluate_policy`` over ``model.get_env()``, and the public
semi-MDP :class:`~sb3_hhp.hierarchy.HierarchicalEnv` under SB3's own algorithms."""

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import pytest
import torch as th
from stable_baselines3 import DQN, PPO
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

from sb3_hhp import HhP, HierarchicalEnv
from sb3_hhp.goals import wrap_env

th.set_num_threads(1)

ENV = "MiniGrid-DoorKey-5x5-v0"
SMALL = dict(buffer_size=2_000, learning_starts=300, batch_size=32, max_subgoal_steps=30, query_budget=10,
             policy_kwargs=dict(net_arch=[64]), predictor_kwargs=dict(hidden_dim=64, batch_size=32, n_masks=20),
             rnd_kwargs=dict(hidden_dim=64, refresh_interval=500), subgoal_learner_kwargs=dict(exploration_steps=500),
             subpolicy_kwargs=dict(learning_starts=50, buffer_size=2_000, batch_size=32, policy_kwargs=dict(net_arch=[64])))


@pytest.fixture(scope="module")
def trained() -> HhP:
    model = HhP("MlpPolicy", ENV, seed=0, **SMALL)
    model.learn(2_500)
    assert len(model.subgoals) >= 2
    return model


def envs(n_envs: int, subprocess: bool, seed: int):
    return make_vec_env(ENV, n_envs=n_envs, wrapper_class=wrap_env, seed=seed,
                        vec_env_cls=SubprocVecEnv if subprocess else DummyVecEnv)


@pytest.mark.parametrize("n_envs, subprocess", [(1, False), (4, False), (2, True)])
def test_sb3_readme_loop_and_evaluate_policy_run_on_the_models_env(trained: HhP, n_envs: int, subprocess: bool) -> None:
    """SB3's README loop (no ``state``) runs 1,000 steps on ``model.get_env()``, and ``evaluate_policy`` on it gives
    the returns it gives on an env built apart with the same seeds."""
    trained.set_env(envs(n_envs, subprocess, seed=7))
    vec_env = trained.get_env()
    assert vec_env.num_envs == n_envs and vec_env.action_space == gym.make(ENV).action_space
    obs = vec_env.reset()
    for _ in range(1_000):
        action, _ = trained.predict(obs, deterministic=True)
        assert vec_env.action_space.contains(action[0])
        obs, reward, done, info = vec_env.step(action)
    vec_env.seed(100)
    own = evaluate_policy(trained, vec_env, n_eval_episodes=10, deterministic=True, return_episode_rewards=True)
    apart = envs(n_envs, False, seed=100)
    other = evaluate_policy(trained, apart, n_eval_episodes=10, deterministic=True, return_episode_rewards=True)
    assert sorted(own[0]) == pytest.approx(sorted(other[0])) and sorted(own[1]) == sorted(other[1])
    vec_env.close()


def test_the_loop_with_state_follows_each_envs_subgoal(trained: HhP) -> None:
    """With ``state`` and ``episode_start`` (as RecurrentPPO's docs show), each env keeps its sub-goal until it is
    reached or gives up: the sub-goal changes only at those steps."""
    trained.set_env(envs(2, False, seed=3))
    vec_env = trained.get_env()
    obs, state, starts = vec_env.reset(), None, np.ones(2, dtype=bool)
    changes = 0
    for _ in range(200):
        action, new_state = trained.predict(obs, state=state, episode_start=starts, deterministic=True)
        if state is not None:
            changed = (new_state[0] != state[0]) & ~starts
            # a sub-goal left while pursued: its walk was reached or gave up (counted in state[1])
            assert np.all(new_state[1][changed] == 1)
            changes += int(changed.sum())
        state = new_state
        obs, _, starts, _ = vec_env.step(action)
    assert changes > 0


def test_stepping_the_models_env_by_hand_then_learning_starts_fresh_episodes(trained: HhP) -> None:
    """Observations the option runner held are stale once the user steps the envs: ``learn`` resets them first."""
    trained.set_env(envs(1, False, seed=5))
    vec_env = trained.get_env()
    vec_env.reset()
    for _ in range(5):
        vec_env.step(np.array([vec_env.action_space.sample()]))
    assert trained.options.interrupted
    resets = []
    reset = trained.options.reset
    trained.options.reset = lambda: resets.append(1) or reset()
    try:
        trained.learn(50, reset_num_timesteps=False)
    finally:
        del trained.options.reset
    assert resets == [1] and not trained.options.interrupted


def test_hierarchical_env_runs_one_subgoal_per_action(trained: HhP) -> None:
    """An action runs the sub-goal's learner until terminal(s, g): it is reached, it gives up after
    max_subgoal_steps, or the episode ends; the reward is the extrinsic reward of those primitive steps."""
    env = HierarchicalEnv.from_model(trained, ENV)
    check_env(env, warn=False)
    assert env.action_space == gym.spaces.Discrete(len(trained.subgoals))
    rng = np.random.default_rng(0)
    ended = 0
    for episode in range(5):
        obs, _ = env.reset(seed=episode)
        done, total_steps, total_reward = False, 0, 0.0
        while not done:
            goal = int(rng.integers(env.action_space.n))
            obs, reward, terminated, truncated, info = env.step(goal)
            done = terminated or truncated
            steps = info["primitive_steps"]
            assert 1 <= steps <= trained.max_subgoal_steps
            reached = trained.goal_space.achieved(trained.goal_space.key(obs), trained.subgoals[goal].key)
            if info["subgoal_reached"]:
                assert reached
            elif not done:
                assert steps == trained.max_subgoal_steps  # it gave up
            total_steps += steps
            total_reward += reward
        ended += 1
        assert total_steps <= gym.make(ENV).unwrapped.max_steps
        assert (total_reward > 0) == terminated  # DoorKey pays only at the goal, which ends the episode
    assert ended == 5
    with pytest.raises(ValueError, match="Sub-goal 99 does not exist"):
        env.reset(seed=0)
        env.step(99)


def test_hierarchical_env_refuses_bad_input(trained: HhP) -> None:
    env = HierarchicalEnv.from_model(trained, ENV)
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(0)
    with pytest.raises(ValueError, match="at least one sub-goal"):
        HierarchicalEnv(ENV, trained.goal_space, [], trained.subpolicies)
    with pytest.raises(ValueError, match="one gymnasium env"):
        HierarchicalEnv(envs(1, False, 0), trained.goal_space, list(trained.subgoals), trained.subpolicies)


@pytest.mark.parametrize("algo", [DQN, PPO])
def test_sb3_algorithms_train_on_the_hierarchical_env(trained: HhP, algo) -> None:
    """Any SB3 algorithm is a meta-controller over the model's skills; the learners stay frozen."""
    before = {name: value.clone() for name, value in trained.subpolicies.state_dict().items()
              if isinstance(value, th.Tensor)}
    env = HierarchicalEnv.from_model(trained, ENV)
    kwargs = dict(learning_starts=20, buffer_size=500) if algo is DQN else dict(n_steps=32, batch_size=16)
    meta = algo("MlpPolicy", env, seed=0, **kwargs).learn(120)
    action, _ = meta.predict(env.reset(seed=1)[0], deterministic=True)
    assert env.action_space.contains(int(action))
    after = trained.subpolicies.state_dict()
    assert all(th.equal(value, after[name]) for name, value in before.items())
