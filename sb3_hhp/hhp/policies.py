"""Meta-controller policies: SB3's DQN Q-networks over the (growing) set of sub-goals."""

from stable_baselines3.dqn.policies import CnnPolicy, DQNPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["CnnPolicy", "DQNPolicy", "MlpPolicy", "MultiInputPolicy"]
