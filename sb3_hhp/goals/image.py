"""Image goal space for fixed-layout image envs (Atari rooms, a fixed maze drawn as pixels).

When the layout does not change between episodes, the frame itself can stand for a sub-goal (design
decisions: a sub-goal recurs). Exact frames rarely recur (a sprite moves a pixel, a timer ticks), so the sub-goal key is a
*cell*: the current frame in grayscale, shrunk by area averaging to ``cell_shape`` and quantised to
``levels`` intensities, as Go-Explore's cell representation (Ecoffet et al., 2021). Two states share a
key when they look alike at that coarse scale, which makes keys recur, visits countable (CSD's "visited
several times") and ``done(s, g)`` a key comparison. The discovery gate compares the frames themselves
with SSIM (the paper's similarity, section 5.1), and people see the frame.

*Landmarks* (``landmarks=[(row0, col0, row1, col1), ...]``) are the paper's sub-goal detector for Atari (section 5.1,
after hg-DAgger, Le et al., 2018): each landmark is a box of the frame, *attained* where at least
``changed_fraction`` (20 %) of its pixels differ from a fixed ``reference`` frame. The key of a state is then the set
of landmarks it attains, and a sub-goal, a set of landmarks, is reached where all of them are attained. The
reference is one frame for the whole run (hg-DAgger's detector compares with the game's first screen), not the frame
where the option began: ``done(s, g)`` must be a function of the state alone, since the sub-goal learners' shared
replay decides it from each transition's key for every sub-goal when a batch is drawn.
``reference="first"`` takes the first frame the goal space reads (the first observation of the run) as the
reference. :data:`MONTEZUMA_LANDMARKS` are boxes of Montezuma's first room (``goal_space: montezuma_landmarks``).

Observations: ``(H, W)``, ``(H, W, C)`` or ``(C, H, W)`` uint8 images (SB3's image-space test). Three
channels are read as RGB; any other channel count as a stack of grayscale frames, oldest first (SB3's
``VecFrameStack``, gymnasium's ``FrameStackObservation``), whose last frame is the current one.

On ALE Montezuma's Revenge the goal space records a few bytes of the console's RAM at each sub-goal choice
(:meth:`ImageGoalSpace.snapshot`: the room, the agent's position, the inventory, the objects, the lives), the facts
:class:`~sb3_hhp.oracles.montezuma.MontezumaScriptedOracle` answers from; its module says how each address was verified.
"""

import math
import zlib
from collections.abc import Hashable, Sequence
from typing import Any, Optional

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.atari_wrappers import MaxAndSkipEnv
from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first

from sb3_hhp.goals.base import SUCCESS_KEY, GoalSpace
from sb3_hhp.goals.similarity import ssim_to_set

#: smallest image side accepted (smaller "images" are better served by a goal space of their own)
MIN_SIDE = 8
#: the ROM name ale-py gives Montezuma's Revenge
MONTEZUMA = "montezuma_revenge"
#: the RAM bytes recorded on Montezuma's Revenge, by fact (verified in :mod:`sb3_hhp.oracles.montezuma`)
MONTEZUMA_RAM = {"room": 3, "x": 42, "y": 43, "inventory": 65, "room_objects": 66, "first_room_objects": 67,
                 "lives": 58, "death_timer": 55}
_MONTEZUMA_ADDRESSES = np.array(list(MONTEZUMA_RAM.values()), dtype=np.int64)
#: landmark boxes ``(row0, col0, row1, col1)`` of Montezuma's first room in SB3's ``AtariWrapper`` frames (84x84), each
#: where the agent's sprite stands at a place on the way to the key and back (RAM position ``(x, y)`` of
#: :mod:`sb3_hhp.oracles.montezuma`: column about x / 2 + 1.5, top row about 46 + 0.39 (192 - y)), and the key, which
#: leaves its box when taken, and the two doors, which leave theirs when opened with the key (the agent stopped at a
#: closed door changes 8 % of its box). Read from frames of the agent placed there (tests/test_goals_image.py); none
#: lies on the start, whose frame is the reference.
MONTEZUMA_LANDMARKS = {
    "middle ladder's foot": (44, 40, 53, 45),  # (77, 192)
    "rope": (40, 55, 50, 62),                  # (109, 205)
    "right ladder's top": (45, 66, 55, 74),    # (133, 192)
    "right ladder's foot": (62, 67, 72, 75),   # (133, 148)
    "left ladder's foot": (62, 9, 72, 17),     # (21, 148)
    "left ladder's top": (45, 9, 55, 17),      # (21, 192)
    "key": (39, 6, 46, 11),
    "left door": (21, 10, 37, 13),
    "right door": (21, 71, 37, 74),
}


