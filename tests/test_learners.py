"""The shared replay (eq. 5 and 6 computed when a batch is drawn, n-step returns, the lower bound, per-sub-goal
priorities) and the stacked sub-goal learners (one grouped Double DQN update equal to SB3's, sub-goal by sub-goal)."""

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from torch.nn import functional as F

from sb3_hhp.hierarchy.encoders import Overview
from sb3_hhp.hierarchy.heads import SharedHeadsDQN
from sb3_hhp.hierarchy.learners import StackedDQN
from sb3_hhp.hierarchy.replay import GoalBatch, GoalTrees, SharedReplay

OBS = spaces.Box(0, 255, (3,), np.uint8)
ACTIONS = spaces.Discrete(3)


def equal_keys(key, goal_key) -> bool:
    return key == goal_key


def fill(replay: SharedReplay, keys: list, acting: list, terminated=None, truncated=None, gave_up=None, intrinsic=None) -> None:
    n = len(keys)
    terminated = terminated or [False] * n
    truncated = truncated or [False] * n
    gave_up = gave_up or [False] * n
    intrinsic = intrinsic if intrinsic is not None else [0.0] * n
    for t in range(n):
        replay.add(np.full((1, 3), t, np.uint8), np.array([t % 3]), np.full((1, 3), t + 1, np.uint8),
                   np.array([replay.key_id(keys[t])]), np.array([terminated[t]]), np.array([truncated[t]]),
                   np.array([gave_up[t]]), np.array([acting[t]]), np.array([intrinsic[t]], np.float32))


def test_eq5_and_eq6_are_computed_for_each_subgoal_when_drawn() -> None:
    replay = SharedReplay(16, OBS, ACTIONS, equal_keys, alpha=0.5)
    replay.add_goal("A")
    replay.add_goal("B")
    intrinsic = [0.2, 0.4, 0.6, 0.8, 1.0]
    fill(replay, ["x", "A", "x", "B", "x"], acting=[0, 0, 1, 1, 1], terminated=[False, False, False, False, True],
         intrinsic=intrinsic)
    rows, cols = np.arange(5), np.zeros(5, dtype=int)
    r_a, terminal_a, cut_a = replay.rewards(rows, cols, np.zeros(5, dtype=int))
    r_b, terminal_b, _ = replay.rewards(rows, cols, np.ones(5, dtype=int))
    # eq. 5: +1 where done(s', g), -1 where the episode terminated without it, else 0; eq. 6 adds alpha * r^i
    np.testing.assert_allclose(r_a, np.array([0, 1, 0, 0, -1]) + 0.5 * np.array(intrinsic), rtol=1e-6)
    np.testing.assert_allclose(r_b, np.array([0, 0, 0, 1, -1]) + 0.5 * np.array(intrinsic), rtol=1e-6)
    assert terminal_a.tolist() == [False, True, False, False, True]
    assert terminal_b.tolist() == [False, False, False, True, True]
    assert not cut_a.any()


def test_a_give_up_cuts_only_the_acting_subgoal_and_a_time_limit_cuts_all() -> None:
    replay = SharedReplay(16, OBS, ACTIONS, equal_keys)
    replay.add_goal("A")
    replay.add_goal("B")
    fill(replay, ["x", "x", "x"], acting=[1, 1, 0], gave_up=[False, True, False], truncated=[False, False, True])
    rows, cols = np.arange(3), np.zeros(3, dtype=int)
    assert replay.rewards(rows, cols, np.zeros(3, dtype=int))[2].tolist() == [False, False, True]
    assert replay.rewards(rows, cols, np.ones(3, dtype=int))[2].tolist() == [False, True, True]


def test_n_step_returns_follow_the_subgoals_own_behaviour_and_the_lower_bound_all_of_it() -> None:
    gamma = 0.5
    replay = SharedReplay(16, OBS, ACTIONS, equal_keys, alpha=1.0, gamma=gamma, n_steps=3, lower_bound=True)
    replay.add_goal("A")
    replay.add_goal("B")
    r_i = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0]
    fill(replay, ["x", "x", "B", "x", "x", "x", "x"], acting=[1, 1, 1, 0, 0, 1, 1], intrinsic=r_i)
    rows = np.array([[0, 3], [0, 3]])  # (T=2 sub-goals, B=2 draws)
    cols = np.zeros_like(rows)
    goals = np.array([[1], [0]])
    returns, last, discounts, dones = replay._n_step(rows, cols, goals, own=True)
    # sub-goal B from row 0: its own steps 0, 1, 2, stopped by done(s', B) at row 2
    assert returns[0, 0] == pytest.approx(1 + gamma * 2 + gamma**2 * (4 + 1))
    assert (last[0, 0], discounts[0, 0], dones[0, 0]) == (2, gamma**3, 1.0)
    # sub-goal B from row 3: A acted there, a one-step transition for B
    assert returns[0, 1] == pytest.approx(8) and (last[0, 1], discounts[0, 1], dones[0, 1]) == (3, gamma, 0.0)
    # sub-goal A from row 0: B acted: one step; from row 3: its own steps 3, 4, up to where B acts again
    assert returns[1, 0] == pytest.approx(1) and last[1, 0] == 0
    assert returns[1, 1] == pytest.approx(8 + gamma * 16) and (last[1, 1], discounts[1, 1]) == (4, gamma**2)
    # the lower bound runs along the stored behaviour whoever acted: A from row 0 over rows 0, 1, 2
    b_returns, b_last, b_discounts, _ = replay._n_step(rows, cols, goals, own=False)
    assert b_returns[1, 0] == pytest.approx(1 + gamma * 2 + gamma**2 * 4) and (b_last[1, 0], b_discounts[1, 0]) == (2, gamma**3)
    batch = replay.sample(np.array([0, 1]), 4)
    assert batch.returns.shape == (2, 4) and batch.behaviour_returns.shape == (2, 4)
    assert batch.observations.dtype == np.uint8  # stored in the observation space's own dtype


def test_a_new_subgoal_learns_from_what_was_stored_before_it_and_only_its_own_without_sharing() -> None:
    shared = SharedReplay(16, OBS, ACTIONS, equal_keys)
    own_only = SharedReplay(16, OBS, ACTIONS, equal_keys, share_experience=False)
    for replay in (shared, own_only):
        replay.add_goal("A")
        fill(replay, ["x"] * 6, acting=[0, 0, -1, -1, 0, -1])
        replay.add_goal("B")  # found late
    assert shared.trees.total(np.array([1]))[0] == pytest.approx(6.0)  # every stored step, at priority 1
    assert own_only.trees.total(np.array([1]))[0] == 0.0  # it never acted
    drawn = own_only.sample(np.array([0]), 64).leaves
    assert set(drawn.ravel().tolist()) <= {0, 1, 4}


