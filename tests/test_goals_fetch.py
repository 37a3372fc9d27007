"""Fetch goal space: the flat observation, cell keys, done(s, g), similarity, the facts the scripted oracle
reads, the drawing, and HhP end to end on FetchReach with its goal-conditioned learner (sb3_hhp.goals.fetch)."""

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_hhp import HhP
from sb3_hhp.hierarchy.options import is_success as _is_success
from sb3_hhp.goals import SUCCESS_KEY, FetchFlatObs, FetchGoalSpace, make_goal_space, wrap_env
from sb3_hhp.oracles import FetchScriptedOracle, Label, Query

gymnasium_robotics = pytest.importorskip("gymnasium_robotics", reason='needs the [fetch] extra: pip install "sb3_hhp[fetch]"')
gym.register_envs(gymnasium_robotics)

REACH = "FetchReach-v4"


def _flat(observation: np.ndarray, achieved: list, desired: list) -> np.ndarray:
    return np.concatenate([observation, achieved, desired]).astype(np.float32)


def test_flat_observation_is_observation_then_achieved_then_desired() -> None:
    env = FetchFlatObs(gym.make(REACH))
    raw, _ = env.env.reset(seed=0)
    flat = env.observation(raw)
    assert env.observation_space.shape == (10 + 3 + 3,)
    assert flat.dtype == np.float32 and flat.shape == env.observation_space.shape
    np.testing.assert_allclose(flat[:10], raw["observation"], rtol=1e-6)
    space = FetchGoalSpace()
    np.testing.assert_allclose(space.achieved_position(flat), raw["achieved_goal"], rtol=1e-6)
    np.testing.assert_allclose(space.desired_position(flat), raw["desired_goal"], rtol=1e-6)
    obs, _ = env.reset(seed=1)
    np.testing.assert_allclose(space.desired_position(obs), env.unwrapped.goal, rtol=1e-6)
    env.close()


def test_wrap_env_and_auto_goal_space_pick_fetch() -> None:
    raw = gym.make(REACH)
    assert not FetchGoalSpace.supports(raw)  # a dict observation: wrap it first
    with pytest.raises(ValueError, match="FetchFlatObs"):
        make_goal_space("auto", raw)
    wrapped = wrap_env(raw)
    assert isinstance(wrapped, FetchFlatObs) and FetchGoalSpace.supports(wrapped)
    assert isinstance(make_goal_space("auto", wrapped), FetchGoalSpace)
    assert wrap_env(wrapped) is wrapped
    with pytest.raises(ValueError, match="Fetch env"):
        FetchFlatObs(gym.make("MiniGrid-Empty-5x5-v0"))
    with pytest.raises(ValueError, match="cell_size must be > 0"):
        FetchGoalSpace(cell_size=0)


def test_key_is_the_cell_of_the_achieved_position() -> None:
    space = FetchGoalSpace(cell_size=0.05)
    obs = _flat(np.zeros(10), [1.34, 0.749, -0.01], [1.0, 1.0, 1.0])
    # floor(1.34 / 0.05) = 26, floor(0.749 / 0.05) = 14, floor(-0.01 / 0.05) = -1
    assert space.key(obs) == (26, 14, -1)
    np.testing.assert_allclose(space.cell_center((26, 14, -1)), [1.325, 0.725, -0.025])
    assert space.key(_flat(np.ones(10), [1.301, 0.701, -0.049], [0.0, 0.0, 0.0])) == (26, 14, -1)  # robot, target ignored
    assert space.describe((26, 14, -1)) == "at (132.5, 72.5, -2.5) cm"
    assert space.describe(SUCCESS_KEY) == "task solved"
    assert FetchGoalSpace().key(obs) == (134, 74, -1)  # 1 cm cells by default


