"""Tests of VecRNDReward: curiosity (eq. 7) added to the reward of any VecEnv."""

import copy
import io
from typing import Any, Optional

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_hhp.curiosity import VecRNDReward
from sb3_hhp.curiosity.vec_rnd import EXTRINSIC_KEY, INTRINSIC_KEY

th.set_num_threads(1)

EPISODE_LENGTH = 3
RND_KWARGS = dict(embedding_dim=4, hidden_dim=8, batch_size=8, seed=0)


class CountingEnv(gym.Env):
    """Observes ``[t, offset]``, pays ``0.5 * t`` and ends at ``t = EPISODE_LENGTH``: every next observation is known."""

    observation_space = spaces.Box(low=0.0, high=10.0, shape=(2,), dtype=np.float32)
    action_space = spaces.Discrete(2)

    def __init__(self, offset: float = 0.0) -> None:
        self.offset = offset
        self.t = 0

    def _obs(self) -> np.ndarray:
        return np.array([self.t, self.offset], dtype=np.float32)

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self.t += 1
        return self._obs(), 0.5 * self.t, self.t == EPISODE_LENGTH, False, {}


def counting_venv(n_envs: int = 2, monitor: bool = False) -> Any:
    if monitor:
        return make_vec_env(CountingEnv, n_envs=n_envs, env_kwargs={"offset": 1.0})
    return DummyVecEnv([lambda i=i: CountingEnv(offset=float(i)) for i in range(n_envs)])


def expected_next_obs(t: int, n_envs: int = 2) -> np.ndarray:
    """s_{t+1} of each env after its t-th step of an episode (the terminal one at the end, not the reset one)."""
    return np.array([[t, i] for i in range(n_envs)], dtype=np.float32)


@pytest.mark.parametrize("coef", [0.0, 0.3, 2.0])
def test_reward_is_extrinsic_plus_coef_times_rnd_of_next_obs(coef):
    env = VecRNDReward(counting_venv(), intrinsic_coef=coef, rnd_kwargs=RND_KWARGS, update_every=100)
    env.reset()
    for t in range(1, 2 * EPISODE_LENGTH + 1):
        step = (t - 1) % EPISODE_LENGTH + 1
        reference = copy.deepcopy(env.rnd)  # the same statistics and weights the step will use
        env.step_async(np.zeros(2, dtype=int))
        obs, rewards, dones, infos = env.step_wait()
        next_obs = expected_next_obs(step)
        intrinsic = reference.intrinsic_reward(next_obs)
        assert np.all(intrinsic > 0)
        np.testing.assert_allclose(rewards, 0.5 * step + coef * intrinsic, rtol=1e-6)
        for i in range(2):
            assert infos[i][EXTRINSIC_KEY] == pytest.approx(0.5 * step)
            assert infos[i][INTRINSIC_KEY] == pytest.approx(float(intrinsic[i]), rel=1e-6)


def test_terminal_observation_is_used_at_episode_ends():
    env = VecRNDReward(counting_venv(), intrinsic_coef=1.0, rnd_kwargs=RND_KWARGS, update_every=100)
    env.reset()
    for _ in range(EPISODE_LENGTH - 1):
        env.step(np.zeros(2, dtype=int))
    reference = copy.deepcopy(env.rnd)
    wrong = copy.deepcopy(env.rnd)
    obs, rewards, dones, infos = env.step(np.zeros(2, dtype=int))
    assert dones.all()
    np.testing.assert_array_equal(obs, expected_next_obs(0))  # already the next episode's first observation
    np.testing.assert_array_equal(np.stack([info["terminal_observation"] for info in infos]), expected_next_obs(3))
    extrinsic = 0.5 * EPISODE_LENGTH
    np.testing.assert_allclose(rewards - extrinsic, reference.intrinsic_reward(expected_next_obs(3)), rtol=1e-6)
    assert not np.allclose(rewards - extrinsic, wrong.intrinsic_reward(obs), rtol=1e-3)


def test_predictor_is_trained_every_update_every_steps_on_the_next_observations():
    env = VecRNDReward(counting_venv(), intrinsic_coef=1.0, rnd_kwargs=RND_KWARGS, update_every=2, n_epochs=3)
    env.reset()
    before = copy.deepcopy(env.rnd.predictor.state_dict())
    untrained = copy.deepcopy(env.rnd)
    env.step(np.zeros(2, dtype=int))
    assert env.n_updates == 0 and env.last_loss is None
    assert all(th.equal(before[k], v) for k, v in env.rnd.predictor.state_dict().items())
    env.step(np.zeros(2, dtype=int))
    assert env.n_updates == 1 and env.last_loss is not None
    assert any(not th.equal(before[k], v) for k, v in env.rnd.predictor.state_dict().items())
    # the observation statistics saw exactly the four next observations s_{t+1} (RunningMeanStd's prior: count 1e-4)
    seen = np.concatenate([expected_next_obs(1), expected_next_obs(2)])
    assert env.rnd.obs_rms.count == pytest.approx(len(seen) + 1e-4)
    np.testing.assert_allclose(env.rnd.obs_rms.mean, seen.mean(axis=0), rtol=1e-3)
    for _ in range(40):
        env.step(np.zeros(2, dtype=int))
    assert env.n_updates == 21
    assert env.rnd.num_steps == 42 * 2
    # the states it saw are better predicted than by the untrained predictor under the same normalisation
    states = np.concatenate([expected_next_obs(t) for t in range(1, EPISODE_LENGTH + 1)])
    untrained.obs_rms = env.rnd.obs_rms.copy()
    assert env.rnd.prediction_error(states).mean() < 0.5 * untrained.prediction_error(states).mean()


