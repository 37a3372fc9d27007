"""The meta-controller's reward (eq. 3): the preference bonus b = p_hat(s, g) of its choices.

``r = beta * R_e + (1 - beta) * b / sigma(R_p)`` (:func:`~sb3_hhp.preferences.rewards.meta_reward`), with the bonus
recomputed by the current predictor for every sampled choice of R_H (cached per row while the predictor and the
sub-goal set stay the same), optionally centred over the sub-goals of each state, and, with ``exact_bonus``, added
to the meta-controller's Q-values instead of being learnt.
"""

from typing import Any, Optional

import numpy as np
import torch as th

from sb3_hhp.goals import SUCCESS_KEY
from sb3_hhp.preferences.rewards import meta_reward


class PreferenceBonus:
    """The preference bonus of :class:`~sb3_hhp.hhp.hhp.HhP`'s choices (a mixin: it reads the model's predictor, sub-goals
    and meta replay)."""

    def predictor_inputs(self, observations: np.ndarray) -> np.ndarray:
        """What the predictor reads for a batch of observations: the goal space's features, or the
        observations themselves (``predictor_input``)."""
        observations = self._env_layout(np.asarray(observations))
        return self.goal_space.features(observations) if self._predictor_reads_features else observations

    def query_inputs(self, query: Any) -> np.ndarray:
        """What the predictor reads of a question: its state and its two sub-goals, stacked."""
        return self.predictor_inputs(np.stack([query.state, query.goal1_obs, query.goal2_obs]))

    def add_preference(self, query: Any, label: Any) -> bool:
        """Feed one answered query to the predictor's buffer R (False: the label teaches nothing, e.g.
        "incomparable")."""
        state, goal1, goal2 = self.query_inputs(query)
        return self.predictor.add(state, goal1, goal2, label)

    @property
    def goal_obs(self) -> np.ndarray:
        return np.stack([goal.obs for goal in self.subgoals])

    def _rewards(self, replay_data: Any) -> th.Tensor:
        """r^e = beta * R_e + (1 - beta) * b / sigma(R_p) (eq. 3, Algorithm 1 lines 32-33), with the bonus
        b = p_hat(s, g) recomputed by the current predictor for the sampled choices."""
        extrinsic = replay_data.rewards
        if len(self.predictor) == 0:
            return extrinsic
        goals = replay_data.actions.long().flatten().cpu().numpy()
        states = replay_data.observations.cpu().numpy().astype(self.primitive_observation_space.dtype)
        bonus = self._replay_bonus(np.asarray(replay_data.indices) // self.replay_buffer.n_envs, states, goals)
        bonus_t = th.as_tensor(bonus, dtype=extrinsic.dtype, device=extrinsic.device).reshape(-1, 1)
        return meta_reward(extrinsic, bonus_t, sigma=self.return_normalizer.sigma, beta=self.beta)

    def _replay_bonus(self, rows: np.ndarray, states: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """:meth:`preference_bonus` of sampled rows of R_H, scored once per row while the predictor and the sub-goal
        set (and the centring) stay the same (a row's bonus depends on nothing else): late in a run, when the budget is spent, the
        meta-controller's updates stop re-scoring the same choices."""
        key = (self.predictor.version, len(self.subgoals), self.center_bonus, self.success_bonus, self.mask_subgoals, id(self.replay_buffer),
               self.replay_buffer.buffer_size)
        if getattr(self, "_bonus_key", None) != key:
            self._bonus_key = key
            self._bonus_cache = np.zeros(self.replay_buffer.buffer_size, dtype=np.float32)
            self._bonus_valid = np.zeros(self.replay_buffer.buffer_size, dtype=bool)
        stale = ~self._bonus_valid[rows]
        if stale.any():
            self._bonus_cache[rows[stale]] = self.preference_bonus(states[stale], goals[stale])
            self._bonus_valid[rows[stale]] = True
        return self._bonus_cache[rows]

    def preference_bonus(self, states: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """The preference bonus b = p_hat(s, g) (Algorithm 1 line 12), centred over the sub-goals when
        ``center_bonus``: b(s, g) - mean_g' p_hat(s, g') (True or "mean"), or b(s, g) - max_g' p_hat(s, g') over
        the sub-goals choosable in s and g ("max": never positive). Bradley-Terry (eq. 2) fixes scores only up to a
        per-state constant, so the uncentred level is arbitrary shaping that can pay for dawdling. With
        ``success_bonus="best"`` the task's own goal scores as the best of the other sub-goals choosable in s."""
        if not self.center_bonus and self.success_bonus != "best":
            return self.predictor.score(self.predictor_inputs(states), self.predictor_inputs(self.goal_obs)[goals])
        return self.bonus_matrix(states)[np.arange(len(states)), goals]

    def bonus_matrix(self, states: np.ndarray) -> np.ndarray:
        """:meth:`preference_bonus` of every sub-goal in each state, ``(N, n_sub-goals)``; under "max" centring a
        sub-goal not choosable in s and scored above every choosable one gets 0, as it would if chosen."""
        success = self.success_goal if self.success_bonus == "best" else None
        mask = self.action_mask(states) if self.center_bonus == "max" or success is not None else None
        goal_obs, inputs = self.predictor_inputs(self.goal_obs), self.predictor_inputs(states)
        n_goals, n_states = len(goal_obs), len(inputs)
        scores = self.predictor.score_matrix(inputs, goal_obs)  # (n_states, n_goals)
        choosable = (np.ones_like(scores, dtype=bool) if mask is None
                     else np.broadcast_to(mask, (n_states, mask.shape[-1]))[:, :n_goals])
        if success is not None:  # the best other choosable score (the success's own where it is the only choice)
            others = choosable & (np.arange(n_goals) != success)
            best_other = np.where(others, scores, -np.inf).max(axis=1)
            scores[:, success] = np.where(np.isfinite(best_other), best_other, scores[:, success])
        if not self.center_bonus:
            return scores
        if self.center_bonus == "max":
            best = np.where(choosable, scores, -np.inf).max(axis=1, keepdims=True)
            return np.minimum(scores - np.where(np.isfinite(best), best, scores), 0.0)
        return scores - scores.mean(axis=1, keepdims=True)

    def _q_offset(self, observations: th.Tensor) -> Optional[th.Tensor]:
        """With ``exact_bonus``: eq. 3's bonus term ``(1 - beta) * b(s, g) / sigma`` of every sub-goal, the part of the
        meta-controller's Q-values that the predictor computes (0 for the head's unused rows); else None."""
        if not self.exact_bonus or len(self.predictor) == 0 or not self.subgoals:
            return None
        states = observations.cpu().numpy().astype(self.primitive_observation_space.dtype)
        bonus = np.zeros((len(states), int(self.action_space.n)), dtype=np.float32)
        bonus[:, : len(self.subgoals)] = self.bonus_matrix(states)
        bonus_t = th.as_tensor(bonus, device=observations.device)
        return meta_reward(th.zeros_like(bonus_t), bonus_t, sigma=self.return_normalizer.sigma, beta=self.beta)

    @property
    def success_goal(self) -> Optional[int]:
        """The index of the task's own goal among the sub-goals (:data:`~sb3_hhp.goals.base.SUCCESS_KEY`), None before
        it is found."""
        keys = self.subgoal_set.keys
        return keys.index(SUCCESS_KEY) if SUCCESS_KEY in keys else None

