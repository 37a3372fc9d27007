"""HhP on several envs at once: the option loop steps a VecEnv (DummyVecEnv or SubprocVecEnv), each env pursuing its
own sub-goal; predict and evaluate_policy on n envs; a model moves between numbers of envs; runs repeat given
their seed; wrappers HhP cannot honour are refused."""

import contextlib
from typing import Any

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecMonitor

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env

th.set_num_threads(1)

EMPTY = "MiniGrid-Empty-5x5-v0"
TINY: dict[str, Any] = dict(
    buffer_size=2_000, learning_starts=300, batch_size=32, max_subgoal_steps=30, meta_kwargs=dict(target_update_interval=50),
    policy_kwargs=dict(net_arch=[64]), predictor_kwargs=dict(hidden_dim=64, batch_size=32, n_masks=20),
    rnd_kwargs=dict(hidden_dim=64, refresh_interval=500), subgoal_learner_kwargs=dict(exploration_steps=500), query_budget=10,
    subpolicy_kwargs=dict(learning_starts=50, buffer_size=2_000, batch_size=32, policy_kwargs=dict(net_arch=[64, 64])),
)


def vec_env(n_envs: int, seed: int = 0, **kwargs: Any):
    return make_vec_env(EMPTY, n_envs=n_envs, wrapper_class=wrap_env, seed=seed, **kwargs)


class Calls(BaseCallback):
    def _on_step(self) -> bool:
        return True


def test_four_envs_pursue_their_own_subgoals() -> None:
    model = HhP("MlpPolicy", vec_env(4), seed=0, **TINY)
    chosen: list[int] = []
    choose = model.choose_subgoals

    def counted(obs, *args, **kwargs):
        chosen.append(len(obs))
        return choose(obs, *args, **kwargs)

    model.choose_subgoals = counted
    calls = Calls()
    model.learn(2_000, callback=calls)
    assert model.n_envs == 4 and model.subpolicies.replay.n_envs == 4
    assert model.num_timesteps >= 2_000 and model.num_timesteps % 4 == 0
    assert model.options.num_steps == model.num_timesteps
    assert calls.n_calls == model.num_timesteps // 4  # one call per step of the four envs
    assert sum(model.subgoal_set.visits.values()) == model.num_timesteps
    assert len(model.subgoals) >= 2 and model._episode_num >= 4
    assert max(chosen) > 1  # envs waiting at the same step get their sub-goals in one forward
    assert model.replay_buffer.size() == sum(chosen) - int((model.options.goals >= 0).sum())  # every ended choice stored
    assert model.replay_buffer.n_envs == 1  # R_H is one stream of choices


def test_predict_and_evaluate_policy_on_n_envs() -> None:
    model = HhP("MlpPolicy", vec_env(2), seed=1, **TINY)
    model.learn(1_500)
    env = vec_env(3, seed=100)
    obs = env.reset()
    actions, state = model.predict(obs, deterministic=True)
    assert actions.shape == (3,) and state[0].shape == (3,) and (state[1] == 1).all()
    actions, state = model.predict(obs, state=state, episode_start=np.array([True, False, False]), deterministic=True)
    assert state[1].tolist() == [1, 2, 2]  # env 0 started afresh: a new sub-goal
    mean, std = evaluate_policy(model, env, n_eval_episodes=6)
    assert np.isfinite(mean) and np.isfinite(std)


def test_subproc_vec_env() -> None:
    venv = vec_env(2, vec_env_cls=SubprocVecEnv)
    try:
        model = HhP("MlpPolicy", venv, seed=0, oracle="scripted", **TINY)
        model.learn(800)
        assert model.num_timesteps >= 800 and len(model.subgoals) >= 1
    finally:
        venv.close()


