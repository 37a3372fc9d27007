"""
The subpolicies' rewards (section 4.2): the pseudo-reward of reaching a sub-goal (eq. 5) and the full
reward with curiosity (eq. 6).

The meta-controller's reward (eq. 3) lives with the preferences, in :mod:`sb3_hhp.preferences.rewards`.
"""

import numpy as np
import torch as th

__all__ = ["pseudo_reward", "subpolicy_reward"]


def _check_alpha(alpha: float) -> None:
    if not alpha >= 0.0:
        raise ValueError(f"alpha must be >= 0, got {alpha}")


def _as_output(value: np.ndarray) -> float | np.ndarray:
    return float(value) if value.ndim == 0 else value


def pseudo_reward(done: bool | np.ndarray, terminal: bool | np.ndarray) -> float | np.ndarray:
    """
    Pseudo-reward of a subpolicy pursuing sub-goal ``g`` (eq. 5): +1 if ``done(s, g)`` (the sub-goal is
    reached), -1 if ``terminal(s, g)`` without ``done(s, g)``, 0 otherwise.

    :param done: ``done(s, g)``, a bool or a boolean array
    :param terminal: ``terminal(s, g)``, same shape
    :return: a float for scalar inputs, else a float32 array
    """
    done_arr = np.asarray(done, dtype=bool)
    terminal_arr = np.asarray(terminal, dtype=bool)
    reward = np.where(done_arr, 1.0, np.where(terminal_arr, -1.0, 0.0)).astype(np.float32)  # eq. 5
    return _as_output(reward)


def subpolicy_reward(
    pseudo: float | np.ndarray | th.Tensor,
    intrinsic: float | np.ndarray | th.Tensor,
    alpha: float = 0.5,
) -> float | np.ndarray | th.Tensor:
    """
    Reward of a subpolicy at every primitive step (eq. 6): ``r_t = r^{e,g}_t + alpha * r^i_t``.

    :param pseudo: ``r^{e,g}``, the pseudo-reward of eq. 5
    :param intrinsic: ``r^i``, the curiosity reward of eq. 7
    :param alpha: weight of curiosity, >= 0 (paper: 0.5)
    :return: a float for scalar inputs, else an array (a tensor if either input is one)
    """
    _check_alpha(alpha)
    if isinstance(pseudo, th.Tensor) or isinstance(intrinsic, th.Tensor):
        return pseudo + alpha * intrinsic  # eq. 6
    return _as_output(np.asarray(pseudo, dtype=np.float64) + alpha * np.asarray(intrinsic, dtype=np.float64))  # eq. 6
