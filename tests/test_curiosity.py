"""Tests of the RND curiosity module: eq. 7 (intrinsic reward), Omega and eq. 8 (novelty progress)."""

import copy
import io

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import NatureCNN
from torch import nn

from sb3_hhp.curiosity.rnd import RND

th.set_num_threads(1)

OBS_DIM = 4
SPACE = spaces.Box(low=-10.0, high=10.0, shape=(OBS_DIM,), dtype=np.float32)


def tiny_rnd(**kwargs) -> RND:
    params = dict(embedding_dim=3, hidden_dim=5, batch_size=16, seed=0)
    params.update(kwargs)
    return RND(SPACE, **params)


def hand_forward(state_dict: dict, x: np.ndarray) -> np.ndarray:
    """The MLP by hand from its weights: linear layers in order, ReLU between them, none after the last."""
    weights = [(k, v.cpu().numpy().astype(np.float64)) for k, v in state_dict.items()]
    layers = [(w, dict(weights)[name[: -len("weight")] + "bias"]) for name, w in weights if name.endswith("weight")]
    for i, (w, b) in enumerate(layers):
        x = x @ w.T + b
        if i < len(layers) - 1:
            x = np.maximum(x, 0.0)
    return x


def hand_normalize(obs: np.ndarray, mean: np.ndarray, var: np.ndarray, clip: float = 5.0) -> np.ndarray:
    return np.clip((obs - mean) / np.sqrt(var + 1e-8), -clip, clip).astype(np.float32).astype(np.float64)


def hand_error(predictor_sd: dict, target_sd: dict, obs: np.ndarray, mean: np.ndarray, var: np.ndarray) -> np.ndarray:
    x = hand_normalize(obs, mean, var)
    return np.sum((hand_forward(predictor_sd, x) - hand_forward(target_sd, x)) ** 2, axis=1)


def pooled_var(values: list[float], prior_count: float = 1e-4) -> float:
    """Variance of ``values`` pooled with RunningMeanStd's prior (mean 0, variance 1, count 1e-4), in one shot."""
    values = np.asarray(values, np.float64)
    n = len(values)
    total = n + prior_count
    sample_mean = values.mean()
    m2 = prior_count * 1.0 + np.sum((values - sample_mean) ** 2) + sample_mean**2 * prior_count * n / total
    return m2 / total


def test_error_falls_on_trained_states_only():
    rnd = RND(SPACE, embedding_dim=8, hidden_dim=32, batch_size=32, seed=1)
    rng = np.random.default_rng(0)
    familiar = (rng.normal(size=(64, OBS_DIM)) * 0.1).astype(np.float32)
    far = np.full((1, OBS_DIM), 4.0, np.float32)
    rnd.update(familiar)  # fixes the observation statistics (the same batch keeps them unchanged)
    familiar_before = rnd.prediction_error(familiar).mean()
    far_before = rnd.prediction_error(far)[0]
    for _ in range(150):
        rnd.update(familiar)
    familiar_after = rnd.prediction_error(familiar).mean()
    far_after = rnd.prediction_error(far)[0]
    assert familiar_after < 0.05 * familiar_before
    # the unseen state keeps a high error: far above the trained states', and the gap has widened
    assert far_after > 20 * familiar_after
    assert far_after / familiar_after > 3 * far_before / familiar_before
    rewards = rnd.intrinsic_reward(np.concatenate([familiar[:1], far]))
    assert rewards[1] > 20 * rewards[0]


def test_prediction_error_is_eq7_by_hand():
    rnd = tiny_rnd()
    rng = np.random.default_rng(1)
    data = rng.normal(loc=2.0, scale=[0.5, 1.0, 2.0, 3.0], size=(50, OBS_DIM)).astype(np.float32)
    rnd.update(data, n_epochs=2)
    np.testing.assert_allclose(rnd.obs_rms.mean, data.mean(axis=0), rtol=1e-4)
    np.testing.assert_allclose(rnd.obs_rms.var, data.var(axis=0), rtol=1e-4)
    # includes a state far enough to be clipped at obs_clip
    obs = np.concatenate([data[:5], np.full((1, OBS_DIM), 9.0, np.float32)])
    expected = hand_error(rnd.predictor.state_dict(), rnd.target.state_dict(), obs, rnd.obs_rms.mean, rnd.obs_rms.var)
    np.testing.assert_allclose(rnd.prediction_error(obs), expected, rtol=1e-5, atol=1e-6)
    assert expected.std() > 0  # the states are told apart