def test_goal_trees_draw_in_proportion_to_each_trees_priorities() -> None:
    trees = GoalTrees(2, 5)
    trees.add(np.arange(5), np.array([True, True]))
    trees.update(np.array([0, 1]), np.array([[0, 1, 2, 3, 4], [0, 1, 2, 3, 4]]),
                 np.array([[1.0, 2.0, 3.0, 4.0, 0.0], [0.0, 0.0, 0.0, 0.0, 5.0]]))
    np.testing.assert_allclose(trees.total(np.array([0, 1])), [10.0, 5.0])
    leaves, probabilities = trees.sample(np.array([0, 1]), 20_000, np.random.default_rng(0))
    counts = np.bincount(leaves[0], minlength=5) / 20_000
    np.testing.assert_allclose(counts, [0.1, 0.2, 0.3, 0.4, 0.0], atol=0.01)
    assert (leaves[1] == 4).all() and np.allclose(probabilities[1], 1.0)


def test_goal_trees_refresh_ancestors_lazily_to_the_sums_of_a_rebuilt_tree() -> None:
    """New leaves added one run at a time (the usual case) and scattered (a wrap-around, several runs pending):
    after the lazy refresh every node is the sum of its two children, as in a tree summed bottom-up."""
    rng = np.random.default_rng(0)
    trees = GoalTrees(3, 40)
    for start in [0, 8, 16, 24, 32, 0, 8]:  # runs of 8 leaves, the last two written over the first (wrap-around)
        trees.add(np.arange(start, start + 8), np.array([True, True, False]))
        if start == 16:  # priorities set between adds, then scattered leaves pending with a run
            trees.update(np.array([0, 1]), rng.integers(0, 24, (2, 5)), rng.uniform(0.1, 3.0, (2, 5)))
            trees.add(np.arange(24, 32), np.array([True, True, True]))
            trees.add(np.array([38, 39, 2]), np.array([True, False, True]))
        totals = trees.total(np.arange(3))  # refreshes
        expected = trees._sum.copy()
        size = trees._size
        for node in range(size - 1, 0, -1):  # bottom-up, from the leaves alone
            expected[:, node] = expected[:, 2 * node] + expected[:, 2 * node + 1]
        np.testing.assert_array_equal(trees._sum, expected)
        np.testing.assert_array_equal(totals, expected[:, 1])
    assert totals[0] > 0 and totals[1] > 0 and totals[2] == 0  # tree 2 took none of the last runs


def observe_one(learners: StackedDQN, acting: int) -> None:
    """One primitive step of one env in state "x", sub-goal ``acting`` acting (-1: none), nothing ended, no curiosity."""
    learners.observe(np.zeros((1, 3), np.float32), np.zeros(1, np.int64), np.zeros((1, 3), np.float32), ["x"],
                     np.zeros(1, bool), np.zeros(1, bool), np.zeros(1, bool), np.array([acting]), np.zeros(1, np.float32))


def small_learners(**kwargs) -> StackedDQN:
    sub_kwargs = dict(policy_kwargs=dict(net_arch=[8]), batch_size=4, learning_starts=4, train_freq=2, gamma=0.9,
                      target_update_interval=5, learning_rate=0.01, max_grad_norm=0.5, n_steps=1)
    sub_kwargs.update(kwargs.pop("subpolicy_kwargs", {}))
    return StackedDQN(spaces.Box(-1, 1, (3,), np.float32), ACTIONS, equal_keys, subpolicy_kwargs=sub_kwargs, seed=0, **kwargs)


def fixed_batch(goals: np.ndarray, seed: int) -> GoalBatch:
    rng = np.random.default_rng(seed)
    t, b = len(goals), 4
    return GoalBatch(
        goals=goals, observations=rng.uniform(-1, 1, (t, b, 3)).astype(np.float32), actions=rng.integers(3, size=(t, b)),
        returns=rng.normal(size=(t, b)).astype(np.float32), next_observations=rng.uniform(-1, 1, (t, b, 3)).astype(np.float32),
        dones=rng.integers(2, size=(t, b)).astype(np.float32), discounts=np.full((t, b), 0.81, np.float32),
        weights=rng.uniform(0.2, 1, (t, b)).astype(np.float32), leaves=np.zeros((t, b), dtype=np.int64),
    )


def sb3_step(policy, batch: GoalBatch, row: int, mask=None, target_range=None) -> th.Tensor:
    """One Double DQN step of SB3's policy on row ``row`` of ``batch`` (torch's Adam, clip_grad_norm_ 0.5), the next
    action chosen among those ``mask`` allows, the targets clipped to ``target_range``: the parameters after it, flat."""
    optimizer = th.optim.Adam(policy.q_net.parameters(), lr=0.01)
    obs, next_obs = th.as_tensor(batch.observations[row]), th.as_tensor(batch.next_observations[row])
    with th.no_grad():
        online = policy.q_net(next_obs)
        if mask is not None:  # a masked action is no candidate of the max
            online[~th.as_tensor(mask(batch.next_observations[row]))] = -th.inf
        next_action = online.argmax(dim=1, keepdim=True)  # double Q: online chooses
        next_q = policy.q_net_target(next_obs).gather(1, next_action)[:, 0]  # target evaluates
        y = th.as_tensor(batch.returns[row]) + 0.81 * (1 - th.as_tensor(batch.dones[row])) * next_q
        if target_range is not None:
            y = y.clamp(*target_range)
    q = policy.q_net(obs).gather(1, th.as_tensor(batch.actions[row]).long()[:, None])[:, 0]
    loss = (th.as_tensor(batch.weights[row]) * F.smooth_l1_loss(q, y, reduction="none")).mean()
    optimizer.zero_grad()
    loss.backward()
    th.nn.utils.clip_grad_norm_(policy.q_net.parameters(), 0.5)
    optimizer.step()
    return th.cat([p.detach().reshape(-1) for p in policy.q_net.parameters()])