def _channels_first(shape: tuple) -> bool:
    return len(shape) == 3 and is_image_space_channels_first(spaces.Box(0, 255, shape, np.uint8))


#: the height and width of an ALE game's own screen, which the image goal space refuses to read unwrapped
ALE_SCREEN = (210, 160)


def ale_game(env: gym.Env) -> Optional[str]:
    """The ROM name of the ALE game underneath ``env`` (``"montezuma_revenge"``), None when it is not an ALE env."""
    base = getattr(env, "unwrapped", env)
    if not type(base).__module__.startswith("ale_py") or not hasattr(base, "ale"):
        return None
    return getattr(base, "_game", None)


def double_frame_skip(env: gym.Env) -> Optional[tuple[int, int]]:
    """(ALE's frame skip, a wrapper's) when an ALE env skips frames itself (the ``v5`` ids skip 4 by default) under a
    wrapper that skips frames again (SB3's ``AtariWrapper`` and its ``MaxAndSkipEnv``): each step then spans their
    product of frames (16); None otherwise."""
    if ale_game(env) is None:
        return None
    own = getattr(env.unwrapped, "_frameskip", 1)
    if not isinstance(own, int) or own <= 1:  # a tuple is a random skip, which no wrapper stacks on
        return None
    layer = env
    while isinstance(layer, gym.Wrapper):
        if isinstance(layer, MaxAndSkipEnv) and layer._skip > 1:
            return own, layer._skip
        layer = layer.env
    return None


def montezuma_facts(ram: np.ndarray) -> dict[str, Any]:
    """The facts of a Montezuma's Revenge state from its 128 bytes of RAM (or from the bytes of
    :data:`MONTEZUMA_RAM` alone, in that order), as JSON values."""
    ram = np.frombuffer(ram, dtype=np.uint8) if isinstance(ram, bytes) else np.asarray(ram, dtype=np.uint8)
    values = ram[_MONTEZUMA_ADDRESSES] if len(ram) == 128 else ram
    return {"game": MONTEZUMA, **{name: int(value) for name, value in zip(MONTEZUMA_RAM, values)}}


