"""
The meta-controller's reward (eq. 3, section 4.1.2) with its preference-return normaliser sigma(R_p).

The subpolicies' rewards (eq. 5, 6) live with them, in :mod:`sb3_hhp.hierarchy.rewards`.
"""

from typing import Any

import numpy as np
import torch as th


def _check_beta(beta: float) -> None:
    if not 0.0 <= beta <= 1.0:
        raise ValueError(f"beta must be in [0, 1], got {beta}")


def _as_output(value: np.ndarray) -> float | np.ndarray:
    return float(value) if value.ndim == 0 else value


def meta_reward(
    extrinsic_return: float | np.ndarray | th.Tensor,
    bonus: float | np.ndarray | th.Tensor,
    sigma: float,
    beta: float = 0.7,
) -> float | np.ndarray | th.Tensor:
    """
    Reward of the meta-controller for choosing a sub-goal (eq. 3):
    ``r^e_t = beta * R_e + (1 - beta) * b_t / sigma(R_p)``.

    :param extrinsic_return: ``R_e``, the (undiscounted) extrinsic return collected while the subpolicy ran
    :param bonus: ``b_t = p_hat(s_t, g)``, the predictor's preference bonus for the chosen sub-goal
    :param sigma: ``sigma(R_p)``, e.g. :attr:`PreferenceReturnNormalizer.sigma` (> 0)
    :param beta: weight of the extrinsic return, in [0, 1] (paper: 0.7)
    :return: the reward, a float for scalar inputs, else an array (a tensor if either input is one)
    """
    _check_beta(beta)
    if not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be finite and > 0, got {sigma}")
    if isinstance(extrinsic_return, th.Tensor) or isinstance(bonus, th.Tensor):
        return beta * extrinsic_return + (1.0 - beta) * bonus / sigma  # eq. 3
    extrinsic = np.asarray(extrinsic_return, dtype=np.float64)
    preference = np.asarray(bonus, dtype=np.float64)
    return _as_output(beta * extrinsic + (1.0 - beta) * preference / sigma)  # eq. 3


class PreferenceReturnNormalizer:
    """
    ``sigma(R_p)`` of eq. 3 (section 5.1): the running average of the standard deviations of the discounted
    preference returns, computed on consecutive rollouts of ``rollout_length`` meta-steps.

    Bonuses are appended in the order the meta-steps happen (rollouts run across episode boundaries, as RND's
    non-episodic returns do). Each time ``rollout_length`` of them have accumulated, the rollout's returns
    ``R_p,t = sum_{k=t}^{L-1} gamma^(k-t) b_k`` (t = 0..L-1) are computed, their (population) standard deviation
    taken, and folded into the plain average of all rollouts' standard deviations so far.

    :attr:`sigma` is 1.0 (bonuses left unscaled) before the first complete rollout, and also while that average
    is below ``epsilon`` (e.g. every bonus so far was 0, or ``rollout_length`` is 1, whose single return has no
    spread): a zero spread carries no scale, so it is never used as a divisor.

    :param gamma: discount of the preference returns, in (0, 1] (paper: 0.99)
    :param rollout_length: meta-steps per rollout, >= 1 (paper: 64)
    :param epsilon: averages below this are treated as no spread (>= 0)
    """

    def __init__(self, gamma: float = 0.99, rollout_length: int = 64, epsilon: float = 1e-8) -> None:
        if not 0.0 < gamma <= 1.0:
            raise ValueError(f"gamma must be in (0, 1], got {gamma}")
        if int(rollout_length) != rollout_length or rollout_length < 1:
            raise ValueError(f"rollout_length must be an integer >= 1, got {rollout_length}")
        if not epsilon >= 0.0:
            raise ValueError(f"epsilon must be >= 0, got {epsilon}")
        self.gamma = float(gamma)
        self.rollout_length = int(rollout_length)
        self.epsilon = float(epsilon)
        self._pending: list[float] = []
        self.mean_std = 0.0
        self.num_rollouts = 0

    def discounted_returns(self, bonuses: np.ndarray) -> np.ndarray:
        """
        ``R_p,t = sum_{k >= t} gamma^(k-t) b_k`` within one rollout.

        :param bonuses: the rollout's bonuses, shape ``(L,)``
        :return: the returns, shape ``(L,)``
        """
        returns = np.empty(len(bonuses), np.float64)
        running = 0.0
        for t in range(len(bonuses) - 1, -1, -1):
            running = float(bonuses[t]) + self.gamma * running
            returns[t] = running
        return returns

    def update(self, bonuses: float | np.ndarray) -> None:
        """
        Append meta-step preference bonuses ``b_t``; fold in every rollout they complete.

        :param bonuses: one bonus or an array of them, in time order
        """
        values = np.asarray(bonuses, dtype=np.float64).ravel()
        if not np.all(np.isfinite(values)):
            raise ValueError("bonuses must be finite")
        self._pending.extend(values.tolist())
        while len(self._pending) >= self.rollout_length:
            rollout = np.asarray(self._pending[: self.rollout_length])
            del self._pending[: self.rollout_length]
            std = float(np.std(self.discounted_returns(rollout)))
            self.num_rollouts += 1
            self.mean_std += (std - self.mean_std) / self.num_rollouts

    @property
    def sigma(self) -> float:
        """``sigma(R_p)``: the running average of the rollouts' return stds; 1.0 while it is undefined or < epsilon."""
        if self.num_rollouts == 0 or self.mean_std < self.epsilon or not np.isfinite(self.mean_std):
            return 1.0
        return self.mean_std

    def state_dict(self) -> dict[str, Any]:
        """
        :return: the bonuses of the unfinished rollout, the running average and the number of rollouts
        """
        return {
            "gamma": self.gamma,
            "rollout_length": self.rollout_length,
            "epsilon": self.epsilon,
            "pending": list(self._pending),
            "mean_std": self.mean_std,
            "num_rollouts": self.num_rollouts,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """
        :param state: a state from :meth:`state_dict`
        """
        self.gamma = float(state["gamma"])
        self.rollout_length = int(state["rollout_length"])
        self.epsilon = float(state["epsilon"])
        self._pending = [float(b) for b in state["pending"]]
        self.mean_std = float(state["mean_std"])
        self.num_rollouts = int(state["num_rollouts"])
