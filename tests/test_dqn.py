"""Tests of the sum tree, the prioritized replay buffer and DoubleDQN."""

import numpy as np
import pytest
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from scipy import stats
from stable_baselines3.common.buffers import NStepReplayBuffer
from stable_baselines3.common.envs import IdentityEnv
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import configure
from stable_baselines3.common.monitor import Monitor
from torch.nn import functional as F

from sb3_hhp.dqn.buffers import PrioritizedReplayBuffer, PrioritizedReplayBufferSamples
from sb3_hhp.dqn.dqn import DoubleDQN, double_q_target
from sb3_hhp.dqn.sum_tree import SumTree

th.set_num_threads(1)


# ----------------------------------------------------------------------------- sum tree


@pytest.mark.parametrize("capacity", [1, 5, 8, 13])
def test_sum_tree_totals(capacity: int) -> None:
    rng = np.random.default_rng(0)
    tree = SumTree(capacity)
    assert tree.total == 0.0
    priorities = rng.random(capacity) * 10
    priorities[0] = 0.0
    tree.update(np.arange(capacity), priorities)
    assert tree.total == pytest.approx(priorities.sum())
    assert tree.max_priority == pytest.approx(priorities.max())
    positive = priorities[priorities > 0]
    assert tree.min_priority == (pytest.approx(positive.min()) if positive.size else np.inf)
    np.testing.assert_allclose(tree.priorities(np.arange(capacity)), priorities)
    assert tree[capacity - 1] == pytest.approx(priorities[-1])
    # Partial update
    tree.update(np.array([capacity - 1]), 0.25)
    priorities[-1] = 0.25
    assert tree.total == pytest.approx(priorities.sum())
    assert tree.max_priority == pytest.approx(priorities.max())


def test_sum_tree_repeated_indices_last_wins() -> None:
    tree = SumTree(6)
    tree.update(np.array([1, 3, 1, 1, 3]), np.array([5.0, 2.0, 7.0, 4.0, 9.0]))
    expected = np.array([0.0, 4.0, 0.0, 9.0, 0.0, 0.0])
    np.testing.assert_allclose(tree.priorities(np.arange(6)), expected)
    assert tree.total == pytest.approx(13.0)
    # Same result as a sequence of single updates
    sequential = SumTree(6)
    for index, priority in zip([1, 3, 1, 1, 3], [5.0, 2.0, 7.0, 4.0, 9.0]):
        sequential.update(np.array([index]), np.array([priority]))
    np.testing.assert_allclose(sequential._sum, tree._sum)
    np.testing.assert_allclose(sequential._min, tree._min)
    np.testing.assert_allclose(sequential._max, tree._max)


