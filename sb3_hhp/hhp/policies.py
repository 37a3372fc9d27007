"""Meta-controller policies: SB3's DQN Q-networks over the (growing) set of sub-goals, and a features
extractor that lets the meta-controller read the goal space's layout-free description of a state."""

from typing import Any

import gymnasium as gym
import torch as th
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.dqn.policies import CnnPolicy, DQNPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["CnnPolicy", "DQNPolicy", "GoalSpaceFeatures", "GridCNN", "MlpPolicy", "MultiInputPolicy"]


class GridCNN(BaseFeaturesExtractor):
    """A small CNN for symbolic grids (MiniGrid's ``(H, W, 3)`` encodings of object, colour and state): three 2x2
    convolutions of 16, 32 and 64 channels and a linear layer, as MiniGrid's documentation trains on 7x7 views.
    SB3's NatureCNN (8x8 kernels of stride 4) is made for 84x84 frames and refuses these observations.

    :param observation_space: a channel-last Box of at least 4x4 cells
    :param features_dim: size of the output
    """

    def __init__(self, observation_space: gym.spaces.Box, features_dim: int = 128) -> None:
        super().__init__(observation_space, features_dim)
        height, width, channels = observation_space.shape
        self.cnn = th.nn.Sequential(
            th.nn.Conv2d(channels, 16, 2), th.nn.ReLU(), th.nn.Conv2d(16, 32, 2), th.nn.ReLU(),
            th.nn.Conv2d(32, 64, 2), th.nn.ReLU(), th.nn.Flatten(),
        )
        self.linear = th.nn.Sequential(th.nn.Linear(64 * (height - 3) * (width - 3), features_dim), th.nn.ReLU())

    def forward(self, observations: th.Tensor) -> th.Tensor:
        return self.linear(self.cnn(observations.float().permute(0, 3, 1, 2)))


class GoalSpaceFeatures(BaseFeaturesExtractor):
    """Features = :meth:`GoalSpace.features <sb3_hhp.goals.base.GoalSpace.features>` of the observations, a fixed
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
