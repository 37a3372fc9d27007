"""The goal-conditioned sub-goal learner of continuous actions: hindsight relabelling (HER's future strategy) with the
rewards of eq. 5 and 6, one model for every sub-goal, and HhP on FetchReach with it."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_hhp.goals import SUCCESS_KEY, FetchGoalSpace, wrap_env
from sb3_hhp.hierarchy.goal_conditioned import GoalConditionedLearner, HindsightReplay, reached_goals

gymnasium_robotics = pytest.importorskip("gymnasium_robotics")
gym.register_envs(gymnasium_robotics)
th.set_num_threads(1)
REACH = "FetchReach-v4"


def filled(future_p: float, alpha: float = 0.0) -> HindsightReplay:
    """Two envs, episodes of 5 steps; env e's step t reaches (t, e, 0) and was sent to (100, 100, 100)."""
    replay = HindsightReplay(obs_dim=2, action_dim=1, buffer_size=40, n_envs=2, future_p=future_p,
                             distance_threshold=0.05, alpha=alpha, seed=0)
    for t in range(12):
        achieved = np.array([[t % 5, 0, 0], [t % 5, 1, 0]], np.float32)
        obs = np.full((2, 2), t, np.float32)
        replay.add(obs, obs + 1, np.zeros((2, 1)), achieved, np.full((2, 3), 100.0), np.array([0.2, 0.4]),
                   np.zeros(2, bool), np.full(2, t % 5 == 4))
    return replay


