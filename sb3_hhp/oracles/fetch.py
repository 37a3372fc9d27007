"""A scripted (privileged) oracle for the gymnasium-robotics Fetch tasks (Reach, Push, PickAndPlace, Slide)."""

import numpy as np

from sb3_hhp.oracles.base import Label, Oracle, Query

REQUIRED_KEYS = ("desired_goal", "goal1_achieved", "goal2_achieved")


class FetchScriptedOracle(Oracle):
    """Prefer the sub-goal that brings the task closer to its desired goal.

    Each query's ``info`` must hold ``"desired_goal"`` (the episode's target position, metres),
    ``"goal1_achieved"`` and ``"goal2_achieved"``: the position (metres) of the object (of the gripper
    for Reach) in each sub-goal, i.e. the ``achieved_goal`` of the Fetch observation where the sub-goal
    was found. The sub-goal whose achieved position is nearer (Euclidean distance) to the desired goal
    is preferred; distances within ``equal_tolerance`` of each other give ``EQUAL``. On the tasks with an object the
    info may also say whether each sub-goal has the gripper at the object (``"goal1_gripper_at_object"``,
    ``"goal2_gripper_at_object"``): a person sees that the object moves only once the gripper is at it, so such a
    sub-goal counts ``gripper_bonus`` nearer than its place (with 0.02 m: the gripper at the object where it lies is
    better than the object left there, worse than the object 2 cm nearer the target).

    :param name: annotator name recorded with every answer
    :param equal_tolerance: distance difference (metres, >= 0) under which both sub-goals are equally good
    :param gripper_bonus: metres (>= 0) a sub-goal with the gripper at the object counts nearer the target
    """

    def __init__(self, name: str = "scripted", equal_tolerance: float = 1e-3, gripper_bonus: float = 0.02) -> None:
        if not equal_tolerance >= 0:
            raise ValueError(f"equal_tolerance must be >= 0 metres, got {equal_tolerance}")
        if not gripper_bonus >= 0:
            raise ValueError(f"gripper_bonus must be >= 0 metres, got {gripper_bonus}")
        super().__init__(name)
        self.equal_tolerance = float(equal_tolerance)
        self.gripper_bonus = float(gripper_bonus)

    def answer(self, query: Query) -> Label:
        missing = [key for key in REQUIRED_KEYS if key not in query.info]
        if missing:
            raise ValueError(
                f"FetchScriptedOracle needs query.info keys {list(REQUIRED_KEYS)} (positions in metres); "
                f"query {query.query_id} lacks {missing}"
            )
        desired = np.asarray(query.info["desired_goal"], dtype=np.float64)
        achieved1 = np.asarray(query.info["goal1_achieved"], dtype=np.float64)
        achieved2 = np.asarray(query.info["goal2_achieved"], dtype=np.float64)
        if not desired.shape == achieved1.shape == achieved2.shape:
            raise ValueError(
                "desired_goal, goal1_achieved and goal2_achieved must have the same shape, got "
                f"{desired.shape}, {achieved1.shape}, {achieved2.shape}"
            )
        distance1, distance2 = (
            float(np.linalg.norm(achieved - desired)) - self.gripper_bonus * bool(query.info.get(f"{name}_gripper_at_object"))
            for achieved, name in ((achieved1, "goal1"), (achieved2, "goal2")))
        if abs(distance1 - distance2) <= self.equal_tolerance:
            return Label.EQUAL
        return Label.FIRST if distance1 < distance2 else Label.SECOND
