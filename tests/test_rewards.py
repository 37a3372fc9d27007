"""Tests of the reward formulas: eq. 3 with sigma(R_p), eq. 5 and eq. 6."""

import numpy as np
import pytest
import torch as th

from sb3_hhp.hierarchy.rewards import pseudo_reward, subpolicy_reward
from sb3_hhp.preferences.rewards import PreferenceReturnNormalizer, meta_reward


def test_meta_reward_eq3_by_hand():
    # 0.7 * 2 + 0.3 * 0.5 / 0.25 = 1.4 + 0.6
    assert meta_reward(2.0, 0.5, sigma=0.25) == pytest.approx(2.0)
    # beta = 0.2: 0.2 * (-1) + 0.8 * 3 / 2 = -0.2 + 1.2
    assert meta_reward(-1.0, 3.0, sigma=2.0, beta=0.2) == pytest.approx(1.0)
    assert meta_reward(5.0, 7.0, sigma=3.0, beta=1.0) == pytest.approx(5.0)
    assert meta_reward(5.0, 6.0, sigma=3.0, beta=0.0) == pytest.approx(2.0)
    returns, bonuses = np.array([0.0, 1.0, -2.0]), np.array([1.0, 0.0, 4.0])
    expected = np.array([0.3 * 1.0 / 0.5, 0.7, -1.4 + 0.3 * 4.0 / 0.5])
    np.testing.assert_allclose(meta_reward(returns, bonuses, sigma=0.5), expected)
    out = meta_reward(th.tensor(returns), th.tensor(bonuses), sigma=0.5)
    assert isinstance(out, th.Tensor)
    np.testing.assert_allclose(out.numpy(), expected)


def expected_sigma(bonuses: np.ndarray, gamma: float, length: int) -> float:
    """Average over complete rollouts of the std of R_t = sum_{k=t}^{L-1} gamma^(k-t) b_k, by a double loop."""
    stds = []
    for start in range(0, len(bonuses) - length + 1, length):
        rollout = bonuses[start : start + length]
        returns = []
        for t in range(length):
            total = 0.0
            for k in range(t, length):
                total += gamma ** (k - t) * rollout[k]
            returns.append(total)
        returns = np.array(returns)
        stds.append(np.sqrt(np.mean((returns - returns.mean()) ** 2)))
    return float(np.mean(stds))


def test_sigma_is_running_average_of_rollout_return_stds():
    gamma, length = 0.99, 64
    rng = np.random.default_rng(0)
    bonuses = np.concatenate(
        [
            np.sin(np.arange(length) / 5.0),  # rollout 1
            np.where(np.arange(length) % 3 == 0, 1.0, -0.5),  # rollout 2
            rng.normal(size=length) * 2.0,  # rollout 3
            [0.3, -7.0, 11.0],  # an unfinished rollout: not counted
        ]
    )
    normalizer = PreferenceReturnNormalizer(gamma=gamma, rollout_length=length)
    assert normalizer.sigma == 1.0  # before the first full rollout
    normalizer.update(bonuses[:40])
    assert normalizer.sigma == 1.0
    # uneven chunks, one rollout completed at a time, then two at once
    normalizer.update(bonuses[40:70])
    assert normalizer.sigma == pytest.approx(expected_sigma(bonuses[:64], gamma, length), rel=1e-10)
    normalizer.update(bonuses[70])
    normalizer.update(bonuses[71:])
    sigma_three = expected_sigma(bonuses[: 3 * length], gamma, length)
    assert normalizer.num_rollouts == 3
    assert normalizer.sigma == pytest.approx(sigma_three, rel=1e-10)
    # the average of the three stds differs from each single one: the running average is really taken
    assert sigma_three != pytest.approx(expected_sigma(bonuses[2 * length : 3 * length], gamma, length), rel=1e-3)


