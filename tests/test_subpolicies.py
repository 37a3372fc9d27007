"""The DDPG sub-goal learners of Box actions: gradient steps at the model's own train frequency, eq. 5 / 6 rewards
for the acting and the relabelled sub-goals, save / load, clear errors otherwise."""

import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_hhp.hierarchy.subpolicies import PerGoalLearners, SubpolicySet

OBS = spaces.Box(0.0, 1.0, (4,), np.float32)
ACTIONS = spaces.Box(-1.0, 1.0, (2,), np.float32)
SMALL = dict(policy_kwargs=dict(net_arch=[8]), buffer_size=100)


def _feed(subpolicy, steps: int) -> list[int]:
    """Observe ``steps`` random transitions; the model's update count after each."""
    rng = np.random.default_rng(0)
    counts = []
    for _ in range(steps):
        obs, next_obs = rng.random(4, dtype=np.float32), rng.random(4, dtype=np.float32)
        subpolicy.observe(obs, next_obs, rng.uniform(-1, 1, 2).astype(np.float32), float(rng.random()), False)
        counts.append(subpolicy.model._n_updates)
    return counts


@pytest.mark.parametrize("train_freq, gradient_steps", [(1, 1), (4, 1), (4, 2)])
def test_gradient_steps_follow_the_models_train_frequency(train_freq: int, gradient_steps: int) -> None:
    subpolicies = SubpolicySet(OBS, ACTIONS, seed=0, subpolicy_kwargs=dict(
        SMALL, train_freq=train_freq, gradient_steps=gradient_steps, learning_starts=8, batch_size=8))
    subpolicy = subpolicies.add()
    assert subpolicy.train_freq == train_freq
    counts = _feed(subpolicy, 40)
    # no update before the buffer holds learning_starts transitions, then gradient_steps every train_freq own steps
    expected = [gradient_steps * ((step // train_freq) - (7 // train_freq)) if step >= 8 else 0 for step in range(1, 41)]
    assert counts == expected
    assert subpolicy.num_steps == 40 and subpolicy.model.num_timesteps == 40


def test_the_paper_default_is_one_update_every_step_of_256x256_units_with_action_noise() -> None:
    subpolicy = SubpolicySet(OBS, ACTIONS, seed=0).add()
    model = subpolicy.model
    assert subpolicy.train_freq == 1 and model.gradient_steps == 1 and model.batch_size == 128
    assert [layer.out_features for layer in model.actor.mu if isinstance(layer, th.nn.Linear)] == [256, 256, 2]
    assert model.action_noise is not None
    obs = np.full(4, 0.5, np.float32)
    noisy = np.stack([subpolicy.act(obs) for _ in range(20)])
    assert np.ptp(noisy, axis=0).min() > 0 and ACTIONS.contains(noisy[0])  # explores around its greedy action
    greedy = subpolicy.act(obs, deterministic=True)
    np.testing.assert_array_equal(greedy, subpolicy.act(obs, deterministic=True))


@pytest.mark.parametrize("kwargs, match", [
    (dict(train_freq=(1, "episode")), "counts its own steps"),
    (dict(gradient_steps=-1), "gradient_steps >= 1"),
])
def test_a_train_frequency_a_subpolicy_cannot_follow_is_refused(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        SubpolicySet(OBS, ACTIONS, seed=0, subpolicy_kwargs={**SMALL, **kwargs}).add()


def test_discrete_actions_are_refused_with_the_learner_that_takes_them() -> None:
    with pytest.raises(ValueError, match="Box actions.*StackedDQN"):
        SubpolicySet(OBS, spaces.Discrete(3))


def per_goal_learners(**kwargs) -> PerGoalLearners:
    subpolicies = SubpolicySet(OBS, ACTIONS, seed=0, subpolicy_kwargs=dict(SMALL, learning_starts=2, batch_size=2))
    learners = PerGoalLearners(subpolicies, lambda key, goal_key: key == goal_key, alpha=0.5, **kwargs)
    for key in ("A", "B"):
        learners.add(key)
    return learners


def step(learners: PerGoalLearners, key: str, acting: int, intrinsic: float, terminated: bool = False) -> None:
    learners.observe(np.zeros((1, 4), np.float32), np.zeros((1, 2), np.float32), np.ones((1, 4), np.float32), [key],
                     np.array([terminated]), np.array([False]), np.array([False]), np.array([acting]),
                     np.array([intrinsic], np.float32))


@pytest.mark.parametrize("share", [True, False])
def test_the_acting_subgoal_learns_its_eq6_reward_and_the_others_store_theirs_relabelled(share: bool) -> None:
    """A step reaching "A" while "B" acts: B stores eq. 6's 0 + alpha r^i and takes its own step; with
    share_experience A stores +1 + alpha r^i, terminal for it; without, A stores nothing."""
    learners = per_goal_learners(share_experience=share)
    step(learners, "A", acting=1, intrinsic=0.4)
    a, b = learners.subpolicies[0], learners.subpolicies[1]
    assert b.num_steps == 1 and a.num_steps == 0
    assert b.model.replay_buffer.rewards[0, 0] == pytest.approx(0.5 * 0.4)
    assert not b.model.replay_buffer.dones[0, 0]
    if share:
        assert a.model.replay_buffer.pos == 1 and a.model.replay_buffer.rewards[0, 0] == pytest.approx(1 + 0.5 * 0.4)
        assert a.model.replay_buffer.dones[0, 0]  # done(s', A): terminal for A
    else:
        assert a.model.replay_buffer.pos == 0
    step(learners, "x", acting=1, intrinsic=0.0, terminated=True)  # the episode ends without B: -1 (eq. 5)
    assert b.model.replay_buffer.rewards[1, 0] == pytest.approx(-1.0) and b.model.replay_buffer.dones[1, 0]


def test_state_dict_round_trip_and_another_learners_state_is_refused() -> None:
    learners = per_goal_learners()
    for t in range(6):
        step(learners, "x", acting=t % 2, intrinsic=0.1)
    learners.record_outcome(0, True)
    restored = per_goal_learners()
    restored.load_state_dict(learners.state_dict())
    assert restored.goal_keys == ["A", "B"] and restored.success_rate(0) == 1.0 and restored.success_rate(1) is None
    for sub, back in zip(learners.subpolicies.policies, restored.subpolicies.policies):
        assert (back.num_steps, back.num_ticks) == (sub.num_steps, sub.num_ticks) == (3, 3)
        for name, value in sub.model.policy.state_dict().items():
            th.testing.assert_close(back.model.policy.state_dict()[name], value)
    obs = np.full((2, 4), 0.3, np.float32)
    np.testing.assert_array_equal(restored.act(np.array([0, 1]), obs, deterministic=True),
                                  learners.act(np.array([0, 1]), obs, deterministic=True))
    with pytest.raises(ValueError, match="not saved by PerGoalLearners"):
        per_goal_learners().load_state_dict({"format": "sb3_hhp.StackedDQN"})
