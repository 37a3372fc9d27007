"""Curiosity: Random Network Distillation (eq. 7), the memory Omega and novelty progress (eq. 8), and
RND's intrinsic reward for any SB3 algorithm as a VecEnv reward wrapper."""

from sb3_hhp.curiosity.rnd import RND, RNDSnapshot
from sb3_hhp.curiosity.vec_rnd import VecRNDReward

__all__ = ["RND", "RNDSnapshot", "VecRNDReward"]