@pytest.mark.parametrize("due", [[0, 2], [0, 1, 2]])  # some sub-goals (gathered rows), all of them (in place)
def test_one_grouped_update_equals_sb3s_double_dqn_step_for_every_subgoal(monkeypatch: pytest.MonkeyPatch,
                                                                          due: list) -> None:
    learners = small_learners()
    for goal in ("A", "B", "C"):
        learners.add(goal)
    fill(learners.replay, ["x"] * 8, acting=[0] * 8)
    goals = np.array(due)
    batch = fixed_batch(goals, seed=1)
    monkeypatch.setattr(learners.replay, "sample", lambda goals, batch_size: batch)
    expected = {}
    for row, goal in enumerate(goals):  # SB3's DQN policy, torch's Adam and clip_grad_norm_, one sub-goal at a time
        expected[int(goal)] = sb3_step(learners.policy(int(goal)), batch, row)
    untouched = learners.params[1].clone()
    learners.train(goals)
    for goal, params in expected.items():
        th.testing.assert_close(learners.params[goal], params, rtol=1e-5, atol=1e-6)
    if 1 not in due:
        th.testing.assert_close(learners.params[1], untouched)  # a sub-goal that was not due does not move
    assert learners.n_updates.tolist() == [1, int(1 in due), 1]


def test_cnn_learners_grouped_update_equals_sb3s_double_dqn_step_for_every_subgoal(monkeypatch: pytest.MonkeyPatch) -> None:
    """CnnPolicy learners (NatureCNN on frames, one learner after the other, each parameter a leaf of its own): the
    same step as SB3's policy of each sub-goal, its uint8 frames scaled as SB3 scales them."""
    frames = spaces.Box(0, 255, (1, 36, 36), np.uint8)
    learners = StackedDQN(frames, ACTIONS, equal_keys, policy="CnnPolicy", seed=0, subpolicy_kwargs=dict(
        policy_kwargs=dict(features_extractor_kwargs=dict(features_dim=8)), batch_size=4, learning_starts=4,
        train_freq=2, gamma=0.9, target_update_interval=5, learning_rate=0.01, max_grad_norm=0.5, n_steps=1))
    for goal in ("A", "B", "C"):
        learners.add(goal)
    goals = np.array([0, 2])
    batch = fixed_batch(goals, seed=3)
    rng = np.random.default_rng(3)
    batch = batch._replace(observations=rng.integers(0, 256, (2, 4, 1, 36, 36), dtype=np.uint8),
                           next_observations=rng.integers(0, 256, (2, 4, 1, 36, 36), dtype=np.uint8))
    monkeypatch.setattr(learners.replay, "sample", lambda goals, batch_size: batch)
    monkeypatch.setattr(learners.replay, "update_priorities", lambda *args: None)
    expected = {int(goal): sb3_step(learners.policy(int(goal)), batch, row) for row, goal in enumerate(goals)}
    untouched = learners.params[1].clone()
    learners.train(goals)
    for goal, params in expected.items():
        th.testing.assert_close(learners.params[goal], params, rtol=1e-5, atol=1e-6)
    th.testing.assert_close(learners.params[1], untouched)
    assert learners.n_updates.tolist() == [1, 0, 1]


