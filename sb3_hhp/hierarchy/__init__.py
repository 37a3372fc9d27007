"""The hierarchy: the option runner, the public semi-MDP (:class:`HierarchicalEnv`) and the sub-goal learners."""

from sb3_hhp.hierarchy.options import OptionRunner, PrimitiveVecEnv, Subgoal, SubgoalSet, option_terminal
from sb3_hhp.hierarchy.semi_mdp import HierarchicalEnv

__all__ = ["HierarchicalEnv", "OptionRunner", "PrimitiveVecEnv", "Subgoal", "SubgoalSet", "option_terminal"]
