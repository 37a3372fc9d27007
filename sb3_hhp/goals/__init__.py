"""Goal spaces: state -> sub-goal, done(s, g), similarity and images, one per domain."""

from typing import Union

import gymnasium as gym

from sb3_hhp.goals.base import SUCCESS_KEY, GoalSpace
from sb3_hhp.goals.fetch import FetchFlatObs, FetchGoalSpace, find_fetch
from sb3_hhp.goals.image import MONTEZUMA_LANDMARKS, ImageGoalSpace
from sb3_hhp.goals.minigrid import MiniGridEgocentricObs, MiniGridGoalSpace, find_minigrid, register_minigrid_tasks

#: in the order "auto" tries them
GOAL_SPACES: dict[str, type[GoalSpace]] = {"minigrid": MiniGridGoalSpace, "fetch": FetchGoalSpace, "image": ImageGoalSpace}
#: goal spaces with settings, by name (for the YAML): MiniGrid keys that tell objects apart by colour (several keys)
NAMED_GOAL_SPACES = {
    "minigrid_color": lambda: MiniGridGoalSpace(use_color=True),
    # the minigrid entry's: colours related (a key to the door it opens) and objects in the way marked where the
    # task's layouts call for them
    "minigrid_open_doors": lambda: MiniGridGoalSpace(use_color="auto", keep_doors_open=True, mark_blockers="auto",
                                                     count_blockers="auto"),
    # the entry's with colours related for any two objects, not only a key and a door (the entry's before)
    "minigrid_open_doors_any_colours": lambda: MiniGridGoalSpace(use_color="auto", keep_doors_open=True,
                                                                 mark_blockers="auto", count_blockers="auto",
                                                                 color_relation="any"),
    # that without marking objects in the way (the entry's before both)
    "minigrid_open_doors_unmarked": lambda: MiniGridGoalSpace(use_color="auto", keep_doors_open=True,
                                                              color_relation="any"),
    "minigrid_count_doors": lambda: MiniGridGoalSpace(keep_doors_open=True, count_open_doors=True),
    "minigrid_color_open_doors": lambda: MiniGridGoalSpace(use_color=True, keep_doors_open=True),
    "minigrid_open_doors_blockers": lambda: MiniGridGoalSpace(keep_doors_open=True, mark_blockers=True),
    "minigrid_open_doors_blockers_counted": lambda: MiniGridGoalSpace(keep_doors_open=True, mark_blockers=True,
                                                                      count_blockers=True),
    # Montezuma's Revenge: the paper's detector boxes of its first room, compared with the run's first frame
    "montezuma_landmarks": lambda: ImageGoalSpace(landmarks=MONTEZUMA_LANDMARKS, reference="first"),
    # Fetch tasks with an object: keys of the object's place alone, without the gripper's flag
    "fetch_places": lambda: FetchGoalSpace(gripper=False),
}


def wrap_env(env: gym.Env) -> gym.Env:
    """Give a raw env the observation its goal space reads (MiniGrid: :class:`~sb3_hhp.goals.minigrid.MiniGridEgocentricObs`; Fetch:
    :class:`~sb3_hhp.goals.fetch.FetchFlatObs`)."""
    if find_minigrid(env) is not None and not MiniGridGoalSpace.supports(env):
        return MiniGridEgocentricObs(env)
    if find_fetch(env) is not None and isinstance(env.observation_space, gym.spaces.Dict):
        return FetchFlatObs(env)
    return env


def make_goal_space(goal_space: Union[str, GoalSpace], env: gym.Env) -> GoalSpace:
    """The goal space called ``goal_space`` ("auto": the first that supports ``env``), checked against ``env``."""
    if isinstance(goal_space, GoalSpace):
        candidates = [goal_space]
    elif goal_space == "auto":
        candidates = [cls() for cls in GOAL_SPACES.values() if cls.supports(env)]
    elif goal_space in GOAL_SPACES:
        candidates = [GOAL_SPACES[goal_space]()]
    elif goal_space in NAMED_GOAL_SPACES:
        candidates = [NAMED_GOAL_SPACES[goal_space]()]
    else:
        raise ValueError(f"Unknown goal space {goal_space!r}: use 'auto', one of {sorted({**GOAL_SPACES, **NAMED_GOAL_SPACES})} "
                         "or a GoalSpace")
    if not candidates or not candidates[0].supports(env):
        raise ValueError(
            f"No goal space supports this env (observation space {env.observation_space}). "
            "HhP supports MiniGrid tasks wrapped with sb3_hhp.goals.minigrid.MiniGridEgocentricObs "
            "(sb3_hhp.goals.wrap_env(env) does it), gymnasium-robotics Fetch tasks wrapped with "
            "sb3_hhp.goals.fetch.FetchFlatObs (wrap_env does it too) and fixed-layout envs that observe uint8 images of at least "
            "8x8 pixels (goal_space='image'; Atari: stable_baselines3.common.atari_wrappers.AtariWrapper); "
            "pass goal_space= a GoalSpace for other envs."
        )
    candidates[0].bind(env)
    return candidates[0]


__all__ = ["GOAL_SPACES", "NAMED_GOAL_SPACES", "SUCCESS_KEY", "FetchFlatObs", "FetchGoalSpace", "GoalSpace", "ImageGoalSpace",
           "MiniGridEgocentricObs", "MiniGridGoalSpace", "make_goal_space", "register_minigrid_tasks", "wrap_env"]