class ImageGoalSpace(GoalSpace):
    """Sub-goal key = the frame shrunk to ``cell_shape`` and quantised to ``levels`` gray levels; with ``landmarks``,
    the landmarks (detector boxes) whose pixels changed from ``reference``.

    :param cell_shape: (height, width) of the cell; Go-Explore's Montezuma cells are 8 x 11
    :param levels: gray levels of the cell (2-256); fewer levels and smaller cells merge more states
    :param landmarks: detector boxes ``(row0, col0, row1, col1)`` in pixels of the frame the goal space reads (84x84 under
        SB3's ``AtariWrapper``): rows ``row0`` to ``row1 - 1`` and columns ``col0`` to ``col1 - 1``, as numpy slices.
        None (the default): cells
    :param reference: with ``landmarks``, the frame the boxes are compared with: an observation of the env (e.g. its
        first after a reset), read as every observation is (the last frame of a stack); ``"first"``: the first frame this
        goal space reads (the run's first observation; the boxes are checked against the env's frames when bound)
    :param changed_fraction: share in (0, 1] of a box's pixels that must differ from ``reference`` for its landmark to be
        attained; the paper's 0.2. A pixel differs when its value (any channel of an RGB frame) does
    """

    name = "image"
    #: the detector boxes (None: cells); class defaults for goal spaces pickled before landmarks existed
    landmarks: Optional[tuple[tuple[int, int, int, int], ...]] = None
    reference: Optional[np.ndarray] = None
    changed_fraction = 0.2
    #: the ALE game of the env this goal space was bound to (:meth:`bind`; None: not an ALE env, or not bound)
    game: Optional[str] = None
    #: the landmark boxes' names, one each (``landmarks`` given as a mapping), or None
    landmark_names: Optional[tuple[str, ...]] = None

    def __init__(self, cell_shape: tuple[int, int] = (8, 11), levels: int = 8,
                 landmarks: Optional[Sequence[Sequence[int]]] = None, reference: Optional[np.ndarray] = None,
                 changed_fraction: float = 0.2) -> None:
        if len(cell_shape) != 2 or min(cell_shape) < 1:
            raise ValueError(f"cell_shape must be (height, width) with both >= 1, got {cell_shape}")
        if not 2 <= levels <= 256:
            raise ValueError(f"levels must be in [2, 256], got {levels}")
        self.cell_shape = (int(cell_shape[0]), int(cell_shape[1]))
        self.levels = int(levels)
        if not 0 < changed_fraction <= 1:
            raise ValueError(f"changed_fraction must be in (0, 1] (the share of a landmark box's pixels that must change), "
                             f"got {changed_fraction}")
        self.changed_fraction = float(changed_fraction)
        if landmarks is None:
            if reference is not None:
                raise ValueError("reference is the frame landmark boxes are compared with: give landmarks too, or leave "
                                 "reference out for cells")
            return
        if reference is None:
            raise ValueError("landmarks need a reference frame to compare their boxes with: pass reference= an "
                             "observation of the env, e.g. env.reset()[0], or reference='first' (the first frame read)")
        if isinstance(landmarks, dict):
            self.landmark_names = tuple(str(name) for name in landmarks)
            landmarks = list(landmarks.values())
        if isinstance(reference, str):
            if reference != "first":
                raise ValueError(f"reference must be a frame of the env or 'first' (the first frame read), got {reference!r}")
            self.landmarks = self._check_boxes(landmarks, None)  # against the env's frames when bound
        else:
            self.reference = np.array(self.frame(reference), dtype=np.uint8, copy=True)
            self.landmarks = self._check_boxes(landmarks, self.reference.shape[:2])
        # the fewest changed pixels that attain each box: changed >= changed_fraction * area
        self._needed = tuple(max(1, math.ceil(self.changed_fraction * (r1 - r0) * (c1 - c0) - 1e-9))
                             for r0, c0, r1, c1 in self.landmarks)

    @staticmethod
    def _check_boxes(landmarks: Sequence[Sequence[int]], size: Optional[tuple[int, int]]
                     ) -> tuple[tuple[int, int, int, int], ...]:
        """The boxes as tuples, checked to be boxes and (``size``: (height, width) of the frame) to lie inside it."""
        height, width = size if size is not None else (math.inf, math.inf)
        if len(landmarks) == 0:
            raise ValueError("landmarks must hold at least one box (row0, col0, row1, col1); leave it out for cells")
        boxes = []
        for index, box in enumerate(landmarks):
            if len(box) != 4 or not all(isinstance(v, (int, np.integer)) for v in box):
                raise ValueError(f"landmark {index} must be four integers (row0, col0, row1, col1), got {box!r}")
            r0, c0, r1, c1 = (int(v) for v in box)
            if not (r0 < r1 and c0 < c1):
                raise ValueError(f"landmark {index} {(r0, c0, r1, c1)} is empty or inverted: give (row0, col0, row1, col1) "
                                 "with row0 < row1 and col0 < col1 (row1 and col1 are excluded, as in a numpy slice)")
            if r0 < 0 or c0 < 0 or r1 > height or c1 > width:
                raise ValueError(f"landmark {index} {(r0, c0, r1, c1)} lies outside the {height}x{width} frame: rows must "
                                 f"be within [0, {height}] and columns within [0, {width}] (boxes are in pixels of the "
                                 "frame the goal space reads, 84x84 under AtariWrapper)")
            boxes.append((r0, c0, r1, c1))
        return tuple(boxes)

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

    def bind(self, env: gym.Env) -> None:
        """Record the env's ALE game (:attr:`game`: a Montezuma's Revenge env gets its scripted oracle) and check that
        its frames have the reference's shape, which the landmark boxes were checked against."""
        self.game = ale_game(env)
        if self.game is not None and self._height_width(env.observation_space.shape) == ALE_SCREEN:
            raise ValueError(f"This ALE env ({self.game}) observes its raw {ALE_SCREEN[0]}x{ALE_SCREEN[1]} screen: wrap it "
                             "with stable_baselines3.common.atari_wrappers.AtariWrapper (84x84 gray frames, a life lost "
                             "ending the episode; make_atari_env does it), as the atari entry's env_wrapper does")
        skips = double_frame_skip(env)
        if skips is not None:
            raise ValueError(f"This ALE env ({self.game}) skips {skips[0]} frames a step itself and its frame wrapper "
                             f"{skips[1]} more, {skips[0] * skips[1]} frames a step: make it with frameskip=1 "
                             "(gym.make(id, frameskip=1), make_atari_env(id, env_kwargs=dict(frameskip=1)), or "
                             "env_kwargs: {frameskip: 1} in a YAML entry, as the atari entry has)")
        self.facts_per_step = self.game == MONTEZUMA  # 8 bytes of RAM a step
        if self.landmarks is not None:
            frame = self.frame(np.zeros(env.observation_space.shape, dtype=np.uint8))
            if self.reference is None:  # reference "first": the boxes against the env's frames
                self._check_boxes(self.landmarks, frame.shape[:2])
            else:
                self._check_frame(frame, "the env observes")

    def _check_frame(self, frame: np.ndarray, source: str) -> None:
        if self.reference is None:  # reference "first": this frame, the first read, becomes it
            self._check_boxes(self.landmarks, frame.shape[:2])
            self.reference = np.array(frame, dtype=np.uint8, copy=True)
            return
        if frame.shape != self.reference.shape:
            raise ValueError(f"The landmarks' reference frame has shape {self.reference.shape} but {source} frames of shape "
                             f"{frame.shape}: take the reference from an observation of this env (wrapped as it is)")

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

    def changed(self, obs: np.ndarray) -> np.ndarray:
        """The share of each landmark box's pixels that differ from the reference, ``(n_landmarks,)`` in [0, 1]."""
        frame = self.frame(obs)
        self._check_frame(frame, "this observation has")
        return np.array([self._changed_pixels(frame, box) / ((box[2] - box[0]) * (box[3] - box[1]))
                         for box in self.landmarks])

    def _changed_pixels(self, frame: np.ndarray, box: tuple[int, int, int, int]) -> int:
        r0, c0, r1, c1 = box
        differs = frame[r0:r1, c0:c1] != self.reference[r0:r1, c0:c1]
        return int(np.count_nonzero(differs.any(axis=-1) if differs.ndim == 3 else differs))

    def attained(self, obs: np.ndarray) -> tuple[int, ...]:
        """The landmarks an observation attains, by index: at least ``changed_fraction`` of the box's pixels changed."""
        frame = self.frame(obs)
        self._check_frame(frame, "this observation has")
        return tuple(index for index, (box, needed) in enumerate(zip(self.landmarks, self._needed))
                     if self._changed_pixels(frame, box) >= needed)

    def key(self, obs: np.ndarray) -> Hashable:
        if self.landmarks is not None:
            return ("landmarks", self.attained(obs))
        return ("cell", self.cell(obs).tobytes())

    @staticmethod
    def _is_landmarks(key: Hashable) -> bool:
        return isinstance(key, tuple) and len(key) == 2 and key[0] == "landmarks"

    def achieved(self, key: Hashable, goal_key: Hashable) -> bool:
        """``done(s, g)``: every landmark of the sub-goal is attained in the state (the paper's rule for each box;
        the sub-goal of no landmark, where none is); cells and "task solved": equal keys."""
        if self._is_landmarks(key) and self._is_landmarks(goal_key) and goal_key[1]:
            return set(goal_key[1]) <= set(key[1])
        return key == goal_key

    def similarity(self, key: Hashable, obs: np.ndarray, goal_keys: Sequence[Hashable], goal_obs: np.ndarray) -> np.ndarray:
        """SSIM of the candidate's frame with each stored sub-goal's frame, clipped to [0, 1]; 1 for an equal key.
        With landmarks: 1 for an equal key, else 0 (the landmarks attained are all the detector says of a state;
        two frames of one room are alike by SSIM wherever the agent stands)."""
        if self.landmarks is not None:
            return super().similarity(key, obs, goal_keys, goal_obs)
        if len(goal_keys) == 0:
            return np.zeros(0, dtype=np.float64)
        frames = np.stack([self.frame(o) for o in np.asarray(goal_obs)])
        values = np.clip(ssim_to_set(self.frame(obs), frames), 0.0, 1.0)
        values[[other == key for other in goal_keys]] = 1.0
        return values

    def privileged(self, env: gym.Env) -> dict[str, Any]:
        """Montezuma's Revenge: its RAM facts (:func:`montezuma_facts`); other envs: none."""
        snapshot = self.snapshot(env)
        return self.facts(snapshot)

    def snapshot(self, env: gym.Env) -> Any:
        """Montezuma's Revenge: the bytes of :data:`MONTEZUMA_RAM` (8 bytes, read in about a microsecond); other envs:
        an empty dict (no facts)."""
        if ale_game(env) != MONTEZUMA:
            return {}
        return env.unwrapped.ale.getRAM()[_MONTEZUMA_ADDRESSES].tobytes()

    def facts(self, snapshot: Any) -> dict[str, Any]:
        return montezuma_facts(snapshot) if isinstance(snapshot, bytes) else dict(snapshot)

    def image_of(self, obs: np.ndarray) -> Optional[np.ndarray]:
        """The current frame as RGB (H, W, 3)."""
        frame = self.frame(obs)
        return np.ascontiguousarray(frame if frame.ndim == 3 else np.repeat(frame[..., None], 3, axis=-1), dtype=np.uint8)

    def describe(self, key: Hashable) -> str:
        if key == SUCCESS_KEY:
            return "task solved"
        if isinstance(key, tuple) and len(key) == 2 and key[0] == "cell":
            return f"cell {zlib.crc32(key[1]):08x}"
        if self._is_landmarks(key):
            if not key[1]:
                return "no landmark"
            if self.landmark_names is not None:
                return ", ".join(self.landmark_names[index] for index in key[1])
            return ("landmark " if len(key[1]) == 1 else "landmarks ") + ", ".join(str(index) for index in key[1])
        return str(key)
