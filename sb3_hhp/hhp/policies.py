"""Meta-controller policies: SB3's DQN Q-networks over the (growing) set of sub-goals, and a features
extractor that lets the meta-controller read the goal space's layout-free description of a state."""

from typing import Any

import gymnasium as gym
import torch as th
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.dqn.policies import CnnPolicy, DQNPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["CnnPolicy", "DQNPolicy", "GoalSpaceFeatures", "MlpPolicy", "MultiInputPolicy"]


class GoalSpaceFeatures(BaseFeaturesExtractor):
    """Features = :meth:`GoalSpace.features <sb3_hhp.goals.GoalSpace.features>` of the observations, a fixed
    (not learnt) description; the Q-network's ``net_arch`` layers learn on top of it.

    :param observation_space: the primitive observation space
    :param goal_space: a goal space whose ``features`` are not None
    """

    def __init__(self, observation_space: gym.spaces.Box, goal_space: Any) -> None:
        features_dim = goal_space.features_dim(observation_space)
        if features_dim is None:
            raise ValueError(f"{type(goal_space).__name__} has no features: the meta-controller must read observations")
        super().__init__(observation_space, features_dim=features_dim)
        self.goal_space = goal_space

    def forward(self, observations: th.Tensor) -> th.Tensor:
        obs = observations.detach().cpu().numpy().astype(self._observation_space.dtype)
        return th.as_tensor(self.goal_space.features(obs), device=observations.device)