def test_sum_tree_sampling_frequencies_follow_priorities() -> None:
    priorities = np.array([1.0, 2.0, 3.0, 4.0, 0.0, 5.0, 6.0])
    tree = SumTree(len(priorities))
    tree.update(np.arange(len(priorities)), priorities)
    rng = np.random.default_rng(42)
    samples = np.concatenate([tree.sample(64, rng)[0] for _ in range(200_000 // 64)])
    counts = np.bincount(samples, minlength=len(priorities))
    assert counts[4] == 0  # priority 0: never drawn
    expected = priorities / priorities.sum() * len(samples)
    positive = priorities > 0
    chi2 = ((counts[positive] - expected[positive]) ** 2 / expected[positive]).sum()
    assert chi2 < stats.chi2.ppf(0.999, df=positive.sum() - 1)
    np.testing.assert_allclose(counts / len(samples), priorities / priorities.sum(), atol=3e-3)


def test_sum_tree_sampling_is_stratified_and_returns_priorities() -> None:
    tree = SumTree(4)
    tree.update(np.arange(4), np.ones(4))
    indices, priorities = tree.sample(4, np.random.default_rng(0))
    # One draw per quarter of the total: every leaf exactly once, in order
    np.testing.assert_array_equal(indices, [0, 1, 2, 3])
    np.testing.assert_allclose(priorities, 1.0)


def test_sum_tree_invalid_arguments() -> None:
    with pytest.raises(ValueError, match="capacity"):
        SumTree(0)
    tree = SumTree(4)
    with pytest.raises(ValueError, match="finite and >= 0"):
        tree.update(np.array([0]), np.array([-1.0]))
    with pytest.raises(ValueError, match="finite and >= 0"):
        tree.update(np.array([0, 1]), np.array([1.0, np.nan]))
    with pytest.raises(ValueError, match="indices"):
        tree.update(np.array([4]), np.array([1.0]))
    with pytest.raises(ValueError, match="all 0"):
        tree.sample(2, np.random.default_rng(0))


# ----------------------------------------------------------------------- replay buffer


def _filled_buffer(n: int, buffer_size: int = 16, n_envs: int = 1, **kwargs) -> PrioritizedReplayBuffer:
    """A buffer whose transition number k has observation [k, env] and reward k."""
    buffer = PrioritizedReplayBuffer(
        buffer_size,
        spaces.Box(-np.inf, np.inf, (2,), np.float32),
        spaces.Discrete(3),
        device="cpu",
        n_envs=n_envs,
        **kwargs,
    )
    for k in range(n):
        obs = np.array([[k, e] for e in range(n_envs)], dtype=np.float32)
        buffer.add(obs, obs + 1, np.zeros(n_envs), np.full(n_envs, k, dtype=np.float32), np.zeros(n_envs), [{}] * n_envs)
    return buffer


def test_per_n_step_returns_by_hand() -> None:
    """Transition k (reward k) sums gamma^j r_{k+j} until a terminal (k = 4), a timeout (k = 8), the newest
    transition (k = 11) or n = 3 steps; next obs, done and the bootstrap discount gamma^m follow."""
    gamma, n = 0.9, 3
    buffer = PrioritizedReplayBuffer(32, spaces.Box(-np.inf, np.inf, (1,), np.float32), spaces.Discrete(2),
                                     device="cpu", n_steps=n, gamma=gamma)
    for k in range(12):
        done = k in (4, 8)
        info = {"TimeLimit.truncated": k == 8}
        buffer.add(np.array([[k]], np.float32), np.array([[k + 100]], np.float32), np.zeros(1), np.array([k], np.float32),
                   np.array([done]), [info])
    drawn: dict[int, tuple] = {}
    for _ in range(50):
        batch = buffer.sample(64)
        for row, index in enumerate(batch.indices):
            drawn[int(index)] = (float(batch.rewards[row, 0]), float(batch.next_observations[row, 0]),
                                 float(batch.dones[row, 0]), float(batch.discounts[row, 0]))
    assert sorted(drawn) == list(range(12))
    for k in range(12):
        m = 1
        while m < n and (k + m - 1) not in (4, 8) and k + m - 1 < 11:
            m += 1
        expected_return = sum(gamma**j * (k + j) for j in range(m))
        last = k + m - 1
        expected = (expected_return, last + 100, 1.0 if last == 4 else 0.0, gamma**m)
        np.testing.assert_allclose(drawn[k], expected, rtol=1e-5, err_msg=f"transition {k}")


def test_per_n_step_returns_stop_at_off_policy_transitions() -> None:
    """A transition stored with info["off_policy"] (another policy acted) is a one-step transition, and an
    own transition's n-step return ends before the first off-policy one."""
    gamma, n = 0.5, 4
    buffer = PrioritizedReplayBuffer(32, spaces.Box(-np.inf, np.inf, (1,), np.float32), spaces.Discrete(2),
                                     device="cpu", n_steps=n, gamma=gamma)
    off_policy = {3, 4, 8}
    for k in range(12):
        buffer.add(np.array([[k]], np.float32), np.array([[k + 100]], np.float32), np.zeros(1),
                   np.array([2.0**k], np.float32), np.array([False]), [{"off_policy": k in off_policy}])
    returns, last_rows, discounts = buffer._n_step_returns(np.arange(12), np.zeros(12, dtype=int), None)
    for k in range(12):
        m = 1
        if k not in off_policy:
            while m < n and (k + m) not in off_policy and k + m <= 11:
                m += 1
        assert last_rows[k] == k + m - 1, f"transition {k}"
        assert returns[k, 0] == pytest.approx(sum(gamma**j * 2.0 ** (k + j) for j in range(m))), f"transition {k}"
        assert discounts[k, 0] == pytest.approx(gamma**m), f"transition {k}"
    # by hand: 0 sums 0..2 (stops before 3), 3 and 4 stand alone, 5 sums 5..7, 9 sums 9..11 (the newest)
    assert list(last_rows[[0, 3, 4, 5, 9]]) == [2, 3, 4, 7, 11]
    buffer.reset()
    assert not buffer.off_policy.any()


def test_per_behaviour_returns_run_over_off_policy_transitions() -> None:
    """With off_policy_lower_bound the buffer also samples the n-step return along the stored behaviour:
    off-policy transitions do not stop it, terminals, the newest transition and n still do."""
    gamma, n = 0.5, 4
    buffer = PrioritizedReplayBuffer(32, spaces.Box(-np.inf, np.inf, (1,), np.float32), spaces.Discrete(2),
                                     device="cpu", n_steps=n, gamma=gamma, off_policy_lower_bound=True)
    off_policy, terminal = {3, 4, 8}, {6}
    for k in range(12):
        buffer.add(np.array([[k]], np.float32), np.array([[k + 100]], np.float32), np.zeros(1),
                   np.array([2.0**k], np.float32), np.array([k in terminal]), [{"off_policy": k in off_policy}])
    returns, last_rows, discounts = buffer._n_step_returns(np.arange(12), np.zeros(12, dtype=int), None, behaviour=True)
    # by hand: 0 sums 0..3 (n), 3 sums 3..6 (through 3, 4; stops at the terminal 6), 5 sums 5..6, 7 sums 7..10,
    # 8 sums 8..11, 10 sums 10..11 (the newest)
    expected_last = {0: 3, 3: 6, 4: 6, 5: 6, 6: 6, 7: 10, 8: 11, 10: 11}
    for k, last in expected_last.items():
        m = last - k + 1
        assert last_rows[k] == last, f"transition {k}"
        assert returns[k, 0] == pytest.approx(sum(gamma**j * 2.0 ** (k + j) for j in range(m))), f"transition {k}"
        assert discounts[k, 0] == pytest.approx(gamma**m), f"transition {k}"
    batch = buffer.sample(64)
    rows = batch.indices
    assert np.allclose(batch.behaviour_next_observations.numpy()[:, 0], last_rows[rows] + 100)
    assert np.array_equal(batch.behaviour_dones.numpy()[:, 0], np.isin(last_rows[rows], list(terminal)).astype(np.float32))
    assert np.allclose(batch.behaviour_rewards.numpy(), returns[rows])
    own = buffer._n_step_returns(rows, np.zeros(len(rows), dtype=int), None)  # the usual target still stops
    assert np.allclose(batch.rewards.numpy(), own[0])
    with pytest.raises(ValueError, match="n_steps > 1"):
        PrioritizedReplayBuffer(8, spaces.Box(-1, 1, (1,), np.float32), spaces.Discrete(2), off_policy_lower_bound=True)


def test_double_dqn_target_is_raised_to_the_behaviour_return(monkeypatch: pytest.MonkeyPatch) -> None:
    """Optimality tightening: the TD target is max(double-Q target, behaviour n-step target), so a relabelled
    transition whose behaviour reached the reward two steps later learns it at once."""
    model = DoubleDQN("MlpPolicy", "CartPole-v1", n_steps=3, gamma=0.5, learning_starts=0, batch_size=16,
                      buffer_size=100, policy_kwargs=dict(net_arch=[8]), seed=0, device="cpu",
                      replay_buffer_kwargs={"off_policy_lower_bound": True})
    model.set_logger(configure(None, []))
    buffer = model.replay_buffer
    obs = np.random.default_rng(0).normal(size=(4, 1, 4)).astype(np.float32)
    # two off-policy steps with reward 0, then an own step with reward 1 that ends the episode
    for k, (reward, done, off) in enumerate([(0.0, False, True), (0.0, False, True), (1.0, True, False)]):
        buffer.add(obs[k], obs[k + 1], np.zeros(1), np.array([reward], np.float32), np.array([done]), [{"off_policy": off}])
    seen: dict = {}
    sample, loss = buffer.sample, F.smooth_l1_loss

    def keep_indices(batch_size, env=None):
        batch = sample(batch_size, env)
        seen["indices"] = batch.indices
        return batch

    def keep_targets(current, target, reduction="mean"):
        seen["targets"] = target.detach().numpy()[:, 0]
        return loss(current, target, reduction=reduction)

    monkeypatch.setattr(buffer, "sample", keep_indices)
    monkeypatch.setattr(F, "smooth_l1_loss", keep_targets)
    with th.no_grad():
        bootstrap = [model.q_net_target(th.as_tensor(obs[k])).numpy()[0, model.q_net(th.as_tensor(obs[k])).argmax()]
                     for k in (1, 2)]
    model.train(gradient_steps=1, batch_size=16)
    expected = {0: max(0.25, 0.5 * bootstrap[0]), 1: max(0.5, 0.5 * bootstrap[1]), 2: 1.0}  # behaviour: 0.25, 0.5, 1
    assert set(seen["indices"]) == {0, 1, 2}
    for index, target in zip(seen["indices"], seen["targets"]):
        assert target == pytest.approx(expected[int(index)], abs=1e-6), f"transition {index}"
    assert max(0.5 * bootstrap[0], 0.5 * bootstrap[1]) < 0.25  # the behaviour return is what raised them
    model_without = DoubleDQN("MlpPolicy", "CartPole-v1", n_steps=3, seed=0, device="cpu", buffer_size=100)
    assert model_without.replay_buffer.off_policy_lower_bound is False


def test_per_n_steps_invalid_arguments() -> None:
    space, actions = spaces.Box(-1, 1, (1,), np.float32), spaces.Discrete(2)
    with pytest.raises(ValueError, match="n_steps"):
        PrioritizedReplayBuffer(8, space, actions, n_steps=0)
    with pytest.raises(ValueError, match="optimize_memory_usage"):
        PrioritizedReplayBuffer(8, space, actions, n_steps=3, optimize_memory_usage=True)


def test_double_dqn_n_steps_under_per() -> None:
    model = _model(dim=2, n_steps=3)
    assert isinstance(model.replay_buffer, PrioritizedReplayBuffer) and model.replay_buffer.n_steps == 3
    model.learn(150)
    assert model._n_updates == 50


def test_per_new_transitions_get_max_priority() -> None:
    alpha, eps = 0.6, 1e-6
    buffer = _filled_buffer(5, alpha=alpha, epsilon=eps)
    np.testing.assert_allclose(buffer.tree.priorities(np.arange(5)), 1.0)
    td = np.array([0.5, -2.0, 0.0, 1.0, -3.0])
    buffer.update_priorities(np.arange(5), td)
    # p_i = |delta_i| + epsilon, stored as p_i^alpha
    expected = (np.abs(td) + eps) ** alpha
    np.testing.assert_allclose(buffer.tree.priorities(np.arange(5)), expected)
    obs = np.zeros((1, 2), dtype=np.float32)
    buffer.add(obs, obs, np.zeros(1), np.zeros(1), np.zeros(1), [{}])
    assert buffer.tree[5] == pytest.approx(expected.max())


def test_per_update_priorities_accepts_tensors() -> None:
    buffer = _filled_buffer(3, alpha=1.0, epsilon=0.1)
    buffer.update_priorities(np.array([0, 2]), th.tensor([[-0.5], [2.0]]))
    np.testing.assert_allclose(buffer.tree.priorities(np.arange(3)), [0.6, 1.0, 2.1])
    with pytest.raises(ValueError, match="one value per index"):
        buffer.update_priorities(np.array([0, 1]), np.array([1.0]))


def test_per_sampling_probabilities_and_importance_weights() -> None:
    alpha, beta, eps = 0.6, 0.4, 1e-6
    n = 6
    buffer = _filled_buffer(n, buffer_size=10, alpha=alpha, beta=beta, epsilon=eps)
    td = np.array([0.1, 1.0, 2.0, 0.0, 5.0, 0.5])
    buffer.update_priorities(np.arange(n), td)

    p_alpha = (np.abs(td) + eps) ** alpha
    probabilities = p_alpha / p_alpha.sum()  # P(i) = p_i^alpha / sum_k p_k^alpha
    raw_weights = (n * probabilities) ** (-beta)  # (N * P(i))^-beta
    expected_weights = raw_weights / raw_weights.max()

    counts = np.zeros(n)
    for _ in range(200_000 // 250):
        batch = buffer.sample(250)
        assert isinstance(batch, PrioritizedReplayBufferSamples)
        assert batch.weights.shape == (250, 1)
        # The sampled rows are the transitions the indices name
        np.testing.assert_array_equal(batch.observations[:, 0].numpy(), batch.indices)
        np.testing.assert_array_equal(batch.rewards[:, 0].numpy(), batch.indices)
        np.testing.assert_allclose(batch.weights[:, 0].numpy(), expected_weights[batch.indices], rtol=1e-5)
        counts += np.bincount(batch.indices, minlength=n)
    np.testing.assert_allclose(counts / counts.sum(), probabilities, atol=3e-3)
    assert counts[3] > 0  # |delta| = 0 still has priority epsilon^alpha > 0


def test_per_alpha_zero_is_uniform_with_unit_weights() -> None:
    buffer = _filled_buffer(4, alpha=0.0)
    buffer.update_priorities(np.arange(4), np.array([0.0, 1.0, 10.0, 100.0]))
    batch = buffer.sample(64)
    np.testing.assert_allclose(batch.weights.numpy(), 1.0)
    np.testing.assert_array_equal(np.bincount(batch.indices, minlength=4), [16, 16, 16, 16])


def test_per_several_envs() -> None:
    buffer = _filled_buffer(4, buffer_size=8, n_envs=2)
    batch = buffer.sample(200)
    # index = pos * n_envs + env, observation = [pos, env]
    np.testing.assert_array_equal(batch.observations[:, 0].numpy(), batch.indices // 2)
    np.testing.assert_array_equal(batch.observations[:, 1].numpy(), batch.indices % 2)
    np.testing.assert_array_equal(batch.next_observations.numpy(), batch.observations.numpy() + 1)
    assert set(batch.indices.tolist()) == set(range(8))


def test_per_optimize_memory_never_samples_invalid_transition() -> None:
    buffer = _filled_buffer(7, buffer_size=4, optimize_memory_usage=True, handle_timeout_termination=False)
    assert buffer.full and buffer.pos == 3
    assert buffer.tree[3] == 0.0
    for _ in range(20):
        batch = buffer.sample(32)
        assert 3 not in batch.indices
        # next observation of transition k is the observation stored after it
        np.testing.assert_array_equal(batch.next_observations[:, 0].numpy(), batch.observations[:, 0].numpy() + 1)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(alpha=1.5), "alpha"),
        (dict(alpha=-0.1), "alpha"),
        (dict(beta=1.1), "beta"),
        (dict(epsilon=0.0), "epsilon"),
        (dict(buffer_size=0), "buffer_size"),
    ],
)
def test_per_invalid_arguments(kwargs: dict, match: str) -> None:
    args = dict(buffer_size=8, observation_space=spaces.Box(0, 1, (2,)), action_space=spaces.Discrete(2))
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        PrioritizedReplayBuffer(**args)


def test_per_rejects_dict_observations_and_empty_sampling() -> None:
    with pytest.raises(ValueError, match="Dict"):
        PrioritizedReplayBuffer(8, spaces.Dict({"a": spaces.Box(0, 1, (2,))}), spaces.Discrete(2))
    buffer = PrioritizedReplayBuffer(8, spaces.Box(0, 1, (2,)), spaces.Discrete(2), device="cpu")
    with pytest.raises(ValueError, match="empty"):
        buffer.sample(4)


# ---------------------------------------------------------------------- double Q target


def test_double_q_target_by_hand() -> None:
    next_q_online = th.tensor([[1.0, 5.0, 2.0], [3.0, 0.0, 1.0], [0.0, 1.0, 4.0]])
    next_q_target = th.tensor([[4.0, 1.0, 9.0], [2.0, 7.0, 0.0], [3.0, 2.0, 6.0]])
    rewards = th.tensor([[1.0], [0.5], [-1.0]])
    dones = th.tensor([[0.0], [1.0], [0.0]])
    gamma = 0.9
    target = double_q_target(next_q_online, next_q_target, rewards, dones, gamma)
    # row 0: online argmax = 1 -> Q_target = 1 (plain max would use 9)
    # row 1: terminal -> reward only
    # row 2: online argmax = 2 -> Q_target = 6 (same as plain max here)
    expected = th.tensor([[1.0 + 0.9 * 1.0], [0.5], [-1.0 + 0.9 * 6.0]])
    th.testing.assert_close(target, expected)
    plain = double_q_target(next_q_target, next_q_target, rewards, dones, gamma)
    th.testing.assert_close(plain, th.tensor([[1.0 + 0.9 * 9.0], [0.5], [-1.0 + 0.9 * 6.0]]))
    assert not th.allclose(target, plain)


def test_double_q_target_respects_valid_actions() -> None:
    next_q_online = th.tensor([[1.0, 5.0, 2.0], [0.0, 1.0, 4.0]])
    next_q_target = th.tensor([[4.0, 1.0, 9.0], [3.0, 2.0, 6.0]])
    rewards = th.zeros(2, 1)
    dones = th.zeros(2, 1)
    mask = th.tensor([True, False, True])
    # row 0: argmax over {0, 2} of online -> 2 -> 9; row 1: argmax over {0, 2} -> 2 -> 6
    target = double_q_target(next_q_online, next_q_target, rewards, dones, 0.5, valid_actions=mask)
    th.testing.assert_close(target, th.tensor([[4.5], [3.0]]))
    # per-row mask: row 1 may only take action 0 or 1 -> online argmax 1 -> Q_target 2
    row_mask = th.tensor([[True, False, True], [True, True, False]])
    target = double_q_target(next_q_online, next_q_target, rewards, dones, 0.5, valid_actions=row_mask)
    th.testing.assert_close(target, th.tensor([[4.5], [1.0]]))
    # per-sample discounts (n-step returns)
    target = double_q_target(next_q_online, next_q_target, rewards, dones, th.tensor([[1.0], [0.0]]))
    th.testing.assert_close(target, th.tensor([[1.0], [0.0]]))


# --------------------------------------------------------------------------- DoubleDQN


def _model(dim: int = 4, **kwargs) -> DoubleDQN:
    params = dict(
        learning_starts=100,
        learning_rate=1e-3,
        batch_size=32,
        train_freq=1,
        target_update_interval=100,
        exploration_fraction=0.3,
        gamma=0.0,
        policy_kwargs=dict(net_arch=[32]),
        seed=0,
        device="cpu",
        buffer_size=1000,
    )
    params.update(kwargs)
    return DoubleDQN("MlpPolicy", IdentityEnv(dim=dim), **params)


def test_double_dqn_learns_identity_env() -> None:
    model = _model(dim=4)
    assert isinstance(model.replay_buffer, PrioritizedReplayBuffer)
    assert model.replay_buffer.alpha == 0.6 and model.replay_buffer.beta == 0.4
    model.learn(2000)
    mean_reward, _ = evaluate_policy(model, Monitor(IdentityEnv(dim=4)), n_eval_episodes=3)
    assert mean_reward >= 90  # 100 steps per episode, +1 per correct action


def _record_batches(model: DoubleDQN) -> list:
    batches = []
    sample = model.replay_buffer.sample

    def recording_sample(*args, **kwargs):
        batch = sample(*args, **kwargs)
        batches.append(batch)
        return batch

    model.replay_buffer.sample = recording_sample
    return batches


@pytest.mark.parametrize("double_q", [True, False])
def test_train_step_matches_hand_computation(double_q: bool) -> None:
    """One gradient step with lr = 0: the logged loss is the IS-weighted Huber loss of the
    (double) Q target, and the priorities become |delta| + eps."""
    model = _model(dim=3, learning_rate=0.0, gamma=0.9, double_q=double_q, learning_starts=0, gradient_steps=0)
    model.set_logger(configure(None, []))
    model.learn(30)  # fills the buffer, no training (gradient_steps=0)
    # Make the target network differ from the online one so that double Q matters
    with th.no_grad():
        for param in model.q_net_target.parameters():
            param.add_(th.randn_like(param))
    buffer = model.replay_buffer
    buffer.update_priorities(np.arange(30), np.linspace(0.0, 3.0, 30))
    batches = _record_batches(model)
    model.train(gradient_steps=1, batch_size=16)
    batch = batches[0]

    with th.no_grad():
        q_online_next = model.q_net(batch.next_observations)
        q_target_next = model.q_net_target(batch.next_observations)
        if double_q:
            next_actions = q_online_next.argmax(dim=1)
        else:
            next_actions = q_target_next.argmax(dim=1)
        next_values = q_target_next[th.arange(16), next_actions].reshape(-1, 1)
        targets = batch.rewards + 0.9 * (1 - batch.dones) * next_values
        current = model.q_net(batch.observations)[th.arange(16), batch.actions[:, 0].long()].reshape(-1, 1)
        delta = targets - current
        huber = th.where(delta.abs() < 1, 0.5 * delta**2, delta.abs() - 0.5)
        expected_loss = (batch.weights * huber).mean().item()
    assert model.logger.name_to_value["train/loss"] == pytest.approx(expected_loss, rel=1e-5)
    expected_priorities = (np.abs(delta.numpy()[:, 0]) + 1e-6) ** 0.6
    # For repeated indices the last update wins: compare per unique index
    last = {int(i): p for i, p in zip(batch.indices, expected_priorities)}
    np.testing.assert_allclose(buffer.tree.priorities(np.array(list(last))), list(last.values()), rtol=1e-5)


def test_rewards_hook_is_used_in_target() -> None:
    class ZeroReward(DoubleDQN):
        def _rewards(self, replay_data) -> th.Tensor:
            return th.zeros_like(replay_data.rewards)

    model = ZeroReward("MlpPolicy", IdentityEnv(dim=3), learning_rate=0.0, gamma=0.0, learning_starts=0,
                       gradient_steps=0, policy_kwargs=dict(net_arch=[8]), seed=1, device="cpu")
    model.set_logger(configure(None, []))
    model.learn(20)
    batches = _record_batches(model)
    model.train(gradient_steps=1, batch_size=8)
    batch = batches[0]
    assert batch.rewards.abs().sum() > 0  # IdentityEnv pays 1 for a correct action
    with th.no_grad():
        current = model.q_net(batch.observations).gather(1, batch.actions.long())
        expected = (batch.weights * F.smooth_l1_loss(current, th.zeros_like(current), reduction="none")).mean().item()
    assert model.logger.name_to_value["train/loss"] == pytest.approx(expected, rel=1e-5)


def test_valid_actions_restrict_predict_and_exploration() -> None:
    model = _model(dim=4, learning_starts=50)
    obs = np.array([2])
    greedy = model.predict(obs, deterministic=True)[0].item()
    mask = np.ones(4, dtype=bool)
    mask[greedy] = False
    model.valid_actions = mask
    with th.no_grad():
        q_values = model.q_net(th.as_tensor(obs)).numpy()[0]
    best_valid = int(np.flatnonzero(mask)[np.argmax(q_values[mask])])
    assert model.predict(obs, deterministic=True)[0].item() == best_valid
    vec_actions, _ = model.predict(np.array([0, 1, 2, 3]), deterministic=True)
    assert vec_actions.shape == (4,) and mask[vec_actions].all()
    # epsilon-greedy: only valid actions, all of them reached
    model.exploration_rate = 1.0
    random_actions = np.concatenate([model.predict(np.array([0, 1, 2, 3]))[0] for _ in range(50)])
    assert set(random_actions.tolist()) == set(np.flatnonzero(mask).tolist())
    # warm-up actions (before learning_starts) too
    model.learn(40)
    stored = model.replay_buffer.actions[: model.replay_buffer.pos, 0, 0].astype(int)
    assert mask[stored].all()


class _EvenOddMaskDQN(DoubleDQN):
    """Allows only actions of the parity of the observation, state by state."""

    def action_mask(self, observations):
        obs = np.asarray(observations).reshape(-1)
        return (np.arange(int(self.action_space.n))[None, :] % 2) == (obs[:, None].astype(int) % 2)


def test_state_action_mask_restricts_predict_exploration_warmup_and_target() -> None:
    model = _EvenOddMaskDQN("MlpPolicy", IdentityEnv(dim=4), learning_starts=60, batch_size=16, train_freq=1,
                            gamma=0.9, policy_kwargs=dict(net_arch=[16]), seed=0, device="cpu", buffer_size=500)
    observations = np.array([0, 1, 2, 3])
    greedy, _ = model.predict(observations, deterministic=True)
    assert (greedy % 2 == observations % 2).all()
    model.exploration_rate = 1.0
    explored = np.stack([model.predict(observations)[0] for _ in range(40)])
    assert (explored % 2 == observations % 2).all()
    assert set(explored[:, 0].tolist()) == {0, 2}
    single, _ = model.predict(np.array(3))
    assert int(single) % 2 == 1
    model.learn(50)  # warm-up only: random actions within each state's mask
    stored_obs = model.replay_buffer.observations[: model.replay_buffer.pos, 0, 0].astype(int)
    stored_actions = model.replay_buffer.actions[: model.replay_buffer.pos, 0, 0].astype(int)
    assert (stored_actions % 2 == stored_obs % 2).all()
    # the TD target takes the max over each next state's own mask
    batches = _record_batches(model)
    seen = []
    original = double_q_target

    import sb3_hhp.dqn.dqn as dqn_module

    def recording_target(*args, valid_actions=None, **kwargs):
        seen.append(valid_actions)
        return original(*args, valid_actions=valid_actions, **kwargs)

    dqn_module.double_q_target = recording_target
    try:
        model.learn(20, reset_num_timesteps=False)
    finally:
        dqn_module.double_q_target = original
    assert seen and batches
    next_obs = batches[-1].next_observations.numpy().reshape(-1).astype(int)
    expected = (np.arange(4)[None, :] % 2) == (next_obs[:, None] % 2)
    np.testing.assert_array_equal(seen[-1].numpy(), expected)


def test_valid_actions_validation() -> None:
    model = _model(dim=3)
    with pytest.raises(ValueError, match="shape"):
        model.valid_actions = np.ones(4, dtype=bool)
    with pytest.raises(ValueError, match="boolean"):
        model.valid_actions = np.ones(3)
    with pytest.raises(ValueError, match="at least one"):
        model.valid_actions = np.zeros(3, dtype=bool)


def test_resize_action_space_keeps_q_values_and_keeps_learning() -> None:
    model = _model(dim=3, learning_starts=20)
    model.learn(100)
    model.valid_actions = np.array([True, False, True])
    obs = th.arange(3)
    with th.no_grad():
        old_q, old_q_target = model.q_net(obs).clone(), model.q_net_target(obs).clone()
    buffer = model.replay_buffer
    model.resize_action_space(5)
    assert model.action_space.n == 5 and model.policy.action_space.n == 5
    assert model.replay_buffer is buffer
    np.testing.assert_array_equal(model.valid_actions, [True, False, True, True, True])
    with th.no_grad():
        new_q, new_q_target = model.q_net(obs), model.q_net_target(obs)
    assert new_q.shape == (3, 5)
    th.testing.assert_close(new_q[:, :3], old_q)
    th.testing.assert_close(new_q_target[:, :3], old_q_target)
    # The optimizer trains the new network
    optimizer_params = {id(p) for group in model.policy.optimizer.param_groups for p in group["params"]}
    assert optimizer_params == {id(p) for p in model.q_net.parameters()}
    # Learning continues with the old replay buffer and new actions
    buffer.add(np.array([0]), np.array([1]), np.array([4]), np.array([1.0]), np.array([0.0]), [{}])
    before = [p.detach().clone() for p in model.q_net.parameters()]
    model.train(gradient_steps=3, batch_size=16)
    assert any(not th.equal(b, p) for b, p in zip(before, model.q_net.parameters()))
    model.exploration_rate = 1.0
    assert set(np.concatenate([model.predict(np.array([0, 1, 2]))[0] for _ in range(30)]).tolist()) == {0, 2, 3, 4}
    with pytest.raises(ValueError, match="n_actions"):
        model.resize_action_space(4)


def test_save_load(tmp_path) -> None:
    model = _model(dim=3, learning_starts=20, double_q=False, prioritized_replay_alpha=0.5)
    model.learn(60)
    model.resize_action_space(4)
    model.valid_actions = np.array([True, True, False, True])
    obs = np.array([0, 1, 2])
    actions, _ = model.predict(obs, deterministic=True)
    model.save(tmp_path / "ddqn.zip")
    loaded = DoubleDQN.load(tmp_path / "ddqn.zip", device="cpu")
    assert loaded.double_q is False and loaded.prioritized_replay_alpha == 0.5
    assert loaded.action_space.n == 4
    np.testing.assert_array_equal(loaded.valid_actions, model.valid_actions)
    assert isinstance(loaded.replay_buffer, PrioritizedReplayBuffer) and loaded.replay_buffer.alpha == 0.5
    with th.no_grad():
        th.testing.assert_close(loaded.q_net(th.as_tensor(obs)), model.q_net(th.as_tensor(obs)))
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], actions)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(prioritized_replay_alpha=1.5), "prioritized_replay_alpha"),
        (dict(prioritized_replay_beta=-0.1), "prioritized_replay_beta"),
        (dict(prioritized_replay_eps=0.0), "prioritized_replay_eps"),
        (dict(double_q="yes"), "double_q"),
        (dict(prioritized_replay=1), "prioritized_replay"),
    ],
)
def test_double_dqn_invalid_arguments(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        _model(dim=2, **kwargs)


def test_without_prioritized_replay_uses_sb3_buffer() -> None:
    model = _model(dim=2, prioritized_replay=False, n_steps=2)
    assert type(model.replay_buffer) is NStepReplayBuffer
    model.learn(150)
    assert model._n_updates == 50
    model.set_logger(configure(None, []))
    model.train(gradient_steps=2, batch_size=8)
    assert np.isfinite(model.logger.name_to_value["train/loss"])
    assert "train/is_weight" not in model.logger.name_to_value