def test_done_is_the_papers_distance_of_at_most_five_centimetres() -> None:
    space = FetchGoalSpace()  # 1 cm cells, 0.05 m
    goal = space.key(_flat(np.zeros(10), [1.305, 0.705, 0.505], [0, 0, 0]))
    for offset, reached in (([0.0, 0.0, 0.0], True), ([0.05, 0.0, 0.0], True), ([0.03, 0.04, 0.0], True),
                            ([0.06, 0.0, 0.0], False), ([0.03, 0.03, 0.03], False), ([0.0, 0.0, -0.1], False)):
        key = space.key(_flat(np.zeros(10), np.add([1.305, 0.705, 0.505], offset), [0, 0, 0]))
        assert space.achieved(key, goal) is reached, offset
        assert space.choosable(key, goal) is not reached  # a sub-goal already reached is no choice
    assert not space.achieved(SUCCESS_KEY, goal) and space.achieved(SUCCESS_KEY, SUCCESS_KEY)
    with pytest.raises(ValueError, match="distance_threshold must be > 0"):
        FetchGoalSpace(distance_threshold=-0.05)


def test_similarity_halves_at_the_distance_threshold() -> None:
    space = FetchGoalSpace(cell_size=0.01, distance_threshold=0.05)
    others = [(0, 0, 0), (5, 0, 0), (3, 4, 0), (10, 0, 0), (0, 0, 1), SUCCESS_KEY]
    similarity = space.similarity((0, 0, 0), np.zeros(16), others, np.zeros((len(others), 16)))
    # 1 / (1 + (d / 0.05)^2) for d = 0, 0.05, 0.05, 0.10, 0.01 m
    np.testing.assert_allclose(similarity, [1.0, 1 / 2, 1 / 2, 1 / 5, 1 / 1.04, 0.0])
    np.testing.assert_allclose(space.similarity(SUCCESS_KEY, np.zeros(16), others, np.zeros((6, 16))), [0, 0, 0, 0, 0, 1])


def _push_obs(gripper: list, block: list, target: list) -> np.ndarray:
    """A flat FetchPush observation: the gripper's place, the block's (the achieved position too), zeros, the target."""
    observation = np.zeros(25)
    observation[0:3], observation[3:6] = gripper, block
    return _flat(observation, block, target)


def test_on_a_task_with_an_object_keys_say_whether_the_gripper_is_at_it() -> None:
    space = FetchGoalSpace()
    assert not space.with_gripper  # unbound (and on Reach): keys of three entries
    space.bind(wrap_env(gym.make("FetchPush-v4")))
    assert space.with_gripper and make_goal_space("auto", wrap_env(gym.make("FetchPush-v4"))).with_gripper
    assert not make_goal_space("auto", wrap_env(gym.make(REACH))).with_gripper
    assert not FetchGoalSpace(gripper=False).with_gripper
    assert not make_goal_space("fetch_places", wrap_env(gym.make("FetchPush-v4"))).with_gripper
    older = FetchGoalSpace()
    del older.gripper  # as a goal space pickled before the flag existed: bound again, its keys keep 3 entries
    older.bind(wrap_env(gym.make("FetchPush-v4")))
    assert not older.with_gripper and len(older.key(_push_obs([1.2, 0.7, 0.4], [1.3, 0.7, 0.4], [1.4, 0.8, 0.4]))) == 3
    block, target = [1.305, 0.705, 0.425], [1.4, 0.8, 0.425]
    away = _push_obs([1.2, 0.705, 0.425], block, target)  # 10.5 cm from the block
    near = _push_obs([1.26, 0.705, 0.425], block, target)  # 4.5 cm: at it
    assert space.key(away) == (130, 70, 42, 0) and space.key(near) == (130, 70, 42, 1)
    np.testing.assert_allclose(space.achieved_goal(np.stack([away, near])), [block + [0.0], block + [1.0]], rtol=1e-6)
    np.testing.assert_allclose(space.cell_center((130, 70, 42, 1)), [1.305, 0.705, 0.425])
    assert space.describe((130, 70, 42, 1)) == "at (130.5, 70.5, 42.5) cm, the gripper at it"
    assert space.describe((130, 70, 42, 0)) == "at (130.5, 70.5, 42.5) cm, the gripper away"
    # done(s, g): the place, and the gripper at the object where the sub-goal has it there
    at_goal, place_goal = (130, 70, 42, 1), (130, 70, 42, 0)
    assert space.achieved((131, 70, 42, 1), at_goal) and not space.achieved((131, 70, 42, 0), at_goal)
    assert space.achieved((131, 70, 42, 0), place_goal) and space.achieved((131, 70, 42, 1), place_goal)
    assert not space.achieved((140, 70, 42, 1), at_goal)  # 10 cm away
    assert space.choosable(space.key(away), at_goal) and not space.choosable(space.key(near), at_goal)
    # the learner's goal: the place, then the flag; the task's own goal asks for none
    np.testing.assert_allclose(space.goal_position(at_goal, away), [1.305, 0.705, 0.425, 1.0])
    np.testing.assert_allclose(space.goal_position(SUCCESS_KEY, away), target + [0.0], rtol=1e-6)
    # the discovery gate: a key whose flag differs from every sub-goal's is new, wherever it is
    similarity = space.similarity(at_goal, near, [place_goal, (135, 70, 42, 1), SUCCESS_KEY], np.zeros((3, 31)))
    np.testing.assert_allclose(similarity, [0.0, 0.5, 0.0])
    # what the oracle reads: each sub-goal's flag (none where the sub-goal is the task solved)
    info = space.query_info(away, near, away)
    assert info["goal1_gripper_at_object"] is True and info["goal2_gripper_at_object"] is False
    assert FetchScriptedOracle().answer(Query(state=away, goal1=0, goal2=1, goal1_obs=near, goal2_obs=away,
                                              info=info)) == Label.FIRST
    solved = _push_obs(target, target, target)
    assert space.query_info(away, solved, near)["goal1_gripper_at_object"] is False