def test_future_goals_are_places_reached_later_in_the_same_episode() -> None:
    replay = filled(future_p=1.0)
    rows, envs, goals, rewards, dones = replay.relabelled(2_000)
    step = replay.step_id[rows, envs]
    np.testing.assert_array_equal(goals[:, 1], envs)  # the same env's places
    later = goals[:, 0].astype(int)
    assert np.all(later >= step % 5)  # reached at or after the row's step ...
    assert np.all(later // 5 == 0) and np.all((step // 5) * 5 + later <= np.minimum((step // 5) * 5 + 4, 11))  # ... in its episode
    assert set(np.unique(later - step % 5)) == set(range(5))  # every later step of the episode is drawn
    # eq. 5: +1 where the row's own place is the goal (the relabelled goal is that step), else 0; no termination
    np.testing.assert_array_equal(rewards, np.where(later == step % 5, 1.0, 0.0))
    assert not dones.any()


def test_without_hindsight_the_goal_is_the_one_pursued_and_eq6_adds_curiosity() -> None:
    replay = filled(future_p=0.0, alpha=0.5)
    _, envs, goals, rewards, _ = replay.relabelled(200)
    np.testing.assert_array_equal(goals, np.full((200, 3), 100.0))
    np.testing.assert_allclose(rewards, 0.5 * np.where(envs == 0, 0.2, 0.4), rtol=1e-6)  # never reached: 0 + alpha r^i


def test_the_replay_counts_the_bytes_of_all_its_arrays() -> None:
    replay = filled(future_p=0.0)
    # 40 transitions of 2 envs (20 steps each): obs and next obs 2 floats, action 1, two places of 3, curiosity one
    # float, termination one bool, step ids and episode ends one int64 each; the episodes' starts one int64 an env
    per_row = 4 * (2 + 2 + 1 + 3 + 3 + 1) + 1 + 8 + 8
    assert replay.nbytes() == 40 * per_row + 2 * 8


def test_a_termination_short_of_the_goal_costs_one() -> None:
    replay = HindsightReplay(2, 1, 10, 1, future_p=0.0, distance_threshold=0.05, alpha=0.0, seed=0)
    replay.add(np.zeros((1, 2)), np.zeros((1, 2)), np.zeros((1, 1)), np.zeros((1, 3)), np.ones((1, 3)), np.zeros(1),
               np.ones(1, bool), np.ones(1, bool))
    _, _, _, rewards, dones = replay.relabelled(4)
    np.testing.assert_array_equal(rewards, -1.0)
    assert dones.all()


def test_a_goal_with_the_gripper_at_the_object_is_reached_only_with_it_there() -> None:
    """Goals (x, y, z, flag): reached where the place is within 5 cm and the flag set wherever the goal sets it; a
    relabelled goal carries the flag the later step had."""
    replay = HindsightReplay(2, 1, 20, 1, future_p=0.0, distance_threshold=0.05, alpha=0.0, seed=0, goal_dim=4)
    achieved = [[0.0, 0, 0, 0], [0.01, 0, 0, 1], [0.0, 0, 0, 1], [0.2, 0, 0, 1]]
    goals = [[0.0, 0, 0, 1], [0.0, 0, 0, 1], [0.0, 0, 0, 0], [0.0, 0, 0, 1]]
    for t, (reached, goal) in enumerate(zip(achieved, goals)):
        replay.add(np.zeros((1, 2)), np.zeros((1, 2)), np.zeros((1, 1)), np.array([reached]), np.array([goal]),
                   np.zeros(1), np.zeros(1, bool), np.array([t == 3]))
    rows, _, _, rewards, _ = replay.relabelled(200)
    # step 0: the place but not the gripper; 1: both; 2: a goal without the flag, reached; 3: the flag, not the place
    np.testing.assert_array_equal(rewards, np.array([0.0, 1.0, 1.0, 0.0])[rows])
    np.testing.assert_array_equal(reached_goals(np.array(achieved), np.array(goals), 0.05), [False, True, True, False])
    future = HindsightReplay(2, 1, 20, 1, future_p=1.0, distance_threshold=0.05, alpha=0.0, seed=0, goal_dim=4)
    future.load_state(replay.state())
    future.future_p = 1.0
    _, _, relabelled, _, _ = future.relabelled(200)
    assert {tuple(goal) for goal in relabelled} <= {tuple(np.float32(v) for v in goal) for goal in achieved}
    with pytest.raises(ValueError, match="goal_dim must be >= 3"):
        HindsightReplay(2, 1, 20, 1, future_p=0.0, distance_threshold=0.05, alpha=0.0, goal_dim=2)


def test_on_push_the_learner_reads_the_place_and_the_gripper_flag() -> None:
    env = wrap_env(gym.make("FetchPush-v4"))
    space = FetchGoalSpace()
    space.bind(env)
    learner = GoalConditionedLearner(env.observation_space, env.action_space, space.achieved_goal,
                                     space.state_part, space.goal_position, space.distance_threshold,
                                     subpolicy_kwargs=dict(learning_starts=0, policy_kwargs=dict(net_arch=[16])),
                                     seed=0)
    assert learner.goal_dim == 4 and learner.input_space["desired_goal"].shape == (4,)
    obs, _ = env.reset(seed=0)
    learner.add(space.key(obs)[:3] + (1,))
    inputs = learner.inputs(obs[None], learner.places(np.array([0]), obs[None]))
    np.testing.assert_allclose(inputs["desired_goal"][0, 3], 1.0)
    np.testing.assert_allclose(inputs["achieved_goal"][0], space.achieved_goal(obs[None])[0], rtol=1e-6)
    assert learner.act(np.array([0]), obs[None], deterministic=True).shape == (1, 4)


def test_one_model_serves_every_subgoal() -> None:
    env = wrap_env(gym.make(REACH))
    space = FetchGoalSpace()
    learner = GoalConditionedLearner(env.observation_space, env.action_space, space.achieved_position,
                                     space.state_part, space.goal_position, space.distance_threshold,
                                     subpolicy_kwargs=dict(learning_starts=0, policy_kwargs=dict(net_arch=[16])),
                                     seed=0)
    parameters = sum(p.numel() for p in learner.model.policy.parameters())
    for i in range(50):
        learner.add((i, 0, 0))
    learner.add(SUCCESS_KEY)
    assert sum(p.numel() for p in learner.model.policy.parameters()) == parameters
    obs, _ = env.reset(seed=0)
    batch = np.stack([obs, obs])
    places = learner.places(np.array([3, 50]), batch)
    np.testing.assert_allclose(places[0], space.cell_center((3, 0, 0)))
    np.testing.assert_allclose(places[1], space.desired_position(obs))  # the task's goal: this state's target
    inputs = learner.inputs(batch, places)
    np.testing.assert_allclose(inputs["achieved_goal"][0], space.achieved_position(obs), rtol=1e-6)
    assert inputs["observation"].shape == (2, env.observation_space.shape[0] - 6)
    assert learner.act(np.array([3, 50]), batch, deterministic=True).shape == (2, 4)


def test_hhp_on_fetch_reach_with_the_goal_conditioned_learner_trains_saves_and_loads(tmp_path) -> None:
    from sb3_hhp import HhP

    model = HhP("MlpPolicy", gym.make(REACH), oracle="scripted", query_budget=6, seed=0, learning_starts=100,
                predictor_kwargs=dict(n_masks=20),
                subpolicy_kwargs=dict(learning_starts=64, batch_size=32, policy_kwargs=dict(net_arch=[32, 32])))
    assert isinstance(model.subpolicies, GoalConditionedLearner)
    model.learn(400)
    assert model.subpolicies.model._n_updates > 0 and model.subpolicies.replay.size() == 400
    model.save(tmp_path / "reach")
    model.save_replay_buffer(tmp_path / "reach_replay")
    loaded = HhP.load(tmp_path / "reach", env=gym.make(REACH))
    loaded.load_replay_buffer(tmp_path / "reach_replay.pkl")
    np.testing.assert_array_equal(loaded.subpolicies.replay.obs, model.subpolicies.replay.obs)
    assert loaded.subpolicies.goal_keys == model.subpolicies.goal_keys
    env = wrap_env(gym.make(REACH))
    obs, _ = env.reset(seed=3)
    for _ in range(5):
        action, _ = model.predict(obs, deterministic=True)
        np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0], action, rtol=1e-5, atol=1e-6)
        obs, *_ = env.step(action)