def test_state_round_trip_goes_on_as_the_original():
    """A wrapper restored from :meth:`VecRNDReward.state_dict` (through ``th.save``) pays the same rewards and trains
    its predictor at the same steps as the one it was saved from; one mid-way between two updates is the hard case
    (the buffered next observations must travel too)."""
    original = VecRNDReward(counting_venv(), intrinsic_coef=1.0, rnd_kwargs=RND_KWARGS, update_every=3, n_epochs=2)
    original.reset()
    for _ in range(7):  # two updates, one observation buffered
        original.step(np.zeros(2, dtype=int))
    assert original.n_updates == 2 and len(original._buffer) == 1
    saved = io.BytesIO()
    th.save(original.state_dict(), saved)
    saved.seek(0)
    restored = VecRNDReward(counting_venv(), intrinsic_coef=1.0, rnd_kwargs={**RND_KWARGS, "seed": 1}, update_every=3,
                            n_epochs=2)
    restored.load_state_dict(th.load(saved, weights_only=True))
    restored.reset()
    original.reset()
    for _ in range(8):
        _, expected, _, _ = original.step(np.zeros(2, dtype=int))
        _, rewards, _, _ = restored.step(np.zeros(2, dtype=int))
        np.testing.assert_array_equal(rewards, expected)
        assert restored.n_updates == original.n_updates and restored.last_loss == original.last_loss
    assert original.n_updates == 5
    # a fresh wrapper (another seed) pays other rewards: the comparison above can fail
    fresh = VecRNDReward(counting_venv(), intrinsic_coef=1.0, rnd_kwargs={**RND_KWARGS, "seed": 1}, update_every=3)
    fresh.reset()
    assert not np.allclose(fresh.step(np.zeros(2, dtype=int))[1], original.step(np.zeros(2, dtype=int))[1])
    with pytest.raises(ValueError, match="same number of envs"):
        VecRNDReward(counting_venv(n_envs=3), rnd_kwargs=RND_KWARGS).load_state_dict(original.state_dict())


def test_monitor_reports_extrinsic_returns():
    env = VecRNDReward(counting_venv(monitor=True), intrinsic_coef=5.0, rnd_kwargs=RND_KWARGS, update_every=1)
    env.reset()
    paid = np.zeros(2)
    for _ in range(EPISODE_LENGTH):
        _, rewards, dones, infos = env.step(np.zeros(2, dtype=int))
        paid += rewards
    assert dones.all()
    extrinsic_return = 0.5 * (1 + 2 + 3)
    for i in range(2):
        assert infos[i]["episode"]["r"] == pytest.approx(extrinsic_return)
        assert paid[i] > extrinsic_return + 1e-3  # the learner was paid curiosity on top


def test_arguments_are_checked():
    with pytest.raises(ValueError, match="intrinsic_coef must be >= 0"):
        VecRNDReward(counting_venv(), intrinsic_coef=-1.0)
    with pytest.raises(ValueError, match="update_every must be an integer >= 1"):
        VecRNDReward(counting_venv(), update_every=0)
    dict_env = DummyVecEnv([lambda: gym.wrappers.TransformObservation(
        CountingEnv(), lambda obs: {"x": obs}, spaces.Dict({"x": CountingEnv.observation_space})
    )])
    with pytest.raises(ValueError, match="Box observation spaces only"):
        VecRNDReward(dict_env)


def test_ppo_learns_on_a_minigrid_env_with_curiosity():
    import minigrid  # noqa: F401  registers the MiniGrid envs

    from sb3_hhp.goals import wrap_env

    venv = make_vec_env("MiniGrid-Empty-5x5-v0", n_envs=2, seed=0, wrapper_class=wrap_env)
    env = VecRNDReward(venv, intrinsic_coef=0.5, rnd_kwargs={"seed": 0, "hidden_dim": 32}, update_every=16)
    model = PPO("MlpPolicy", env, n_steps=32, batch_size=32, n_epochs=1, seed=0, device="cpu")
    model.learn(128)
    assert model.num_timesteps == 128
    assert env.n_updates == 128 // 2 // 16
    env.close()