@pytest.mark.parametrize("env_id", ["FetchReach-v4", "FetchPush-v4", "FetchPickAndPlace-v4", "FetchSlide-v4"])
def test_sub_goals_are_found_within_the_tasks_region(env_id: str) -> None:
    """Every target the env draws and every place its achieved position starts from may become a sub-goal; a place
    more than ``distance_threshold`` beyond the farthest of them may not (on the tasks with an object, the object on
    the floor); the task solved always may; a goal space not bound to an env finds places everywhere."""
    env = wrap_env(gym.make(env_id))
    space = make_goal_space("fetch", env)
    assert FetchGoalSpace().discoverable((0, 0, 0)) and space.discoverable(SUCCESS_KEY)
    places = []
    for seed in range(200):
        obs, _ = env.reset(seed=seed)
        places += [space.achieved_position(obs), space.desired_position(obs)]
    places = np.array(places)

    def key(place: np.ndarray) -> tuple:
        cell = tuple(int(v) for v in np.floor(place / space.cell_size))
        return cell + (1,) if space.with_gripper else cell

    assert all(space.discoverable(key(place)) for place in places)
    beyond = space.distance_threshold + 2 * space.cell_size
    for axis in range(3):
        for sign, edge in ((-1, places[:, axis].min()), (1, places[:, axis].max())):
            place = places[0].copy()
            place[axis] = edge + sign * beyond
            assert not space.discoverable(key(place)), (axis, sign)
    if space.with_gripper:
        assert not space.discoverable(key(np.array([places[0, 0], places[0, 1], 0.025])))  # fallen off the table
    env.close()


def test_query_info_feeds_the_scripted_oracle() -> None:
    space = FetchGoalSpace()
    state = _flat(np.zeros(10), [1.3, 0.7, 0.5], [1.4, 0.8, 0.5])
    goal1 = _flat(np.zeros(10), [1.35, 0.75, 0.5], [1.1, 0.6, 0.4])  # 7 cm from the state's target
    goal2 = _flat(np.zeros(10), [1.2, 0.7, 0.5], [1.4, 0.8, 0.5])  # 22 cm from it
    info = space.query_info(state, goal1, goal2)
    np.testing.assert_allclose(info["desired_goal"], [1.4, 0.8, 0.5], rtol=1e-6)
    np.testing.assert_allclose(info["goal1_achieved"], [1.35, 0.75, 0.5], rtol=1e-6)
    np.testing.assert_allclose(info["goal2_achieved"], [1.2, 0.7, 0.5], rtol=1e-6)
    oracle = FetchScriptedOracle()
    query = Query(state=state, goal1=0, goal2=1, goal1_obs=goal1, goal2_obs=goal2, info=info)
    assert oracle.answer(query) == Label.FIRST
    swapped = Query(state=state, goal1=1, goal2=0, goal1_obs=goal2, goal2_obs=goal1, info=space.query_info(state, goal2, goal1))
    assert oracle.answer(swapped) == Label.SECOND


