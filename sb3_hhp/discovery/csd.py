"""Curiosity-driven sub-goal discovery (CSD, section 4.2.1, Algorithm 1 line 29).

After each episode the visited states are scored by their novelty progress rho(s) (eq. 8, from the
RND memory Omega). States in the lowest ``percentile`` percent of rho (where novelty fell the most:
the agent has been learning about them) that were visited at least ``min_visits`` times over all
training, whose similarity to every stored sub-goal is below ``similarity_threshold`` (b_similarity) and whose
key the goal space lets become a sub-goal (:meth:`~sb3_hhp.goals.base.GoalSpace.discoverable`: Fetch's places within
the task's region) become new sub-goals. ``strategy="random"`` is the paper's ablation (Table 1): a
random visited state passes the same visit and similarity gates. A state where the task was solved
(:data:`~sb3_hhp.goals.base.SUCCESS_KEY`) is always a candidate: the task's own goal needs no
curiosity to be worth pursuing. With ``before_success``, so is the state visited just before it (e.g. facing the
goal square): the last step of a solved task, which CSD may never rank among the lowest novelty progress while
successes are rare, and without which the learner of "task solved" must cross the whole last room on its own.

Which states the percentile is taken over (``percentile_of``): "visited" (default) ranks every state of the episode,
so a situation met for a few steps of a long episode (KeyCorridor's "carrying the key, facing the locked door") is
rarely among its lowest 5 %, behind the many steps of situations that are sub-goals already; "new" ranks only the
states that could become a new sub-goal (a key that is not a sub-goal's and has the visits), the lowest percentile
of the states the paper's check would let through.
"""

from collections import Counter
from collections.abc import Hashable, Sequence
from typing import Optional

import numpy as np

from sb3_hhp.goals.base import SUCCESS_KEY, GoalSpace


class SubgoalDiscovery:
    """Chooses which visited states become new sub-goals.

    :param goal_space: the domain's goal space (keys and similarity)
    :param strategy: "csd" (novelty progress) or "random" (the ablation)
    :param percentile: the lowest percentile of rho that qualifies (5 in the paper), in (0, 100]
    :param min_visits: how often a state's sub-goal key must have been visited over training
    :param similarity_threshold: b_similarity in [0, 1]: a candidate must be less similar than this to every sub-goal
    :param max_new: at most this many sub-goals per episode
    :param seed: seed of the random strategy and tie-breaking
    :param before_success: the state visited just before a success is a candidate too (CSD only; it passes the same
        visit and similarity gates)
    :param percentile_of: "visited" (every state of the episode) or "new" (the states whose key is not a sub-goal's
        and has ``min_visits``): the states whose novelty progress the percentile ranks (CSD only)
    """

    before_success = False  # what a discovery pickled before the option reads
    percentile_of = "visited"  # likewise: discoveries pickled before it ranked every visited state

    def __init__(
        self,
        goal_space: GoalSpace,
        strategy: str = "csd",
        percentile: float = 5.0,
        min_visits: int = 2,
        similarity_threshold: float = 0.5,
        max_new: int = 1,
        seed: Optional[int] = None,
        before_success: bool = False,
        percentile_of: str = "visited",
    ) -> None:
        if strategy not in ("csd", "random"):
            raise ValueError(f"discovery strategy must be 'csd' or 'random', got {strategy!r}")
        if not 0 < percentile <= 100:
            raise ValueError(f"percentile must be in (0, 100], got {percentile}")
        if min_visits < 1:
            raise ValueError(f"min_visits must be >= 1, got {min_visits}")
        if not 0 <= similarity_threshold <= 1:
            raise ValueError(f"similarity_threshold (b_similarity) must be in [0, 1], got {similarity_threshold}")
        if percentile_of not in ("visited", "new"):
            raise ValueError(f"percentile_of must be 'visited' or 'new', got {percentile_of!r}")
        if max_new < 1:
            raise ValueError(f"max_new must be >= 1, got {max_new}")
        self.goal_space = goal_space
        self.strategy = strategy
        self.percentile = percentile
        self.min_visits = min_visits
        self.similarity_threshold = similarity_threshold
        self.max_new = max_new
        self.before_success = bool(before_success)
        self.percentile_of = percentile_of
        self.rng = np.random.default_rng(seed)

    def select(
        self,
        states: np.ndarray,
        keys: Sequence[Hashable],
        rho: Optional[np.ndarray],
        visits: Counter,
        goal_keys: Sequence[Hashable],
        goal_obs: np.ndarray,
    ) -> list[int]:
        """Indices of ``states`` to add as sub-goals (at most ``max_new``, lowest rho first).

        :param states: the episode's visited states ``(N, *obs_shape)``
        :param keys: their sub-goal keys
        :param rho: their novelty progress (eq. 8), required for "csd"
        :param visits: visit counts of every key over training
        :param goal_keys: keys of the current sub-goals
        :param goal_obs: observations of the current sub-goals
        """
        n = len(keys)
        if n == 0:
            return []
        if self.strategy == "csd":
            if rho is None or len(rho) != n:
                raise ValueError("CSD needs one novelty-progress value per visited state")
            # lowest `percentile` percent of rho; random tie-breaking so equal scores are not taken in visit order
            order = np.lexsort((self.rng.random(n), rho))
            ranked = order
            if self.percentile_of == "new":  # only the states that could become a new sub-goal
                existing = set(goal_keys)
                ranked = np.array([index for index in order
                                   if keys[index] not in existing and visits[keys[index]] >= self.min_visits
                                   and self.goal_space.discoverable(keys[index])],
                                  dtype=np.int64)
            n_candidates = max(1, int(np.ceil(len(ranked) * self.percentile / 100.0)))
            candidates = ranked[:n_candidates]
            # the task solved is the one situation that needs no curiosity to be worth a sub-goal
            solved = [index for index in order if keys[index] == SUCCESS_KEY][:1]
            if self.before_success and solved and solved[0] > 0:
                solved.append(solved[0] - 1)  # and, optionally, the state from which it was solved
            solved = [index for index in solved if index not in candidates]
            candidates = np.concatenate([solved, candidates]).astype(np.int64)
        else:
            candidates = self.rng.permutation(n)
        chosen: list[int] = []
        chosen_keys = list(goal_keys)
        chosen_obs = list(goal_obs)
        for index in candidates:
            key = keys[index]
            if visits[key] < self.min_visits or not self.goal_space.discoverable(key):
                continue
            if chosen_keys:
                similarity = self.goal_space.similarity(key, states[index], chosen_keys, np.stack(chosen_obs))
                if np.max(similarity) >= self.similarity_threshold:
                    continue
            chosen.append(int(index))
            chosen_keys.append(key)
            chosen_obs.append(states[index])
            if len(chosen) >= self.max_new:
                break
        return chosen