class _HoldsALock(gym.Wrapper):
    """An env whose unwrapped env holds what cannot be pickled (a lock)."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        import threading

        env.unwrapped.lock = threading.Lock()


def _lock_then_wrap(env: gym.Env) -> gym.Env:
    return wrap_env(_HoldsALock(env))


def test_a_subproc_env_that_cannot_be_pickled_is_refused_before_training() -> None:
    import sys

    import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the worker processes get these classes by value
    try:
        venv = make_vec_env(EMPTY, n_envs=2, wrapper_class=_lock_then_wrap, vec_env_cls=SubprocVecEnv)
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    try:
        with pytest.raises(ValueError, match="copy sent out of the env's process.*picklable attributes, or use a DummyVecEnv"):
            HhP("MlpPolicy", venv, seed=0, **TINY)
    finally:
        with contextlib.suppress(BrokenPipeError):  # the worker that failed to send its env has ended
            venv.close()


def test_a_subproc_env_is_copied_only_while_its_facts_are_kept() -> None:
    """Reading an env of a SubprocVecEnv copies it out of its process: at a choice, only while questions remain (the
    oracle needs the state's facts) or states are drawn for people."""
    venv = vec_env(2, vec_env_cls=SubprocVecEnv)
    try:
        model = HhP("MlpPolicy", venv, seed=0, oracle="scripted", **{**TINY, "query_budget": 0})
        reads: list[str] = []
        get_attr = venv.get_attr
        venv.get_attr = lambda name, indices=None: reads.append(name) or get_attr(name, indices)
        model.learn(800)
        assert not model.options.record_privileged and len(model.subgoals) >= 1
        assert "unwrapped" not in reads  # no questions to ask: no env copied
        model.options.record_images = True  # states drawn for people: each choice's env is read
        model.learn(400, reset_num_timesteps=False)
        assert "unwrapped" in reads
    finally:
        venv.close()


def test_a_model_moves_between_numbers_of_envs(tmp_path) -> None:
    model = HhP("MlpPolicy", gym.make(EMPTY), seed=0, **TINY)
    model.learn(800)
    model.save(tmp_path / "one.zip")
    loaded = HhP.load(tmp_path / "one.zip", env=vec_env(3))
    assert loaded.n_envs == 3 and loaded.subpolicies.replay.n_envs == 3
    assert [goal.key for goal in loaded.subgoals] == [goal.key for goal in model.subgoals]
    loaded.learn(600, reset_num_timesteps=False)
    assert loaded.num_timesteps >= model.num_timesteps + 600
    loaded.set_env(gym.make(EMPTY))
    loaded.learn(200, reset_num_timesteps=False)
    assert loaded.n_envs == 1


def _fingerprint(model: HhP) -> tuple:
    learners = model.subpolicies
    return (
        model.num_timesteps, [goal.key for goal in model.subgoals], model.query_selector.used,
        float(sum(p.detach().double().sum() for p in model.q_net.parameters())),
        float(sum(value.double().sum() for value in learners.state_dict().values() if isinstance(value, th.Tensor))),
    )


def test_a_run_repeats_given_its_seed() -> None:
    """Two runs with the same seed (two envs, one torch thread) end with the same sub-goals, labels and weights."""
    runs = []
    for _ in range(2):
        model = HhP("MlpPolicy", vec_env(2, seed=7), seed=7, **TINY)
        model.learn(1_200)
        runs.append(_fingerprint(model))
    assert runs[0] == runs[1]


def test_only_wrappers_that_change_nothing_are_accepted() -> None:
    """VecMonitor records episodes and changes nothing HhP reads: accepted (VecNormalize and VecFrameStack are refused,
    tests/test_hhp.py)."""
    model = HhP("MlpPolicy", VecMonitor(DummyVecEnv([lambda: wrap_env(gym.make(EMPTY))] * 2)), seed=0, **TINY)
    model.learn(300)
    assert model.num_timesteps >= 300


def test_the_shared_replay_holds_buffer_size_transitions_over_all_envs() -> None:
    """As SB3's replay buffers: ``buffer_size`` is divided among the envs, so n envs keep the same number of
    transitions (the same recent past) as one."""
    one = HhP("MlpPolicy", vec_env(1), seed=0, **TINY).subpolicies.replay
    four = HhP("MlpPolicy", vec_env(4), seed=0, **TINY).subpolicies.replay
    assert one.capacity * one.n_envs == four.capacity * four.n_envs == TINY["subpolicy_kwargs"]["buffer_size"]