def test_image_draws_the_achieved_position_and_the_target_from_above_and_the_side() -> None:
    space = FetchGoalSpace()
    image = space.image_of(_flat(np.zeros(10), [1.1, 0.55, 0.4], [1.5, 0.95, 0.8]))
    assert image.shape == (64, 128, 3) and image.dtype == np.uint8
    blue = (image[..., 2] > 200) & (image[..., 0] < 100)
    red = (image[..., 0] > 200) & (image[..., 2] < 100)
    for panel in (slice(0, 64), slice(64, 128)):
        rows, columns = np.nonzero(blue[:, panel])
        assert rows.size and columns.size
        # the achieved position is at the lower left of both views (x, y and z below the view's centre)
        assert columns.mean() < 32 and rows.mean() > 32
        rows, columns = np.nonzero(red[:, panel])
        assert columns.mean() > 32 and rows.mean() < 32  # the target at the upper right


def test_hhp_on_fetch_reach_asks_with_positions_and_plays_under_evaluate_policy_as_a_plain_loop() -> None:
    th.set_num_threads(1)
    model = HhP(
        "MlpPolicy", gym.make(REACH), oracle="scripted", query_budget=6, seed=0, learning_starts=100,
        predictor_kwargs=dict(n_masks=20),
        subpolicy_kwargs=dict(learning_starts=64, batch_size=32, policy_kwargs=dict(net_arch=[32, 32])),
    )
    assert isinstance(model.goal_space, FetchGoalSpace)
    model.learn(800)
    assert model.num_timesteps >= 800 and len(model.subgoals) >= 2
    # the scripted oracle answered with the positions the goal space put into every question
    answered = [model.store.get_query(query_id) for query_id in model.consumed_query_ids]
    assert answered and all({"desired_goal", "goal1_achieved", "goal2_achieved"} <= set(q.info) for q in answered)
    assert len(model.predictor) > 0

    # evaluate_policy (a VecEnv, the sub-goal carried in ``state``) plays the episode a plain loop over predict does
    eval_env = wrap_env(gym.make(REACH))
    vec_env = DummyVecEnv([lambda: wrap_env(gym.make(REACH))])
    vec_env.seed(3)
    returns, lengths = evaluate_policy(model, vec_env, n_eval_episodes=1, deterministic=True, return_episode_rewards=True,
                                       warn=False)
    obs, _ = eval_env.reset(seed=3)
    state, start, total, steps, done = None, np.ones(1, dtype=bool), 0.0, 0, False
    while not done:
        action, state = model.predict(obs, state=state, episode_start=start, deterministic=True)
        assert action.shape == (4,) and np.all(np.abs(action) <= 1.0)
        obs, reward, terminated, truncated, _ = eval_env.step(action)
        total, steps, done, start = total + float(reward), steps + 1, terminated or truncated, np.zeros(1, dtype=bool)
    assert (returns[0], lengths[0]) == (pytest.approx(total), steps)


@pytest.mark.parametrize(
    "info, terminated, extrinsic_return, success",
    [
        ({"is_success": 1.0}, False, -30.0, True),  # Fetch: solved at the time limit, never terminated
        ({"is_success": 0.0}, True, 1.0, False),  # the env's own word wins
        ({}, True, 0.9, True),  # MiniGrid: a positive return at a terminal state
        ({}, False, 0.9, False),
        ({}, True, 0.0, False),
    ],
)
def test_episode_success_is_the_envs_own_where_it_reports_one(info, terminated, extrinsic_return, success) -> None:
    assert _is_success(info, terminated, extrinsic_return) is success


