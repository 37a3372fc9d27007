"""Double DQN with prioritized experience replay, usable by any SB3 off-policy algorithm."""

from sb3_hhp.dqn.buffers import PrioritizedReplayBuffer, PrioritizedReplayBufferSamples
from sb3_hhp.dqn.dqn import DoubleDQN, double_q_target
from sb3_hhp.dqn.sum_tree import SumTree

__all__ = ["DoubleDQN", "PrioritizedReplayBuffer", "PrioritizedReplayBufferSamples", "SumTree", "double_q_target"]
