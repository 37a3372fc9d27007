"""The image goal space (fixed-layout image envs): cells as keys, SSIM as the discovery gate, HhP end to end."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_hhp import HhP
from sb3_hhp.goals import SUCCESS_KEY, ImageGoalSpace, MiniGridGoalSpace, make_goal_space, wrap_env
from sb3_hhp.goals.similarity import ssim_to_set
from sb3_hhp.oracles.registry import make_oracle
from sb3_hhp.oracles.synthetic import SyntheticOracle


class PixelRoom(gym.Env):
    """A fixed 5x5 room drawn as a 40x40 grayscale image: the agent (white square) walks to the goal (gray corner)."""

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, size: int = 5, cell: int = 8, max_steps: int = 40, render_mode=None) -> None:
        self.size, self.cell, self.max_steps, self.render_mode = size, cell, max_steps, render_mode
        self.observation_space = spaces.Box(0, 255, (size * cell, size * cell, 1), np.uint8)
        self.action_space = spaces.Discrete(4)
        self.pos, self.t = (0, 0), 0

    def _obs(self) -> np.ndarray:
        image = np.zeros(self.observation_space.shape, np.uint8)
        c, last = self.cell, self.size - 1
        image[last * c :, last * c :] = 128
        y, x = self.pos
        image[y * c : (y + 1) * c, x * c : (x + 1) * c] = 255
        return image

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos, self.t = (0, 0), 0
        return self._obs(), {}

    def step(self, action):
        dy, dx = [(-1, 0), (1, 0), (0, -1), (0, 1)][int(action)]
        y, x = self.pos
        self.pos = (min(max(y + dy, 0), self.size - 1), min(max(x + dx, 0), self.size - 1))
        self.t += 1
        solved = self.pos == (self.size - 1, self.size - 1)
        return self._obs(), float(solved), solved, self.t >= self.max_steps and not solved, {}

    def render(self) -> np.ndarray:
        return np.repeat(self._obs(), 3, axis=-1)


def test_key_is_the_frame_shrunk_by_area_and_quantised() -> None:
    """A cell is the area average over each block, times levels // 256: a frame of uniform blocks gives back the
    blocks' levels exactly, and the key is the same for frames that differ below the cell's resolution."""
    space = ImageGoalSpace(cell_shape=(2, 4), levels=8)
    blocks = np.array([[0, 40, 100, 255], [31, 32, 200, 224]], dtype=np.uint8)
    frame = np.kron(blocks, np.ones((10, 5), dtype=np.uint8))[..., None]  # (20, 20, 1): blocks of 10 x 5 pixels
    np.testing.assert_array_equal(space.cell(frame), blocks.astype(np.int64) * 8 // 256)
    assert space.cell(frame).tolist() == [[0, 1, 3, 7], [0, 1, 6, 7]]
    nudged = frame.copy()
    nudged[0, 0] = 9  # one pixel: the block's mean moves by 0.18, not across a level
    assert space.key(nudged) == space.key(frame)
    moved = frame.copy()
    moved[:10, :5] = 255
    assert space.key(moved) != space.key(frame)
    assert space.describe(space.key(frame)).startswith("cell ")


def test_layouts_rgb_gray_and_frame_stacks() -> None:
    """RGB frames are converted to gray; a stack of gray frames (channel last or first) is read by its last frame."""
    space = ImageGoalSpace(cell_shape=(4, 4), levels=16)
    rng = np.random.default_rng(0)
    gray = rng.integers(0, 256, (16, 16), dtype=np.uint8)
    stack_last = np.stack([np.zeros_like(gray), gray], axis=-1)  # (16, 16, 2): oldest first
    stack_first = np.moveaxis(np.stack([np.zeros_like(gray), np.zeros_like(gray), np.zeros_like(gray), gray], -1), -1, 0)
    rgb = np.repeat(gray[..., None], 3, axis=-1)
    for obs in (gray, gray[..., None], stack_last, stack_first, rgb):
        assert space.key(obs) == space.key(gray), obs.shape
        assert space.image_of(obs).shape == (16, 16, 3)
    np.testing.assert_array_equal(space.image_of(stack_first)[..., 0], gray)


def test_similarity_is_ssim_of_the_frames_clipped_and_one_for_an_equal_key() -> None:
    space = ImageGoalSpace()
    env = PixelRoom()
    first, _ = env.reset()
    second, *_ = env.step(3)
    third, *_ = env.step(1)
    goal_obs = np.stack([first, second, third])
    goal_keys = [space.key(o) for o in goal_obs]
    values = space.similarity(space.key(second), second, goal_keys, goal_obs)
    expected = np.clip(ssim_to_set(second[..., 0], goal_obs[..., 0]), 0, 1)
    assert values[1] == 1.0
    np.testing.assert_allclose(values[[0, 2]], expected[[0, 2]])
    assert 0.0 < values[0] < 1.0
    assert space.similarity(space.key(first), first, [], np.zeros((0, *first.shape), np.uint8)).shape == (0,)


def test_supports_images_and_auto_picks_it_after_minigrid() -> None:
    assert isinstance(make_goal_space("auto", PixelRoom()), ImageGoalSpace)
    assert isinstance(make_goal_space("auto", wrap_env(gym.make("MiniGrid-Empty-5x5-v0"))), MiniGridGoalSpace)
    assert not ImageGoalSpace.supports(gym.make("CartPole-v1"))
    assert not ImageGoalSpace.supports(PixelRoom(size=1, cell=4))  # 4 x 4 pixels: too small to be a frame
    with pytest.raises(ValueError, match="levels"):
        ImageGoalSpace(levels=1)
    with pytest.raises(ValueError, match="cell_shape"):
        ImageGoalSpace(cell_shape=(0, 4))


def test_hhp_trains_on_a_fixed_layout_image_env_with_cnn_policy(tmp_path) -> None:
    """HhP("CnnPolicy", env) on an image env: the image goal space is chosen, the subpolicies (built channel first
    by SB3) take the env's channel-last frames, the predictor is asked and trained on frames, evaluate_policy runs, and a saved
    model predicts what the trained one did."""
    th.manual_seed(0)
    room = PixelRoom()
    frames = [room.reset()[0]] + [room.step(action)[0] for action in (3, 3, 1, 1)]  # user sub-goals: a walk to the goal
    model = HhP("CnnPolicy", PixelRoom(), oracle="synthetic", query_budget=5, predictor_kwargs=dict(n_masks=2),
                learning_starts=50, batch_size=16,
                seed=0, subpolicy_kwargs=dict(learning_starts=50, batch_size=16, buffer_size=2_000), discovery_kwargs=dict(subgoals=frames[2:]))
    assert isinstance(model.goal_space, ImageGoalSpace)
    model.learn(300)
    assert model.num_timesteps >= 300 and len(model.subgoals) >= 3
    assert model.query_selector.used > 0 and len(model.predictor) > 0  # the predictor read frames (queries, bonus)
    assert np.asarray(model.goal_obs).shape[1:] == (40, 40, 1)  # sub-goals kept as the env's frames
    assert model.subpolicies.own_steps.sum() > 0
    # evaluate_policy (a VecEnv, the sub-goal carried in ``state``) plays the episode a plain loop over predict does
    returns, lengths = evaluate_policy(model, PixelRoom(), n_eval_episodes=1, return_episode_rewards=True, warn=False)
    room, state, start, total, steps, done = PixelRoom(), None, np.ones(1, dtype=bool), 0.0, 0, False
    obs, _ = room.reset()
    while not done:
        action, state = model.predict(obs, state=state, episode_start=start, deterministic=True)
        obs, reward, terminated, truncated, _ = room.step(int(action))
        total, steps, done, start = total + reward, steps + 1, terminated or truncated, np.zeros(1, dtype=bool)
    assert (returns[0], lengths[0]) == (total, steps)
    model.save(tmp_path / "image_hhp")
    loaded = HhP.load(tmp_path / "image_hhp", env=PixelRoom())
    assert isinstance(loaded.oracle, SyntheticOracle)  # the one it was saved with: there is no scripted oracle for images
    assert HhP.load(tmp_path / "image_hhp", oracle="none").oracle is None  # the caller's
    env = PixelRoom()
    obs, _ = env.reset()
    state_a = state_b = None
    start = np.ones(1, dtype=bool)
    for _ in range(10):
        action_a, state_a = model.predict(obs, state=state_a, episode_start=start, deterministic=True)
        action_b, state_b = loaded.predict(obs, state=state_b, episode_start=start, deterministic=True)
        assert int(action_a) == int(action_b)
        obs, *_ = env.step(int(action_a))
        start = np.zeros(1, dtype=bool)


# ---------------------------------------------------------------------------- landmarks (the paper's Atari detector)
def gray_frame() -> np.ndarray:
    return np.zeros((20, 20, 1), dtype=np.uint8)


def change(frame: np.ndarray, pixels: list, value: int = 200) -> np.ndarray:
    changed = frame.copy()
    for row, col in pixels:
        changed[row, col] = value
    return changed


def test_a_landmark_is_attained_when_20_percent_of_its_box_changed() -> None:
    """A 10x10 box: 19 changed pixels do not attain it, 20 do; changes outside every box attain nothing; an RGB pixel
    changes when any channel does; the last frame of a stack is read."""
    reference = gray_frame()
    space = ImageGoalSpace(landmarks=[(0, 0, 10, 10), (10, 10, 20, 15)], reference=reference, changed_fraction=0.2)
    inside = [(row, col) for row in range(10) for col in range(10)]
    assert space.key(reference) == ("landmarks", ())
    assert space.key(change(reference, inside[:19])) == ("landmarks", ())
    np.testing.assert_allclose(space.changed(change(reference, inside[:19])), [0.19, 0.0])
    assert space.key(change(reference, inside[:20])) == ("landmarks", (0,))
    outside = [(row, col) for row in range(10, 20) for col in range(0, 10)] + [(row, 19) for row in range(20)]
    assert space.key(change(reference, outside)) == ("landmarks", ())  # 120 pixels, none in a box
    second = [(row, col) for row in range(10, 20) for col in range(10, 15)]  # a 10x5 box: 10 pixels are 20 %
    assert space.key(change(reference, inside[:20] + second[:10])) == ("landmarks", (0, 1))
    assert space.key(change(reference, second[:9])) == ("landmarks", ())
    stricter = ImageGoalSpace(landmarks=[(0, 0, 10, 10)], reference=reference, changed_fraction=0.5)
    assert stricter.key(change(reference, inside[:49])) == ("landmarks", ())
    assert stricter.key(change(reference, inside[:50])) == ("landmarks", (0,))
    rgb = np.zeros((20, 20, 3), dtype=np.uint8)
    colour = ImageGoalSpace(landmarks=[(0, 0, 10, 10)], reference=rgb)
    one_channel = rgb.copy()
    one_channel[:2, :, 2] = 1  # rows 0-1, 10 pixels of the box, blue only
    assert colour.changed(one_channel)[0] == 0.2 and colour.key(one_channel) == ("landmarks", (0,))
    stack = np.concatenate([change(reference, inside), change(reference, inside[:20])], axis=-1)  # oldest first
    assert space.key(stack) == ("landmarks", (0,)) and space.changed(stack)[0] == 0.2


def test_a_landmark_subgoal_is_reached_where_all_its_boxes_are_attained() -> None:
    """done(s, g) per box (a set of landmarks is reached where each of them is), the subgoal of no landmark only
    where none is, "task solved" by equality; distinct keys are not alike (SSIM would call two frames of a room alike)."""
    space = ImageGoalSpace(landmarks=[(0, 0, 10, 10), (10, 10, 20, 20)], reference=gray_frame())
    none, first, second, both = (("landmarks", ()), ("landmarks", (0,)), ("landmarks", (1,)), ("landmarks", (0, 1)))
    assert space.achieved(first, first) and space.achieved(both, first) and space.achieved(both, second)
    assert not space.achieved(first, both) and not space.achieved(second, first) and not space.achieved(none, first)
    assert space.achieved(none, none) and not space.achieved(first, none)
    assert space.achieved(SUCCESS_KEY, SUCCESS_KEY) and not space.achieved(both, SUCCESS_KEY)
    assert not space.choosable(both, first) and space.choosable(second, first)
    frames = np.stack([gray_frame()] * 3)
    assert space.similarity(first, frames[0], [first, both, none], frames).tolist() == [1.0, 0.0, 0.0]
    assert [space.describe(key) for key in (none, first, both, SUCCESS_KEY)] == [
        "no landmark", "landmark 0", "landmarks 0, 1", "task solved"]
    assert ImageGoalSpace().key(gray_frame())[0] == "cell"  # cells stay the default


@pytest.mark.parametrize("landmarks, fraction, message", [
    ([(0, 0, 10, 21)], 0.2, r"landmark 0 \(0, 0, 10, 21\) lies outside the 20x20 frame"),
    ([(0, 0, 5, 5), (-1, 0, 5, 5)], 0.2, r"landmark 1 .* lies outside"),
    ([(5, 0, 5, 5)], 0.2, r"landmark 0 \(5, 0, 5, 5\) is empty or inverted.*row0 < row1"),
    ([(0, 8, 5, 2)], 0.2, "empty or inverted"),
    ([(0, 0, 5)], 0.2, r"four integers \(row0, col0, row1, col1\)"),
    ([(0, 0, 5, 5.5)], 0.2, "four integers"),
    ([], 0.2, "at least one box"),
    ([(0, 0, 5, 5)], 0.0, r"changed_fraction must be in \(0, 1\].*got 0.0"),
    ([(0, 0, 5, 5)], 1.5, r"changed_fraction must be in \(0, 1\]"),
    ([(0, 0, 5, 5)], -0.2, r"changed_fraction must be in \(0, 1\]"),
])
def test_bad_landmarks_are_refused_with_what_to_fix(landmarks: list, fraction: float, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ImageGoalSpace(landmarks=landmarks, reference=gray_frame(), changed_fraction=fraction)


def test_landmarks_need_a_reference_of_the_env_frames_shape() -> None:
    with pytest.raises(ValueError, match="need a reference frame.*env.reset"):
        ImageGoalSpace(landmarks=[(0, 0, 5, 5)])
    with pytest.raises(ValueError, match="give landmarks too"):
        ImageGoalSpace(reference=gray_frame())
    space = ImageGoalSpace(landmarks=[(0, 0, 5, 5)], reference=gray_frame())
    with pytest.raises(ValueError, match=r"reference frame has shape \(20, 20\) but this observation has .*\(40, 40\)"):
        space.key(np.zeros((40, 40, 1), np.uint8))
    with pytest.raises(ValueError, match=r"\(20, 20\) but the env observes frames of shape \(40, 40\)"):
        space.bind(PixelRoom())
    room = PixelRoom()
    bound = ImageGoalSpace(landmarks=[(32, 32, 40, 40)], reference=room.reset()[0])
    bound.bind(room)
    assert bound.game is None and bound.snapshot(room) == {} and bound.facts(bound.snapshot(room)) == {}
    with pytest.raises(ValueError, match="no scripted oracle for the 'image' goal space on this env"):
        make_oracle("scripted", bound, room.observation_space)


def test_landmarks_on_montezuma_frames_under_atari_wrapper() -> None:
    """84x84 AtariWrapper frames, the reference the first after a reset: a box at the middle ladder's foot is attained
    once the agent climbed down to it, not at the start; a box at the key, far from the agent, is not."""
    ale_py = pytest.importorskip("ale_py", reason='needs the [atari] extra: pip install "sb3_hhp[atari]"')
    from stable_baselines3.common.atari_wrappers import AtariWrapper

    gym.register_envs(ale_py)
    env = AtariWrapper(gym.make("ALE/MontezumaRevenge-v5", frameskip=1, repeat_action_probability=0.0), noop_max=0,
                       terminal_on_life_loss=False)
    reference, _ = env.reset(seed=0)
    space = ImageGoalSpace(landmarks=[(44, 40, 53, 45), (34, 3, 42, 9)], reference=reference)
    space.bind(env)
    assert space.game == "montezuma_revenge" and space.key(reference) == ("landmarks", ())
    for _ in range(11):  # down the middle ladder (y 251 -> 192 in the RAM)
        obs, *_ = env.step(5)
    assert env.unwrapped.ale.getRAM()[43] == 192
    assert space.key(obs) == ("landmarks", (0,)) and space.changed(obs)[0] > 0.5


def test_montezuma_landmarks_are_attained_where_the_agent_stands_and_where_the_key_was_taken() -> None:
    """The named goal space ``montezuma_landmarks``: its reference the first frame read (the reset's), no landmark at
    the start; the agent placed (RAM x, y) at each place of the way attains that place's box alone; the key's box
    once the key has left the first room (its objects' bit 0x01); a door's box once the agent, placed on the door's
    floor with the key (inventory bit 0x02), has walked into it and opened it (reward 300, clipped to 1), and not
    where the agent without the key stands stopped at it."""
    ale_py = pytest.importorskip("ale_py", reason='needs the [atari] extra: pip install "sb3_hhp[atari]"')
    from stable_baselines3.common.atari_wrappers import AtariWrapper

    from sb3_hhp.goals.image import MONTEZUMA_LANDMARKS

    gym.register_envs(ale_py)

    def placed(ram: dict, action: int = 0, steps: int = 2, settle: int = 0) -> tuple:
        """The goal space and the key of the frame after ``steps`` of ``action`` from the RAM's ``ram`` set after
        ``settle`` no-ops (the reset's jump over), and the rewards of those steps."""
        env = AtariWrapper(gym.make("ALE/MontezumaRevenge-v5", frameskip=1, repeat_action_probability=0.0), noop_max=0,
                           terminal_on_life_loss=False)
        space = make_goal_space("montezuma_landmarks", env)
        assert space.reference is None  # "first": the first frame read
        start, _ = env.reset(seed=0)
        assert space.key(start) == ("landmarks", ()) and np.array_equal(space.reference, start[..., 0])
        for _ in range(settle):
            env.step(0)
        for address, value in ram.items():
            env.unwrapped.ale.setRAM(address, value)
        rewards = []
        for _ in range(steps):
            obs, reward, *_ = env.step(action)
            rewards.append(reward)
        return space, space.key(obs), rewards

    names = list(MONTEZUMA_LANDMARKS)
    places = {"middle ladder's foot": (77, 192), "rope": (109, 205), "right ladder's top": (133, 192),
              "right ladder's foot": (133, 148), "left ladder's foot": (21, 148), "left ladder's top": (21, 192)}
    for name, (x, y) in places.items():
        space, key, _ = placed({42: x, 43: y})
        assert key == ("landmarks", (names.index(name),)), name
        assert space.describe(key) == name
    space, key, _ = placed({67: 30})  # the key gone from the first room
    assert space.describe(key) == "key"
    left, right = 4, 3  # the ALE actions LEFT and RIGHT
    for name, x, action in (("left door", 40, left), ("right door", 115, right)):  # on the door's floor, walking to it
        space, key, rewards = placed({42: x, 65: 0x02}, action, steps=8, settle=10)
        assert 1.0 in rewards and key == ("landmarks", (names.index(name),)), (name, rewards, key)
        space, key, rewards = placed({42: x}, action, steps=20, settle=10)  # no key: stopped at the closed door
        assert 1.0 not in rewards and key == ("landmarks", ()), (name, rewards, key)


def test_reference_first_and_its_bad_input() -> None:
    """``reference="first"``: the boxes are checked against the env's frames when bound, the first frame read becomes
    the reference, later frames of another shape are refused; another string is refused."""
    room = gym.make("MiniGrid-Empty-8x8-v0", render_mode="rgb_array")
    with pytest.raises(ValueError, match="reference must be a frame of the env or 'first'"):
        ImageGoalSpace(landmarks=[(0, 0, 4, 4)], reference="last")
    frames = np.zeros((2, 20, 30), dtype=np.uint8)
    frames[1, 2:6, 3:7] = 255
    space = ImageGoalSpace(landmarks={"corner": (2, 3, 6, 7)}, reference="first")
    outside = ImageGoalSpace(landmarks=[(0, 0, 21, 5)], reference="first")
    env = gym.wrappers.TransformObservation(room, lambda obs: frames[0], gym.spaces.Box(0, 255, (20, 30), np.uint8))
    with pytest.raises(ValueError, match=r"landmark 0 \(0, 0, 21, 5\) lies outside the 20x30 frame"):
        outside.bind(env)
    space.bind(env)
    assert space.reference is None
    assert space.key(frames[0]) == ("landmarks", ()) and space.key(frames[1]) == ("landmarks", (0,))
    assert space.describe(space.key(frames[1])) == "corner"
    with pytest.raises(ValueError, match=r"reference frame has shape \(20, 30\) but this observation has frames of shape"):
        space.key(np.zeros((20, 31), dtype=np.uint8))