def test_cnn_policy_on_flat_observations_names_the_policy_to_use() -> None:
    with pytest.raises(ValueError, match=r"use HhP\('MlpPolicy', env\)"):
        HhP("CnnPolicy", gym.make(REACH))


def test_a_learner_view_on_continuous_subgoals_names_the_fix() -> None:
    with pytest.raises(ValueError, match="view.*discrete actions.*continuous-action.*leave view out"):
        HhP("MlpPolicy", gym.make(REACH), subgoal_learner_kwargs=dict(view=3))


def test_a_learner_overview_on_continuous_subgoals_names_the_fix() -> None:
    with pytest.raises(ValueError, match="overview.*discrete actions.*continuous-action.*leave overview out"):
        HhP("MlpPolicy", gym.make(REACH), subgoal_learner_kwargs=dict(overview=3))


def test_a_target_range_on_continuous_subgoals_names_the_fix() -> None:
    with pytest.raises(ValueError, match="target_range.*discrete actions.*continuous-action.*leave target_range out"):
        HhP("MlpPolicy", gym.make(REACH), subgoal_learner_kwargs=dict(target_range=[-1.0, 1.0]))


def test_a_run_clock_on_continuous_subgoals_names_the_fix() -> None:
    message = "exploration_run_steps.*discrete actions.*continuous-action.*leave exploration_run_steps out"
    with pytest.raises(ValueError, match=message):
        HhP("MlpPolicy", gym.make(REACH), subgoal_learner_kwargs=dict(exploration_run_steps=1000))


def test_predict_ends_task_solved_where_the_target_is_reached_and_chooses_it_again(monkeypatch) -> None:
    """At the target the "task solved" option is reached (training's terminal key), not given up after
    max_subgoal_steps: a greedy meta-controller that values it best keeps it rather than being sent elsewhere."""
    th.set_num_threads(1)
    model = HhP("MlpPolicy", gym.make(REACH), query_budget=0, seed=0, max_subgoal_steps=3)
    env = wrap_env(gym.make(REACH))
    obs, _ = env.reset(seed=0)
    place = model.add_subgoal(model.goal_space.key(obs), obs, None, source="user")
    solved = model.add_subgoal(SUCCESS_KEY, obs, None, source="user")
    at_target = _flat(obs[:-6], list(obs[-3:]), list(obs[-3:]))
    away = _flat(obs[:-6], [1.0, 0.5, 0.2], list(obs[-3:]))
    best = th.full((1, int(model.action_space.n)), -1.0)
    best[0, solved] = 1.0
    monkeypatch.setattr(model, "_q_values", lambda observations: best.expand(len(observations), -1).clone())
    for steps in (1, 3):  # reached after one step, and on the step it would have given up
        _, state = model.predict(at_target, state=(np.array([solved]), np.array([steps])), deterministic=True)
        assert state[0][0] == solved and state[1][0] == 1  # chosen again, a fresh option
    # away from the target the option runs on, then gives up and the best other sub-goal follows
    _, state = model.predict(away, state=(np.array([solved]), np.array([1])), deterministic=True)
    assert state[0][0] == solved and state[1][0] == 2
    _, state = model.predict(away, state=(np.array([solved]), np.array([3])), deterministic=True)
    assert state[0][0] == place


def test_a_subgoal_of_the_wrong_shape_names_the_shape_to_pass() -> None:
    with pytest.raises(ValueError, match=r"subgoals'\]\[0\] has shape \(3,\).*shape \(16,\).*wrap_env"):
        HhP("MlpPolicy", gym.make(REACH), discovery_kwargs=dict(subgoals=[np.zeros(3)]))
    obs, _ = wrap_env(gym.make(REACH)).reset(seed=0)
    assert len(HhP("MlpPolicy", gym.make(REACH), discovery_kwargs=dict(subgoals=[obs])).subgoals) == 1