@pytest.mark.parametrize("written_out", [True, False], ids=["written-out backward", "autograd"])
def test_a_target_range_clips_every_td_target_as_her_does(monkeypatch: pytest.MonkeyPatch, written_out: bool) -> None:
    """target_range (low, high): the update is SB3's Double DQN step on targets clipped to [low, high]; the clip
    bites on this batch (its returns are standard normal), so the unclipped step lands elsewhere."""
    bounds = (-0.3, 0.3)
    clipped, plain = small_learners(target_range=bounds), small_learners()
    assert clipped.target_range == bounds and plain.target_range is None
    goals = np.array([0, 1])
    batch = fixed_batch(goals, seed=5)
    for learners in (clipped, plain):
        learners._relu_mlp = written_out and learners._relu_mlp
        for goal in ("A", "B"):
            learners.add(goal)
        fill(learners.replay, ["x"] * 8, acting=[0] * 8)
        monkeypatch.setattr(learners.replay, "sample", lambda goals, batch_size: batch)
    expected = [sb3_step(clipped.policy(int(goal)), batch, row, target_range=bounds) for row, goal in enumerate(goals)]
    clipped.train(goals)
    plain.train(goals)
    for goal in goals:
        th.testing.assert_close(clipped.params[goal], expected[goal], rtol=1e-5, atol=1e-6)
        assert not th.allclose(plain.params[goal], expected[goal], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("target_range, match", [((1.0, -1.0), "low < high"), ((0.0, float("inf")), "finite"),
                                                 ((1.0,), "two numbers"), ("high", "two numbers")])
def test_a_target_range_that_is_no_range_is_refused(target_range, match: str) -> None:
    with pytest.raises(ValueError, match=f"target_range.*{match}"):
        small_learners(target_range=target_range)


@pytest.mark.parametrize("plan", [[[0, 2], [0, 1, 2]], [[0, 1, 2], [0, 1, 2]], [[1, 2], [1, 2], [1, 2]]],
                         ids=["other sub-goals", "the same (one pass)", "the same, not the first rows"])
def test_grouped_rounds_compute_every_gradient_before_the_first_update_then_step_round_by_round(
        monkeypatch: pytest.MonkeyPatch, plan: list) -> None:
    """grouped_rounds: rounds due at one step (e.g. [0, 2] then [0, 1, 2]) in one call: each round's gradient from the
    parameters as they were before the step (SB3's DQN loss, clipped as SB3 clips), then torch's Adam step of round 1,
    then that of round 2. Rounds of the same sub-goals, whose networks read all their rows in one pass, too."""
    learners = small_learners(grouped_rounds=True)
    for goal in ("A", "B", "C"):
        learners.add(goal)
    fill(learners.replay, ["x"] * 8, acting=[0] * 8)
    plan = [np.array(goals) for goals in plan]
    batch = fixed_batch(np.concatenate(plan), seed=3)
    monkeypatch.setattr(learners.replay, "sample", lambda goals, batch_size: batch)
    policies = {goal: learners.policy(goal) for goal in range(3)}  # the parameters before the step
    optimizers = {goal: th.optim.Adam(policy.q_net.parameters(), lr=0.01) for goal, policy in policies.items()}
    grads = []
    for row, goal in enumerate(np.concatenate(plan)):
        net, target = policies[int(goal)].q_net, policies[int(goal)].q_net_target
        obs, next_obs = th.as_tensor(batch.observations[row]), th.as_tensor(batch.next_observations[row])
        with th.no_grad():
            next_q = target(next_obs).gather(1, net(next_obs).argmax(dim=1, keepdim=True))[:, 0]
            y = th.as_tensor(batch.returns[row]) + 0.81 * (1 - th.as_tensor(batch.dones[row])) * next_q
        q = net(obs).gather(1, th.as_tensor(batch.actions[row]).long()[:, None])[:, 0]
        loss = (th.as_tensor(batch.weights[row]) * F.smooth_l1_loss(q, y, reduction="none")).mean()
        grad = th.autograd.grad(loss, list(net.parameters()))
        norm = th.sqrt(sum((g ** 2).sum() for g in grad))
        grads.append([g * min(1.0, 0.5 / (float(norm) + 1e-6)) for g in grad])
    for row, goal in enumerate(np.concatenate(plan)):  # round 1's steps, then round 2's
        for parameter, grad in zip(policies[int(goal)].q_net.parameters(), grads[row]):
            parameter.grad = grad
        optimizers[int(goal)].step()
    learners.train_rounds(plan, first_round=1)
    for goal, policy in policies.items():
        expected = th.cat([p.detach().reshape(-1) for p in policy.q_net.parameters()])
        th.testing.assert_close(learners.params[goal], expected, rtol=1e-5, atol=1e-6)
    counts = np.bincount(np.concatenate(plan), minlength=3).tolist()
    assert learners.n_updates.tolist() == counts and learners.adam_steps[:3].tolist() == counts


def test_updates_follow_the_train_frequency_in_one_call_whatever_the_number_of_subgoals(monkeypatch) -> None:
    for n_goals in (2, 12):
        learners = small_learners(train_shared=True)
        for goal in range(n_goals):
            learners.add(goal)
        calls = []
        original = learners.train_rounds
        monkeypatch.setattr(learners, "train_rounds",
                            lambda plan, first_round: calls.extend(map(len, plan)) or original(plan, first_round))
        fill(learners.replay, ["x"] * 3, acting=[0] * 3)
        learners.own_steps[:] = 0
        for step in range(10):
            observe_one(learners, acting=1)
        # a tick per step for every sub-goal: an update round every 2 ticks, each one call for all sub-goals
        assert calls == [n_goals] * 5
        assert learners.own_steps.tolist() == [0, 10] + [0] * (n_goals - 2)
        # targets follow every target_update_interval (5) ticks
        th.testing.assert_close(learners.target[:n_goals], learners.params[:n_goals])


@pytest.mark.parametrize("grouped", [False, True])
def test_the_rounds_due_at_one_step_are_one_call_with_grouped_rounds(monkeypatch, grouped: bool) -> None:
    learners = small_learners(train_shared=True, grouped_rounds=grouped, n_envs=4)  # 4 ticks a step: 2 rounds
    for goal in range(3):
        learners.add(goal)
    calls = []
    original = learners.train_rounds
    monkeypatch.setattr(learners, "train_rounds",
                        lambda plan, first_round: calls.append((len(plan), first_round)) or original(plan, first_round))
    for step in range(3):
        learners.observe(np.zeros((4, 3), np.float32), np.zeros(4, np.int64), np.zeros((4, 3), np.float32), ["x"] * 4,
                         np.zeros(4, bool), np.zeros(4, bool), np.zeros(4, bool), np.array([0, 1, 2, 0]),
                         np.zeros(4, np.float32))
    # learning starts at 4 stored transitions (the first step), then two rounds a step, numbered on
    assert calls == ([(2, 0), (2, 2), (2, 4)] if grouped else [(1, 0), (1, 1), (1, 2), (1, 3), (1, 4), (1, 5)])
    assert learners.n_updates.tolist() == [6, 6, 6] and learners.rounds == 6


def test_a_round_updates_at_most_max_updates_subgoals_the_pursued_first_then_the_longest_waiting(monkeypatch) -> None:
    learners = small_learners(train_shared=True, max_updates=3)
    for goal in range(7):
        learners.add(goal)
    calls = []
    original = learners.train_rounds
    monkeypatch.setattr(learners, "train_rounds",
                        lambda plan, first_round: calls.extend(g.tolist() for g in plan) or original(plan, first_round))
    fill(learners.replay, ["x"] * 3, acting=[0] * 3)
    for step in range(12):  # an update round every 2 steps: 6 rounds; sub-goal 5 is pursued throughout
        observe_one(learners, acting=5)
    # 5 every round, then the two that waited longest (ties: the lower id), so every sub-goal gets its turn
    assert calls == [[0, 1, 5], [2, 3, 5], [4, 5, 6], [0, 1, 5], [2, 3, 5], [4, 5, 6]]
    assert learners.n_updates.tolist() == [2, 2, 2, 2, 2, 6, 2]
    # more pursued sub-goals than max_updates: the pursued ones that waited longest
    learners.last_round[:] = [0, 5, 1, 9, 9, 9, 9]
    assert learners.bounded(np.arange(7), np.array([1, 2, 3, 4])).tolist() == [1, 2, 3]
    assert learners.bounded(np.array([0, 6]), np.array([1])).tolist() == [0, 6]  # no more due than max_updates
    restored = small_learners(max_updates=3)
    restored.load_state_dict(learners.state_dict())
    assert restored.last_round.tolist() == learners.last_round.tolist() and restored.rounds == learners.rounds
    with pytest.raises(ValueError, match="max_updates"):
        small_learners(max_updates=0)


def test_epsilon_decays_with_a_subgoals_own_steps() -> None:
    learners = small_learners(exploration_steps=10)
    learners.add("A")
    assert learners.exploration_rate(0) == pytest.approx(1.0)
    learners.own_steps[0] = 5
    assert learners.exploration_rate(0) == pytest.approx(1.0 + 0.5 * (0.05 - 1.0))
    learners.own_steps[0] = 50
    assert learners.exploration_rate(0) == pytest.approx(0.05)


def test_epsilon_also_decays_with_the_run_steps_since_a_subgoal_was_added() -> None:
    learners = small_learners(exploration_steps=10, exploration_run_steps=100, train_shared=True)
    learners.add("A")
    assert learners.exploration_rate(0) == pytest.approx(1.0)
    for _ in range(40):  # 40 primitive steps while another sub-goal (none here: -1) acts: no own step of "A"
        observe_one(learners, acting=-1)
    assert learners.own_steps[0] == 0 and learners.ticks[0] == 40
    assert learners.exploration_rate(0) == pytest.approx(1.0 + 0.4 * (0.05 - 1.0))  # the run's clock, 40 of 100
    learners.own_steps[0] = 6  # the own clock further along (6 of 10) sets the rate
    assert learners.exploration_rate(0) == pytest.approx(1.0 + 0.6 * (0.05 - 1.0))
    learners.ticks[0] = 1_000
    assert learners.exploration_rate(0) == pytest.approx(0.05)
    own_only = small_learners(exploration_steps=10, train_shared=True)
    own_only.add("A")
    own_only.ticks[0] = 1_000
    assert own_only.exploration_rate(0) == pytest.approx(1.0)  # by default the own steps alone


@pytest.mark.parametrize("value", [0, -5, 2.5, True])
def test_exploration_run_steps_is_checked(value) -> None:
    with pytest.raises(ValueError, match="exploration_run_steps"):
        small_learners(exploration_run_steps=value, train_shared=True)


def test_exploration_run_steps_needs_learners_that_learn_from_every_step() -> None:
    with pytest.raises(ValueError, match="train_shared=True"):
        small_learners(exploration_run_steps=100, train_shared=False)


def test_state_dict_round_trip_and_another_learners_state_is_refused() -> None:
    learners = small_learners()
    for goal in ("A", "B"):
        learners.add(goal)
    fill(learners.replay, ["x"] * 8, acting=[0] * 8)
    learners.train(np.array([0, 1]))
    restored = small_learners()
    restored.load_state_dict(learners.state_dict())
    obs = np.random.default_rng(0).uniform(-1, 1, (2, 3)).astype(np.float32)
    th.testing.assert_close(restored.q_values(np.array([0, 1]), obs), learners.q_values(np.array([0, 1]), obs))
    assert restored.replay.goal_keys == ["A", "B"] and restored.adam_steps[:2].tolist() == [1, 1]
    with pytest.raises(ValueError, match="not saved by StackedDQN"):
        small_learners().load_state_dict({**learners.state_dict(), "format": "sb3_hhp.SharedHeadsDQN"})


@pytest.mark.parametrize("kwargs, match", [
    (dict(train_freq=(1, "episode")), "counted in steps"),
    (dict(gradient_steps=0), "gradient_steps"),
    (dict(learning_rate=lambda progress: 1e-3), "must be a number"),
    (dict(not_an_argument=1), "Unknown subpolicy_kwargs"),
    (dict(n_steps=1, replay_buffer_kwargs=dict(off_policy_lower_bound=True)), "needs n_steps > 1"),
])
def test_bad_subpolicy_arguments_are_refused(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        small_learners(subpolicy_kwargs=kwargs)


@pytest.mark.parametrize("target_range", [None, (-0.05, 0.05)])
def test_the_heads_update_is_each_subgoals_double_dqn_loss_on_one_relabelled_batch(monkeypatch, target_range) -> None:
    """SharedHeadsDQN: one batch of stored transitions, relabelled for every sub-goal; its loss is the sum over
    sub-goals of each one's importance-weighted Huber loss against its Double DQN target of its own n-step returns
    (computed here with SB3's DQNPolicy view of each head; clipped to ``target_range`` where one is given), and one
    Adam step on the whole network follows."""
    import copy

    learners = SharedHeadsDQN(spaces.Box(-1, 1, (3,), np.float32), ACTIONS, equal_keys, seed=0, subpolicy_kwargs=dict(
        policy_kwargs=dict(net_arch=[8]), batch_size=4, learning_starts=4, gamma=0.5, n_steps=3, learning_rate=0.01,
        max_grad_norm=100.0, replay_buffer_kwargs=dict()), target_range=target_range)
    for goal in ("A", "B"):
        learners.add(goal)
    rng = np.random.default_rng(0)
    replay = learners.replay
    for t, (key, acting) in enumerate(zip(["x", "A", "x", "B", "x", "x"], [0, 0, 1, 1, 1, 0])):
        replay.add(rng.uniform(-1, 1, (1, 3)).astype(np.float32), np.array([t % 3]),
                   rng.uniform(-1, 1, (1, 3)).astype(np.float32), np.array([replay.key_id(key)]), np.array([False]),
                   np.array([False]), np.array([False]), np.array([acting]), np.array([0.1 * t], np.float32))
    leaves = np.array([0, 2, 3, 4])
    monkeypatch.setattr(learners.replay.trees, "sample", lambda trees, n, rng: (leaves[None], np.full((1, 4), 0.25)))
    goals = np.array([0, 1])
    network = copy.deepcopy(learners.network)
    optimizer = th.optim.Adam(network.parameters(), lr=0.01)
    grid = (2, 4)
    (returns, last, discounts, dones), _ = replay.n_step_returns(np.broadcast_to(leaves, grid), np.zeros(grid, int),
                                                                  np.broadcast_to(goals[:, None], grid))
    loss = 0.0
    for g in goals:
        policy = learners.policy(int(g))  # the SB3 view: the trunk with g's head
        with th.no_grad():
            next_obs = th.as_tensor(replay.next_observations[last[g], 0])
            next_action = policy.q_net(next_obs).argmax(dim=1, keepdim=True)
            next_q = policy.q_net_target(next_obs).gather(1, next_action)[:, 0]
            y = th.as_tensor(returns[g]) + th.as_tensor(discounts[g]) * (1 - th.as_tensor(dones[g])) * next_q
            if target_range is not None:
                assert ((y < target_range[0]) | (y > target_range[1])).any()  # the clip bites on this batch
                y = y.clamp(*target_range)
        obs = th.as_tensor(replay.observations[leaves, 0])
        q = network(obs)[:, g].gather(1, th.as_tensor(replay.actions[leaves, 0]).long()[:, None])[:, 0]
        loss = loss + F.smooth_l1_loss(q, y)  # equal priorities: every importance weight is 1
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    learners.train(goals)
    for (name, expected), actual in zip(network.named_parameters(), learners.network.parameters()):
        th.testing.assert_close(actual, expected, rtol=1e-5, atol=1e-6, msg=name)
    assert learners.last_loss * 2 == pytest.approx(float(loss.detach()), rel=1e-5)


def test_the_written_out_backward_pass_equals_autograd_with_the_lower_bound() -> None:
    kwargs = dict(subpolicy_kwargs=dict(n_steps=3, replay_buffer_kwargs=dict(off_policy_lower_bound=True),
                                        policy_kwargs=dict(net_arch=[8, 8])))
    by_hand, by_autograd = small_learners(**kwargs), small_learners(**kwargs)
    by_autograd._relu_mlp = False  # the generic path: autograd through the batched forward
    assert by_hand._relu_mlp
    rng = np.random.default_rng(0)
    keys, acting = [str(k) for k in rng.integers(4, size=12)], [int(a) for a in rng.integers(3, size=12)]
    for learners in (by_hand, by_autograd):
        for goal in ("0", "1", "2"):
            learners.add(goal)
        fill(learners.replay, keys, acting=acting)
        learners.replay._rng = np.random.default_rng(1)
    for goals in (np.arange(3), np.array([0, 2]), np.arange(3)):
        by_hand.train(goals)
        by_autograd.train(goals)
        th.testing.assert_close(by_hand.params[:3], by_autograd.params[:3], rtol=1e-5, atol=1e-7)
        th.testing.assert_close(by_hand.exp_avg_sq[:3], by_autograd.exp_avg_sq[:3], rtol=1e-5, atol=1e-12)
    assert not th.equal(by_hand.params[0], by_hand.target[0])  # the updates moved the networks


@pytest.mark.parametrize("goals", [[2, 0, 2, 1], [1, 1, 2, 2], [0, 0, 0, 0]])  # some learners, all, the first only
def test_acting_reads_each_envs_own_learner_as_its_sb3_policy_does(goals: list) -> None:
    learners = small_learners()
    for goal in ("A", "B", "C"):
        learners.add(goal)
    obs = np.random.default_rng(0).uniform(-1, 1, (len(goals), 3)).astype(np.float32)
    q = learners.q_values(np.array(goals), obs)
    for i, goal in enumerate(goals):
        with th.no_grad():
            expected = learners.policy(goal).q_net(th.as_tensor(obs[i : i + 1]))[0]
        th.testing.assert_close(q[i], expected)
    assert learners.act(np.array(goals), obs, deterministic=True).tolist() == q.argmax(dim=1).tolist()


def no_action_0_where_x_is_positive(obs: np.ndarray) -> np.ndarray:
    """A goal space's action mask for the tests: action 0 is not taken where the first coordinate is > 0."""
    obs = np.asarray(obs)
    mask = np.ones((*obs.shape[:-1], ACTIONS.n), dtype=bool)
    mask[..., 0] = obs[..., 0] <= 0
    return mask


def test_masked_actions_are_never_taken_nor_in_the_targets_max(monkeypatch: pytest.MonkeyPatch) -> None:
    """With the goal space's action mask: acting (greedy and exploring) never takes a masked action, and the Double
    DQN target chooses the next action among the allowed ones (SB3's target, the argmax restricted by hand)."""
    learners = small_learners(action_mask=no_action_0_where_x_is_positive)
    for goal in ("A", "B"):
        learners.add(goal)
    obs = np.random.default_rng(0).uniform(-1, 1, (400, 3)).astype(np.float32)
    goals = np.arange(400) % 2
    for deterministic in (True, False):  # epsilon is 1 before any own step: every action explores
        actions = learners.act(goals, obs, deterministic=deterministic)
        assert not (actions[obs[:, 0] > 0] == 0).any()
    explored = learners.act(goals, obs)
    assert set(explored[obs[:, 0] <= 0].tolist()) == {0, 1, 2} and set(explored[obs[:, 0] > 0].tolist()) == {1, 2}
    fill(learners.replay, ["x"] * 8, acting=[0] * 8)
    batch = fixed_batch(np.array([0, 1]), seed=2)
    assert (batch.next_observations[..., 0] > 0).any() and (batch.next_observations[..., 0] <= 0).any()
    monkeypatch.setattr(learners.replay, "sample", lambda goals, batch_size: batch)
    expected = {}
    for row, goal in enumerate((0, 1)):
        expected[goal] = sb3_step(learners.policy(goal), batch, row, mask=no_action_0_where_x_is_positive)
    learners.train(np.array([0, 1]))
    for goal, params in expected.items():
        th.testing.assert_close(learners.params[goal], params, rtol=1e-5, atol=1e-6)


GRID = spaces.Box(0, 10, (7, 7, 3), np.uint8)


def grid_learners(space: spaces.Box, view=None, seed: int = 0) -> StackedDQN:
    learners = StackedDQN(space, ACTIONS, equal_keys, n_envs=1, seed=seed, view=view, train_shared=True,
                          subpolicy_kwargs=dict(learning_starts=4, batch_size=4, train_freq=1, n_steps=2,
                                                learning_rate=0.01, policy_kwargs=dict(net_arch=[8])))
    for goal in ("A", "B"):
        learners.add(goal)
    return learners


def learn_side_by_side(learners: StackedDQN, grids: np.ndarray, plain: StackedDQN, read: np.ndarray) -> None:
    """The same steps, sub-goals reached and updates for learners of whole grids and for a learner of what they read
    of them: both update, and end with the same parameters."""
    keys = ["A" if t % 5 == 4 else ("B" if t % 7 == 6 else "x") for t in range(len(grids) - 1)]
    for t, key in enumerate(keys):
        for learner, obs in ((learners, grids), (plain, read)):
            learner.observe(obs[t : t + 1], np.array([t % 3]), obs[t + 1 : t + 2], [key], np.array([False]),
                            np.array([False]), np.array([False]), np.array([t % 2]), np.array([0.1], np.float32))
    assert learners.n_updates.sum() > 0 and learners.n_updates.tolist() == plain.n_updates.tolist()
    th.testing.assert_close(learners.params, plain.params)


def test_a_view_reads_only_the_central_cells_and_learns_as_a_learner_of_those_cells() -> None:
    """With view=3 the learners read the 3 x 3 central cells of a 7 x 7 grid: cells outside change nothing, cells
    inside do; and acting and learning on whole grids give what a learner of the cropped grids gives, step for step
    (the same parameters after the same updates from the same seed)."""
    rng = np.random.default_rng(0)
    viewed, plain = grid_learners(GRID, view=3), grid_learners(spaces.Box(0, 10, (3, 3, 3), np.uint8))
    assert viewed.params.shape == plain.params.shape  # a network of 27 inputs
    grids = rng.integers(0, 11, (40, 7, 7, 3)).astype(np.uint8)
    crop = grids[:, 2:5, 2:5]
    outside = grids.copy()
    outside[:, 0] = 10 - outside[:, 0]  # a row outside the view
    inside = grids.copy()
    inside[:, 3, 3] = 10 - inside[:, 3, 3]  # the centre
    goals = np.zeros(len(grids), dtype=np.int64)
    th.testing.assert_close(viewed.q_values(goals, outside), viewed.q_values(goals, grids))
    assert not th.allclose(viewed.q_values(goals, inside), viewed.q_values(goals, grids))
    learn_side_by_side(viewed, grids, plain, crop)
    th.testing.assert_close(viewed.q_values(goals, grids), plain.q_values(goals, crop))
    assert viewed.replay.observations.shape[-3:] == (7, 7, 3)  # the replay keeps whole grids (the goal space reads them)


def test_the_inner_view_reads_every_cell_but_the_outermost_ring() -> None:
    """view="inner" on a 7 x 7 grid is the 5 x 5 grid inside its outermost ring: the same cells as view=5, and a change
    of the ring changes nothing; on a 7 x 9 grid it reads 5 x 7 cells."""
    rng = np.random.default_rng(1)
    inner, five = grid_learners(GRID, view="inner"), grid_learners(GRID, view=5)
    assert inner.params.shape[1] == five.params.shape[1]
    grids = rng.integers(0, 11, (10, 7, 7, 3)).astype(np.uint8)
    goals = np.zeros(len(grids), dtype=np.int64)
    ring = grids.copy()
    ring[:, 0], ring[:, -1], ring[:, :, 0], ring[:, :, -1] = 10, 10, 10, 10
    th.testing.assert_close(inner.q_values(goals, ring), inner.q_values(goals, grids))
    np.testing.assert_array_equal(inner.input.crop(grids), grids[:, 1:-1, 1:-1])
    wide = grid_learners(spaces.Box(0, 10, (7, 9, 3), np.uint8), view="inner")
    assert wide.input.crop(np.zeros((2, 7, 9, 3), np.uint8)).shape == (2, 5, 7, 3)


@pytest.mark.parametrize("space, view, match", [
    (GRID, "outer", "odd integer >= 1 .* or 'inner'"),
    (spaces.Box(0, 10, (2, 2, 3), np.uint8), "inner", "at least 3 x 3"),
    (GRID, 4, "odd integer"),
    (GRID, 0, "odd integer"),
    (GRID, 9, "at most 7"),
    (spaces.Box(0, 10, (8, 8, 3), np.uint8), 9, "at most 7"),
    (OBS, 3, r"\(H, W, C\)"),
])
def test_a_view_that_cannot_be_read_is_refused(space: spaces.Box, view: int, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        StackedDQN(space, ACTIONS, equal_keys, view=view)


def test_learners_with_an_overview_read_the_view_and_the_blocks_and_learn_as_a_learner_of_both() -> None:
    """view=3 with overview=3 on 7 x 7 grids: the learners read the 3 x 3 central cells and the 3 x 3 blocks, 18 cells
    in one row; a cell outside the view changes the Q-values where it becomes its block's most salient cell and not
    otherwise; acting and learning on whole grids give what a learner of those 18 cells gives, step for step."""
    rng = np.random.default_rng(2)
    learners = StackedDQN(GRID, ACTIONS, equal_keys, n_envs=1, seed=0, view=3, overview=3, train_shared=True,
                          subpolicy_kwargs=dict(learning_starts=4, batch_size=4, train_freq=1, n_steps=2,
                                                learning_rate=0.01, policy_kwargs=dict(net_arch=[8])))
    plain = grid_learners(spaces.Box(0, 10, (1, 18, 3), np.uint8))
    for goal in ("A", "B"):
        learners.add(goal)
    assert learners.params.shape == plain.params.shape  # a network of 54 inputs
    grids = rng.integers(1, 5, (40, 7, 7, 3)).astype(np.uint8)
    read = np.concatenate([grids[:, 2:5, 2:5].reshape(40, 1, 9, 3), Overview(GRID, 3)(grids).reshape(40, 1, 9, 3)], axis=1
                          ).reshape(40, 1, 18, 3)
    np.testing.assert_array_equal(learners.input.crop(grids), read)
    goals = np.zeros(len(grids), dtype=np.int64)
    salient = grids.copy()
    salient[:, 0, 0] = [10, 0, 0]  # outside the view, now its block's highest code
    hidden = salient.copy()
    hidden[:, 1, 1] = rng.integers(0, 10, (40, 3))  # outside the view and below its block's highest code
    assert not th.allclose(learners.q_values(goals, salient), learners.q_values(goals, grids))
    th.testing.assert_close(learners.q_values(goals, hidden), learners.q_values(goals, salient))
    learn_side_by_side(learners, grids, plain, read)
    th.testing.assert_close(learners.q_values(goals, grids), plain.q_values(goals, read))
    assert learners.replay.observations.shape[-3:] == (7, 7, 3)  # the replay keeps whole grids


@pytest.mark.parametrize("space, overview, policy, match", [
    (GRID, 4, "MlpPolicy", "odd integer >= 3"),
    (GRID, 1, "MlpPolicy", "odd integer >= 3"),
    (GRID, True, "MlpPolicy", "odd integer >= 3"),
    (OBS, 3, "MlpPolicy", r"\(H, W, C\)"),
    (spaces.Box(0, 255, (7, 7, 3), np.uint8), 3, "CnnPolicy", "MlpPolicy"),
])
def test_an_overview_that_cannot_be_read_is_refused(space: spaces.Box, overview, policy: str, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        StackedDQN(space, ACTIONS, equal_keys, overview=overview, policy=policy)


def test_a_carrying_subgoal_learns_from_empty_handed_steps_as_they_would_have_gone_carrying() -> None:
    """``carry_relabel``: rows of a carrying sub-goal's batch become the counterfactual's one-step transitions, with
    eq. 5 / eq. 6 from done(s'', g) of the changed next state; other sub-goals' rows and unusable rows stay as drawn."""
    gamma, alpha = 0.5, 0.5

    def counterfactual(goal_key, obs, actions, next_obs):
        if goal_key[0] != "carrying":
            return None
        usable = actions.reshape(-1) != 2  # action 2 would go otherwise
        return usable, obs + 100, next_obs + 100, [("carrying", int(o[0]) - 100) for o in next_obs[usable] + 100]

    replay = SharedReplay(16, OBS, ACTIONS, equal_keys, alpha=alpha, gamma=gamma, n_steps=3, lower_bound=True,
                          carry_relabel=1.0, counterfactual=counterfactual, seed=0)
    replay.add_goal(("carrying", 3))  # reached in the counterfactual of the step 2 -> 3
    replay.add_goal(("empty", 3))
    fill(replay, [("empty", t + 1) for t in range(6)], acting=[0] * 6, intrinsic=[0.25] * 6)  # states 0..6, actions t % 3
    batch = replay.sample(np.array([0, 1]), 32)
    start = batch.observations[..., 0].astype(int) % 100  # the state each drawn row starts in
    changed = batch.observations[..., 0] >= 100
    assert not changed[1].any()  # empty hands: drawn as stored
    np.testing.assert_array_equal(changed[0], start[0] % 3 != 2)  # every usable row of the carrying sub-goal
    rows = changed[0]
    np.testing.assert_array_equal(batch.next_observations[0, rows, 0], batch.observations[0, rows, 0] + 1)  # one step
    reached = start[0, rows] == 2
    np.testing.assert_allclose(batch.returns[0, rows], np.where(reached, 1.0, 0.0) + alpha * 0.25)  # eq. 5, 6
    np.testing.assert_array_equal(batch.dones[0, rows], reached)
    np.testing.assert_allclose(batch.discounts[0, rows], gamma)
    np.testing.assert_allclose(batch.behaviour_returns[0, rows], batch.returns[0, rows])
    np.testing.assert_array_equal(batch.behaviour_next_observations[0, rows], batch.next_observations[0, rows])
    unchanged = ~rows  # rows with action 2: the stored return, never a done of the carrying sub-goal
    assert unchanged.any() and not batch.dones[0, unchanged].any()
    with pytest.raises(ValueError, match="carry_relabel"):
        SharedReplay(16, OBS, ACTIONS, equal_keys, carry_relabel=1.5)


def test_one_hot_updates_read_the_kept_places_and_learn_as_the_dense_input_does(monkeypatch: pytest.MonkeyPatch) -> None:
    """With one_hot, an update's first layer reads the places of the set indicators the replay kept: the same
    parameters, Adam moments and losses, to float rounding, as the dense one-hot input, over grouped rounds, the
    lower bound's closing states, give-ups, target networks renewed (their first layer's rows made again) and
    learners updated in turn."""
    grids = np.random.default_rng(0).integers(0, 11, (60, 7, 7, 3)).astype(np.uint8)
    runs = []
    for keep in (True, False):
        monkeypatch.setattr(StackedDQN, "_encoded_replay", keep)
        learners = StackedDQN(GRID, ACTIONS, equal_keys, n_envs=1, seed=0, view=5, train_shared=True,
                              one_hot=[[2, 4, 5, 6], [], [1, 2]], grouped_rounds=True,
                              subpolicy_kwargs=dict(learning_starts=4, batch_size=4, train_freq=1, gradient_steps=2,
                                                    n_steps=3, learning_rate=0.01, target_update_interval=7,
                                                    policy_kwargs=dict(net_arch=[8, 8])))
        assert (learners.replay.encoded_observations is not None) == keep
        for goal in ("A", "B", "C"):
            learners.add(goal)
        losses = []
        for t in range(len(grids) - 1):
            learners.observe(grids[t : t + 1], np.array([t % 3]), grids[t + 1 : t + 2], ["ABCx"[t % 7 % 4]],
                             np.array([False]), np.array([False]), np.array([t % 9 == 8]), np.array([t % 3]),
                             np.array([0.1], np.float32))
            losses.append(learners.last_loss)
        runs.append((learners, losses))
    (kept, kept_losses), (dense, dense_losses) = runs
    assert kept.n_updates.min() > 20 and kept.n_updates.tolist() == dense.n_updates.tolist()
    # the kept places' learners keep each first layer as rows (plus zeros): compared in SB3's order, as saved
    assert kept.params.shape[1] > dense.params.shape[1]
    kept_state, dense_state = kept.state_dict(), dense.state_dict()
    # the two sum the first layer in different orders: after 100-odd Adam steps at lr 0.01 a weight near zero differs
    # by up to ~2e-6 on some CPUs (AVX-512 machines), so the absolute tolerance is 1e-5, far below one step's size
    th.testing.assert_close(kept_state["params"], dense_state["params"], rtol=1e-4, atol=1e-5)
    th.testing.assert_close(kept_state["target"], dense_state["target"], rtol=1e-4, atol=1e-5)
    th.testing.assert_close(kept_state["exp_avg_sq"], dense_state["exp_avg_sq"], rtol=1e-3, atol=1e-10)
    np.testing.assert_allclose(kept_losses, dense_losses, rtol=1e-4)
    assert not th.equal(kept.params[0], kept.target[0])
    # the zeros of the layout stay zero through training; each learner's SB3 policy reads its own weights
    size, width = kept._shapes[0][1], kept._shapes[0][0]
    rows = kept.params[:3].view(3, -1, width)
    assert not rows[:, size].any() and not kept.params[:3, kept._starts[-1] + kept._numels[-1]:].any()
    for goal in range(3):
        for name, value in kept.policy(goal).q_net.state_dict().items():
            th.testing.assert_close(value, dense.policy(goal).q_net.state_dict()[name], rtol=1e-4, atol=1e-5)


def test_encoded_copies_kept_by_the_replay_match_every_drawn_state_counterfactuals_included() -> None:
    """``keep_encoded``: the replay keeps ``encode`` of every stored state beside it (those stored before it are
    encoded at once), and a drawn batch's encoded rows are the encoding of its states, closing states and the
    behaviour's closing states, rows changed by the carried counterfactual included; None keeps nothing."""
    def counterfactual(goal_key, obs, actions, next_obs):
        usable = actions.reshape(-1) != 2
        return usable, obs + 100, next_obs + 100, [("carrying", int(o[0]) - 100) for o in next_obs[usable] + 100]

    def encode(obs):  # (..., 3) -> (..., 2): a distinct image of each state
        return np.stack([obs[..., 0] // 2, obs[..., 0] % 7], axis=-1).astype(np.uint8)

    replay = SharedReplay(16, OBS, ACTIONS, equal_keys, n_steps=3, lower_bound=True, carry_relabel=0.5,
                          counterfactual=counterfactual, seed=0)
    replay.add_goal(("carrying", 3))
    fill(replay, [("empty", t + 1) for t in range(3)], acting=[0] * 3)
    replay.keep_encoded(encode)  # the three stored steps encoded now, the rest as they are stored
    fill(replay, [("empty", t + 1) for t in range(3, 9)], acting=[0] * 6)
    batch = replay.sample(np.array([0]), 64)
    assert (batch.observations >= 100).any() and (batch.observations < 100).any()  # changed rows and stored ones
    for states, encoded in ((batch.observations, batch.encoded_observations),
                            (batch.next_observations, batch.encoded_next_observations),
                            (batch.behaviour_next_observations, batch.encoded_behaviour_next_observations)):
        np.testing.assert_array_equal(encoded, encode(states))
    replay.keep_encoded(None)
    assert replay.sample(np.array([0]), 8).encoded_observations is None and replay.encoded_observations is None