def test_intrinsic_reward_is_eq7_divided_by_forward_filter_std():
    gamma = 0.9
    rnd = tiny_rnd(gamma=gamma)
    rng = np.random.default_rng(2)
    rnd.update(rng.normal(size=(40, OBS_DIM)).astype(np.float32))
    errors_of = lambda obs: hand_error(  # noqa: E731
        rnd.predictor.state_dict(), rnd.target.state_dict(), obs, rnd.obs_rms.mean, rnd.obs_rms.var
    )
    # calls of 1, 4, 1 and 3 rows: the rows are consecutive steps of one stream
    batches = [rng.normal(size=(n, OBS_DIM)).astype(np.float32) for n in (1, 4, 1, 3)]
    returns: list[float] = []
    discounted = 0.0
    for i, batch in enumerate(batches):
        errors = errors_of(batch)
        for error in errors:
            discounted = gamma * discounted + error
            returns.append(discounted)
        rewards = rnd.intrinsic_reward(batch)
        assert rewards.shape == (len(batch),)
        if i == 0:  # a single return: its std is undefined, the raw error comes back
            np.testing.assert_allclose(rewards, errors, rtol=1e-5)
        else:
            np.testing.assert_allclose(rewards, errors / np.sqrt(pooled_var(returns)), rtol=1e-4)
    assert rnd.reward_filter == pytest.approx(discounted, rel=1e-5)


def test_intrinsic_reward_changes_no_network_and_no_observation_statistics():
    rnd = tiny_rnd()
    rnd.update(np.random.default_rng(3).normal(size=(20, OBS_DIM)).astype(np.float32))
    weights = copy.deepcopy(rnd.predictor.state_dict())
    mean, var = rnd.obs_rms.mean.copy(), rnd.obs_rms.var.copy()
    rnd.intrinsic_reward(np.ones((1, OBS_DIM), np.float32))
    rnd.intrinsic_reward(np.ones(OBS_DIM, np.float32))  # an unbatched observation is accepted
    for key, value in rnd.predictor.state_dict().items():
        assert th.equal(value, weights[key])
    np.testing.assert_array_equal(rnd.obs_rms.mean, mean)
    np.testing.assert_array_equal(rnd.obs_rms.var, var)
    assert all(not p.requires_grad for p in rnd.target.parameters())


def test_novelty_progress_is_eq8_by_hand():
    rnd = tiny_rnd(memory_size=3, refresh_interval=10)
    rng = np.random.default_rng(4)
    obs = rng.normal(size=(7, OBS_DIM)).astype(np.float32)
    np.testing.assert_array_equal(rnd.novelty_progress(obs), np.zeros(7))  # Omega empty
    recorded = []
    for k in range(3):
        # different data each time, so the snapshots (weights and statistics) differ
        rnd.update(rng.normal(loc=k, scale=1 + k, size=(32, OBS_DIM)).astype(np.float32), n_epochs=5)
        recorded.append((copy.deepcopy(rnd.predictor.state_dict()), rnd.obs_rms.mean.copy(), rnd.obs_rms.var.copy()))
        rnd.on_steps(10)
    rnd.update(rng.normal(loc=-1, size=(32, OBS_DIM)).astype(np.float32), n_epochs=5)
    target = rnd.target.state_dict()
    current = hand_error(rnd.predictor.state_dict(), target, obs, rnd.obs_rms.mean, rnd.obs_rms.var)
    old = [hand_error(sd, target, obs, mean, var) for sd, mean, var in recorded]
    assert np.abs(old[0] - old[1]).max() > 1e-3 and np.abs(old[1] - old[2]).max() > 1e-3
    expected = np.mean([current - err for err in old], axis=0)  # eq. 8
    np.testing.assert_allclose(rnd.novelty_progress(obs), expected, rtol=1e-4, atol=1e-6)
    # states an episode revisits are scored once: each repeat gets its first occurrence's value, in place
    order = [3, 0, 3, 6, 1, 0, 0, 5, 2, 4, 6]
    repeated = rnd.novelty_progress(obs[order])
    np.testing.assert_allclose(repeated, expected[order], rtol=1e-4, atol=1e-6)
    assert repeated[0] == repeated[2] and repeated[1] == repeated[5] == repeated[6]


def test_omega_keeps_the_m_newest_snapshots_every_t_steps():
    rnd = tiny_rnd(memory_size=4, refresh_interval=5)
    rng = np.random.default_rng(5)
    rnd.on_steps(4)
    assert rnd.memory == []
    rnd.on_steps(1)
    assert len(rnd.memory) == 1 and rnd.memory[0].num_steps == 5
    rnd.on_steps(3)
    rnd.on_steps(1)
    assert len(rnd.memory) == 1  # 9 steps: no second refresh yet
    rnd.on_steps(1)
    assert len(rnd.memory) == 2  # 10 steps
    recorded = {}
    for _ in range(4):  # refreshes 3..6, at 15, 20, 25, 30 steps
        rnd.update(rng.normal(size=(16, OBS_DIM)).astype(np.float32), n_epochs=3)
        recorded[rnd.num_steps + 5] = (copy.deepcopy(rnd.predictor.state_dict()), rnd.obs_rms.mean.copy())
        rnd.on_steps(5)
    memory = rnd.memory
    assert [snap.num_steps for snap in memory] == [15, 20, 25, 30]
    assert len({id(snap.predictor) for snap in memory}) == 4
    for snap in memory:
        assert snap.predictor is not rnd.predictor and snap.obs_rms is not rnd.obs_rms
        weights, mean = recorded[snap.num_steps]
        for key, value in snap.predictor.state_dict().items():
            assert th.equal(value, weights[key])
        np.testing.assert_array_equal(snap.obs_rms.mean, mean)
    # snapshots are frozen copies: training the live predictor leaves them unchanged
    rnd.update(rng.normal(size=(16, OBS_DIM)).astype(np.float32), n_epochs=3)
    for snap in memory:
        for key, value in snap.predictor.state_dict().items():
            assert th.equal(value, recorded[snap.num_steps][0][key])


