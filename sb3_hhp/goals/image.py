"""Image goal space for fixed-layout image envs (Atari rooms, a fixed maze drawn as pixels).

When the layout does not change between episodes, the frame itself can stand for a sub-goal (design
decisions: a sub-goal recurs). Exact frames rarely recur (a sprite moves a pixel, a timer ticks), so the sub-goal key is a
*cell*: the current frame in grayscale, shrunk by area averaging to ``cell_shape`` and quantised to
``levels`` intensities, as Go-Explore's cell representation (Ecoffet et al., 2021). Two states share a
key when they look alike at that coarse scale, which makes keys recur, visits countable (CSD's "visited
several times") and ``done(s, g)`` a key comparison. The discovery gate compares the frames themselves
with SSIM (the paper's similarity, section 5.1), and people see the frame.

Observations: ``(H, W)``, ``(H, W, C)`` or ``(C, H, W)`` uint8 images (SB3's image-space test). Three
channels are read as RGB; any other channel count as a stack of grayscale frames, oldest first (SB3's
``VecFrameStack``, gymnasium's ``FrameStackObservation``), whose last frame is the current one.
"""

import zlib
from collections.abc import Hashable, Sequence
from typing import Optional

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first

from sb3_hhp.goals.base import SUCCESS_KEY, GoalSpace
from sb3_hhp.goals.similarity import ssim_to_set

#: smallest image side accepted (smaller "images" are better served by a goal space of their own)
MIN_SIDE = 8


def _channels_first(shape: tuple) -> bool:
    return len(shape) == 3 and is_image_space_channels_first(spaces.Box(0, 255, shape, np.uint8))


class ImageGoalSpace(GoalSpace):
    """Sub-goal key = the frame shrunk to ``cell_shape`` and quantised to ``levels`` gray levels.

    :param cell_shape: (height, width) of the cell; Go-Explore's Montezuma cells are 8 x 11
    :param levels: gray levels of the cell (2-256); fewer levels and smaller cells merge more states
    """

    name = "image"

    def __init__(self, cell_shape: tuple[int, int] = (8, 11), levels: int = 8) -> None:
        if len(cell_shape) != 2 or min(cell_shape) < 1:
            raise ValueError(f"cell_shape must be (height, width) with both >= 1, got {cell_shape}")
        if not 2 <= levels <= 256:
            raise ValueError(f"levels must be in [2, 256], got {levels}")
        self.cell_shape = (int(cell_shape[0]), int(cell_shape[1]))
        self.levels = int(levels)

    @classmethod
    def supports(cls, env: gym.Env) -> bool:
        space = env.observation_space
        if not isinstance(space, spaces.Box) or space.dtype != np.uint8 or len(space.shape) not in (2, 3):
            return False
        if len(space.shape) == 2:
            image = spaces.Box(0, 255, (*space.shape, 1), np.uint8)
            ok = bool(np.all(space.low == 0) and np.all(space.high == 255))
        else:
            image, ok = space, is_image_space(space, check_channels=False)
        height, width = cls._height_width(image.shape)
        return ok and min(height, width) >= MIN_SIDE

    @staticmethod
    def _height_width(shape: tuple) -> tuple[int, int]:
        if len(shape) == 2:
            return int(shape[0]), int(shape[1])
        return (int(shape[1]), int(shape[2])) if _channels_first(shape) else (int(shape[0]), int(shape[1]))

    @staticmethod
    def frame(obs: np.ndarray) -> np.ndarray:
        """The current frame of an observation, channel last: (H, W, 3) for RGB, else (H, W) grayscale."""
        obs = np.asarray(obs)
        if obs.ndim == 2:
            return obs
        if _channels_first(obs.shape):
            obs = np.moveaxis(obs, 0, -1)
        return obs if obs.shape[-1] == 3 else obs[..., -1]

    def cell(self, obs: np.ndarray) -> np.ndarray:
        """The cell of an observation: (height, width) uint8 gray levels in [0, levels)."""
        frame = self.frame(obs)
        gray = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY) if frame.ndim == 3 else frame
        small = cv2.resize(np.ascontiguousarray(gray), self.cell_shape[::-1], interpolation=cv2.INTER_AREA)
        return (small.astype(np.uint16) * self.levels // 256).astype(np.uint8)

    def key(self, obs: np.ndarray) -> Hashable:
        return ("cell", self.cell(obs).tobytes())

    def similarity(self, key: Hashable, obs: np.ndarray, goal_keys: Sequence[Hashable], goal_obs: np.ndarray) -> np.ndarray:
        """SSIM of the candidate's frame with each stored sub-goal's frame, clipped to [0, 1]; 1 for an equal key."""
        if len(goal_keys) == 0:
            return np.zeros(0, dtype=np.float64)
        frames = np.stack([self.frame(o) for o in np.asarray(goal_obs)])
        values = np.clip(ssim_to_set(self.frame(obs), frames), 0.0, 1.0)
        values[[other == key for other in goal_keys]] = 1.0
        return values

    def image_of(self, obs: np.ndarray) -> Optional[np.ndarray]:
        """The current frame as RGB (H, W, 3)."""
        frame = self.frame(obs)
        return np.ascontiguousarray(frame if frame.ndim == 3 else np.repeat(frame[..., None], 3, axis=-1), dtype=np.uint8)

    def describe(self, key: Hashable) -> str:
        if key == SUCCESS_KEY:
            return "task solved"
        if isinstance(key, tuple) and len(key) == 2 and key[0] == "cell":
            return f"cell {zlib.crc32(key[1]):08x}"
        return str(key)