def test_sigma_with_short_rollouts_and_other_gamma():
    bonuses = np.array([1.0, 2.0, 0.0, -1.0, 4.0, 4.0, 0.5, 0.0, 3.0])
    normalizer = PreferenceReturnNormalizer(gamma=0.5, rollout_length=3)
    normalizer.update(bonuses)
    # rollout [1, 2, 0]: returns [1 + 0.5 * 2, 2, 0] = [2, 2, 0]; std = sqrt(8/9)
    assert expected_sigma(bonuses[:3], 0.5, 3) == pytest.approx(np.sqrt(8 / 9))
    assert normalizer.sigma == pytest.approx(expected_sigma(bonuses, 0.5, 3), rel=1e-12)


@pytest.mark.parametrize("value", [0.0, 1.0, -3.0])
def test_sigma_is_safe_when_all_bonuses_are_equal(value: float):
    normalizer = PreferenceReturnNormalizer()
    normalizer.update(np.full(64 * 2, value))
    sigma = normalizer.sigma
    assert np.isfinite(sigma) and sigma > 0
    if value == 0.0:
        assert sigma == 1.0  # no spread: bonuses left unscaled
    else:  # equal nonzero bonuses still give returns that differ along the rollout
        assert sigma == pytest.approx(expected_sigma(np.full(128, value), 0.99, 64))
    assert np.isfinite(meta_reward(1.0, value, sigma))
    single = PreferenceReturnNormalizer(rollout_length=1)
    single.update(np.arange(5.0))
    assert single.sigma == 1.0


def test_normalizer_state_dict_round_trip():
    rng = np.random.default_rng(1)
    normalizer = PreferenceReturnNormalizer(gamma=0.9, rollout_length=8)
    normalizer.update(rng.normal(size=21))
    restored = PreferenceReturnNormalizer()
    restored.load_state_dict(normalizer.state_dict())
    more = rng.normal(size=11)
    normalizer.update(more)
    restored.update(more)
    assert restored.num_rollouts == normalizer.num_rollouts == 4
    assert restored.sigma == normalizer.sigma


def test_pseudo_reward_eq5_cases():
    assert pseudo_reward(True, False) == 1.0
    assert pseudo_reward(True, True) == 1.0  # reached on the last step: done wins
    assert pseudo_reward(False, True) == -1.0
    assert pseudo_reward(False, False) == 0.0
    done = np.array([True, True, False, False])
    terminal = np.array([False, True, True, False])
    np.testing.assert_array_equal(pseudo_reward(done, terminal), [1.0, 1.0, -1.0, 0.0])


def test_subpolicy_reward_eq6():
    assert subpolicy_reward(-1.0, 0.4) == pytest.approx(-0.8)
    assert subpolicy_reward(1.0, 2.0, alpha=0.25) == pytest.approx(1.5)
    assert subpolicy_reward(0.0, 3.0, alpha=0.0) == 0.0
    pseudo = pseudo_reward(np.array([True, False, False]), np.array([False, True, False]))
    np.testing.assert_allclose(subpolicy_reward(pseudo, np.array([0.2, 0.4, 1.0])), [1.1, -0.8, 0.5])
    out = subpolicy_reward(th.tensor([1.0, 0.0]), th.tensor([2.0, 4.0]), alpha=0.5)
    np.testing.assert_allclose(out.numpy(), [2.0, 2.0])


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: meta_reward(1.0, 1.0, sigma=1.0, beta=1.1), "beta"),
        (lambda: meta_reward(1.0, 1.0, sigma=1.0, beta=-0.1), "beta"),
        (lambda: meta_reward(1.0, 1.0, sigma=0.0), "sigma"),
        (lambda: subpolicy_reward(1.0, 1.0, alpha=-0.5), "alpha"),
        (lambda: PreferenceReturnNormalizer(gamma=0.0), "gamma"),
        (lambda: PreferenceReturnNormalizer(gamma=1.01), "gamma"),
        (lambda: PreferenceReturnNormalizer(rollout_length=0), "rollout_length"),
        (lambda: PreferenceReturnNormalizer(epsilon=-1.0), "epsilon"),
        (lambda: PreferenceReturnNormalizer().update(np.array([1.0, np.nan])), "finite"),
    ],
)
def test_bad_arguments(call, match: str):
    with pytest.raises(ValueError, match=match):
        call()