def test_hhp_on_fetch_push_keys_the_gripper_and_loads_with_it(tmp_path) -> None:
    """On a task with an object HhP's sub-goals are (place, flag) keys, its learner reads goals of 4 entries, and a
    saved model loads with the same goal space."""
    from sb3_hhp import HhP

    model = HhP("MlpPolicy", gym.make("FetchPush-v4"), oracle="scripted", query_budget=4, seed=0, learning_starts=100,
                predictor_kwargs=dict(n_masks=10),
                subpolicy_kwargs=dict(learning_starts=64, batch_size=16, policy_kwargs=dict(net_arch=[16])))
    model.learn(300)
    assert model.goal_space.with_gripper and model.subpolicies.goal_dim == 4
    assert model.subgoals and all(len(goal.key) == 4 or goal.key == SUCCESS_KEY for goal in model.subgoals)
    model.save(tmp_path / "push")
    loaded = HhP.load(tmp_path / "push", env=gym.make("FetchPush-v4"))
    assert loaded.goal_space.with_gripper and loaded.subpolicies.goal_dim == 4
    assert [goal.key for goal in loaded.subgoals] == [goal.key for goal in model.subgoals]


def test_a_discrete_kind_on_continuous_actions_is_refused() -> None:
    from sb3_hhp import HhP

    with pytest.raises(ValueError, match="kind 'stacked' does not suit"):
        HhP("MlpPolicy", gym.make(REACH), subgoal_learner_kwargs=dict(kind="stacked"))


def test_a_goal_space_whose_places_are_not_positions_is_refused() -> None:
    env = wrap_env(gym.make(REACH))
    space = FetchGoalSpace()
    kwargs = dict(subpolicy_kwargs=dict(learning_starts=0, policy_kwargs=dict(net_arch=[16])), seed=0)
    flat = lambda obs: np.asarray(obs)[..., :2]  # noqa: E731  (x, y) only
    with pytest.raises(ValueError, match=r"position .* gave shape \(2,\) for each of 1 observations \(expected \(3,\)\)"):
        GoalConditionedLearner(env.observation_space, env.action_space, flat, space.state_part, space.goal_position,
                               space.distance_threshold, **kwargs)
    learner = GoalConditionedLearner(env.observation_space, env.action_space, space.achieved_position, space.state_part,
                                     lambda key, obs: np.zeros(4), space.distance_threshold, **kwargs)
    learner.add((1, 0, 0))
    obs, _ = env.reset(seed=0)
    with pytest.raises(ValueError, match=r"goal_position .* gave shape \(4,\) for each of 2 observations"):
        learner.act(np.array([0, 0]), np.stack([obs, obs]), deterministic=True)
