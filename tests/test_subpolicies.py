"""The subpolicy learners: gradient steps at the model's own train frequency, clear errors otherwise."""

import numpy as np
import pytest
from gymnasium import spaces

from sb3_hhp.hierarchy.subpolicies import SubpolicySet

OBS = spaces.Box(0.0, 1.0, (4,), np.float32)


def _feed(subpolicy, steps: int) -> list[int]:
    """Observe ``steps`` random transitions; the model's update count after each."""
    rng = np.random.default_rng(0)
    counts = []
    for _ in range(steps):
        obs, next_obs = rng.random(4, dtype=np.float32), rng.random(4, dtype=np.float32)
        subpolicy.observe(obs, next_obs, np.asarray(rng.integers(3)), float(rng.random()), False)
        counts.append(subpolicy.model._n_updates)
    return counts


@pytest.mark.parametrize("train_freq, gradient_steps", [(1, 1), (4, 1), (4, 2)])
def test_gradient_steps_follow_the_models_train_frequency(train_freq: int, gradient_steps: int) -> None:
    subpolicies = SubpolicySet(OBS, spaces.Discrete(3), seed=0, subpolicy_kwargs=dict(
        train_freq=train_freq, gradient_steps=gradient_steps, learning_starts=8, batch_size=8,
        policy_kwargs=dict(net_arch=[8])))
    subpolicy = subpolicies.add()
    assert subpolicy.train_freq == train_freq
    counts = _feed(subpolicy, 40)
    # no update before the buffer holds learning_starts transitions, then gradient_steps every train_freq own steps
    expected = [gradient_steps * ((step // train_freq) - (7 // train_freq)) if step >= 8 else 0 for step in range(1, 41)]
    assert counts == expected


def test_the_paper_default_is_one_update_every_step() -> None:
    subpolicy = SubpolicySet(OBS, spaces.Discrete(3), seed=0).add()
    assert subpolicy.train_freq == 1 and subpolicy.model.gradient_steps == 1


@pytest.mark.parametrize("kwargs, match", [
    (dict(train_freq=(1, "episode")), "counts its own steps"),
    (dict(gradient_steps=-1), "gradient_steps >= 1"),
])
def test_a_train_frequency_a_subpolicy_cannot_follow_is_refused(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        SubpolicySet(OBS, spaces.Discrete(3), seed=0, subpolicy_kwargs=kwargs).add()