def test_state_dict_round_trip():
    rng = np.random.default_rng(6)
    rnd = tiny_rnd(memory_size=2, refresh_interval=3)
    for _ in range(3):
        rnd.update(rng.normal(size=(20, OBS_DIM)).astype(np.float32), n_epochs=2)
        rnd.intrinsic_reward(rng.normal(size=(2, OBS_DIM)).astype(np.float32))
        rnd.on_steps(3)
    buffer = io.BytesIO()
    th.save(rnd.state_dict(), buffer)
    buffer.seek(0)
    restored = tiny_rnd(memory_size=2, refresh_interval=3, seed=123)
    restored.load_state_dict(th.load(buffer, weights_only=True))
    assert restored.num_steps == rnd.num_steps == 9
    assert [s.num_steps for s in restored.memory] == [s.num_steps for s in rnd.memory] == [6, 9]
    probe = rng.normal(size=(5, OBS_DIM)).astype(np.float32)
    np.testing.assert_array_equal(restored.novelty_progress(probe), rnd.novelty_progress(probe))
    for row in probe:
        np.testing.assert_array_equal(restored.intrinsic_reward(row[None]), rnd.intrinsic_reward(row[None]))
    # training continues identically (optimizer moments and minibatch shuffling restored)
    data = rng.normal(size=(40, OBS_DIM)).astype(np.float32)
    assert restored.update(data, n_epochs=2) == rnd.update(data, n_epochs=2)
    np.testing.assert_array_equal(restored.prediction_error(probe), rnd.prediction_error(probe))
    restored.on_steps(3)
    rnd.on_steps(3)
    np.testing.assert_array_equal(restored.novelty_progress(probe), rnd.novelty_progress(probe))


def test_seed_makes_networks_reproducible():
    a, b, c = tiny_rnd(seed=7), tiny_rnd(seed=7), tiny_rnd(seed=8)
    probe = np.random.default_rng(7).normal(size=(3, OBS_DIM)).astype(np.float32)
    np.testing.assert_array_equal(a.prediction_error(probe), b.prediction_error(probe))
    assert not np.array_equal(a.prediction_error(probe), c.prediction_error(probe))


@pytest.mark.parametrize(
    "space, uses_cnn",
    [
        (spaces.Box(0, 255, (36, 40, 3), np.uint8), True),  # channel-last image
        (spaces.Box(0, 255, (4, 40, 36), np.uint8), True),  # channel-first image
        (spaces.Box(0, 255, (7, 7, 3), np.uint8), False),  # too small for the conv stack: MLP
        (spaces.Box(0.0, 1.0, (2, 3), np.float32), False),
    ],
)
def test_observation_kinds(space: spaces.Box, uses_cnn: bool):
    rnd = RND(space, embedding_dim=4, hidden_dim=8, batch_size=4, seed=0)
    assert any(isinstance(m, NatureCNN) for m in rnd.predictor.modules()) == uses_cnn
    obs = np.stack([space.sample() for _ in range(6)])
    assert np.isfinite(rnd.update(obs))
    assert rnd.intrinsic_reward(obs).shape == (6,)
    rnd.on_steps(rnd.refresh_interval)
    assert rnd.novelty_progress(obs).shape == (6,)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(embedding_dim=0), "embedding_dim"),
        (dict(hidden_dim=0), "hidden_dim"),
        (dict(memory_size=0), "memory_size"),
        (dict(refresh_interval=0), "refresh_interval"),
        (dict(batch_size=0), "batch_size"),
        (dict(gamma=0.0), "gamma"),
        (dict(gamma=1.5), "gamma"),
        (dict(learning_rate=0.0), "learning_rate"),
        (dict(obs_clip=-1.0), "obs_clip"),
    ],
)
def test_invalid_arguments(kwargs: dict, match: str):
    with pytest.raises(ValueError, match=match):
        RND(SPACE, **kwargs)


def test_unsupported_space_and_bad_shapes():
    with pytest.raises(ValueError, match="Box"):
        RND(spaces.Discrete(3))  # type: ignore[arg-type]
    rnd = tiny_rnd()
    with pytest.raises(ValueError, match="shape"):
        rnd.prediction_error(np.zeros((2, OBS_DIM + 1), np.float32))
    with pytest.raises(ValueError, match="n_epochs"):
        rnd.update(np.zeros((2, OBS_DIM), np.float32), n_epochs=0)
    with pytest.raises(ValueError, match="n_steps"):
        rnd.on_steps(-1)


def test_gamma_one_is_accepted():
    assert isinstance(tiny_rnd(gamma=1.0).target, nn.Module)
