"""Query selection (section 4.1.3, Algorithm 1 line 26): which of an episode's (s, g) tuples to ask about.

After an episode, the predictor's confidence ``c(s, g)`` (eq. 4; higher = less sure) is known for
every (state, chosen sub-goal) tuple. A tuple is asked about when ``c > t_qry``; the second
sub-goal ``g2`` shown next to ``g`` is the meta-controller's second choice. A query budget caps
the total number of questions over the whole training run.

Three modes:

* ``"fixed"``: the paper's rule, a constant threshold ``t_qry`` (0.26 MiniGrid, 0.42 Atari/MuJoCo).
* ``"adaptive"`` (design decisions: adaptive threshold; the paper's future work): the budget is paced over training.
  At ``num_timesteps`` out of ``total_timesteps`` the allowance is
  ``A = floor(budget * min(1, num_timesteps / total_timesteps))`` and the quota of this call is
  ``k = A - used``. The confidences of askable tuples are pooled in a window of the last
  ``quantile_window`` values (this episode's included), taken at the calls that may ask (``k > 0``): where
  ``k = 0`` nothing can be asked, and :meth:`QuerySelector.idle` lets the caller skip the confidences
  (eq. 4's dropout masks, the costly part of a question). With ``n`` askable tuples in this episode,
  the threshold is the ``1 - min(1, k / n)`` quantile of the window: if recent confidences are
  representative, about ``k`` of this episode's tuples lie above it, so the expected number of
  questions matches the quota. Tuples with ``c >= threshold`` are asked, at most ``k`` of them (the
  least confident first). A shortfall stays in the quota and lowers the next threshold, so the
  questions keep up with the allowance (the lag is a few questions); ``used`` never exceeds it.
  With ``k = 0`` nothing is asked (threshold ``+inf``). The last call (fewer steps left before
  ``total_timesteps`` than the mean number of steps between calls, so no later episode is likely
  to end in time) spends what is left of the quota on that episode's ``k`` least confident tuples,
  so the whole budget is used by the end of training. The window quantile lags behind confidences
  that drift (a predictor grows surer as it learns): keep ``quantile_window`` to a small part of
  all the tuples a run sees.
* ``"paced"``: both rules at once, asking only when unsure and within the paced budget: the adaptive
  mode's threshold, never below ``t_qry`` (the last call too). A tuple is asked about only where
  ``c > t_qry``, at most the adaptive quota of them, so a predictor that has grown sure stops asking
  and the budget need not be spent.
"""

import math
from collections import deque
from typing import Any, Optional

import numpy as np

MODES = ("fixed", "adaptive", "paced")
#: how the second sub-goal of a question is chosen (:class:`QuerySelector`'s ``second``)
SECONDS = ("meta", "unasked")
#: what the confidence of a tuple measures (:class:`QuerySelector`'s ``reading``)
READINGS = ("score", "pair")


class QuerySelector:
    """Picks the tuples to ask about after an episode, within a total query budget.

    :param budget: most questions over the whole training run (>= 0; paper: 50-200 MiniGrid,
        750 MuJoCo, 3000 Atari)
    :param threshold: ``t_qry``: ask when the confidence exceeds it (>= 0; paper: 0.26 MiniGrid,
        0.42 Atari and MuJoCo). Used by the "fixed" mode and as the "paced" mode's floor; the "adaptive"
        mode starts from it (``current_threshold`` before any data) and then sets its own
    :param mode: "fixed" (the paper's constant threshold), "adaptive" (budget paced over
        training, threshold from a running quantile) or "paced" (the adaptive threshold, never below
        ``threshold``); see the module docstring
    :param total_timesteps: length of training in primitive steps (> 0), needed by the adaptive
        mode; ``HhP.learn`` sets it through :meth:`set_total_timesteps`
    :param quantile_window: number of recent confidences the adaptive quantile is taken over (>= 1)
    :param second: how ``g2`` is chosen: "meta" (the paper: the meta-controller's second choice) or "unasked" (the
        meta-controller's best choosable sub-goal that no question has named yet, where the state has one; else its
        second choice). A predictor extrapolates its scores to sub-goals no label names, and a sub-goal it scores low
        is seldom the meta-controller's first or second choice, so "meta" may never ask about it
    :param reading: what the confidences handed to :meth:`select` measure, for the caller to compute: "score" (the
        paper's eq. 4: the spread of the predictor's score ``p_hat(s, g)`` over dropout masks) or "pair" (the spread
        of the answer to the question itself, "g over g2" with ``P[g > g2]`` of eq. 2 averaged over the masks and
        ``g2`` from :meth:`seconds`: :meth:`~sb3_hhp.preferences.predictor.PreferencePredictor.confidence` with
        ``seconds``). A score's spread grows with the scores' scale as the predictor trains; the answer's lies in
        [0, 0.5], is largest before the predictor can tell the two apart and falls as it orders them surely, so that
        ``t_qry`` keeps one meaning over a run (design decisions: Fetch asks where the answer to the question is unsure)
    """

    def __init__(
        self,
        budget: int,
        threshold: float = 0.26,
        mode: str = "fixed",
        total_timesteps: Optional[int] = None,
        quantile_window: int = 2_000,
        second: str = "meta",
        reading: str = "score",
    ) -> None:
        if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)) or budget < 0:
            raise ValueError(f"query_budget must be an integer >= 0, got {budget!r}")
        if not (isinstance(threshold, (int, float, np.number)) and threshold >= 0):
            raise ValueError(f"threshold (t_qry) must be >= 0, got {threshold!r}")
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        if second not in SECONDS:
            raise ValueError(f"second must be one of {SECONDS}, got {second!r}")
        if reading not in READINGS:
            raise ValueError(f"reading must be one of {READINGS}, got {reading!r}")
        if isinstance(quantile_window, bool) or not isinstance(quantile_window, (int, np.integer)) or quantile_window < 1:
            raise ValueError(f"quantile_window must be an integer >= 1, got {quantile_window!r}")
        self._budget = int(budget)
        self.threshold = float(threshold)
        self.mode = mode
        self.second = second
        self.reading = reading
        self.quantile_window = int(quantile_window)
        self.total_timesteps: Optional[int] = None
        if total_timesteps is not None:
            self.set_total_timesteps(total_timesteps)
        self._used = 0
        self._window: deque[float] = deque(maxlen=self.quantile_window)
        self._n_calls = 0  # adaptive select() calls, to estimate the steps between calls
        self.current_threshold = self.threshold

    @property
    def budget(self) -> int:
        """Most questions over the whole run."""
        return self._budget

    @property
    def used(self) -> int:
        """Questions selected so far."""
        return self._used

    @property
    def remaining(self) -> int:
        """Questions left in the budget."""
        return self._budget - self._used

    def set_total_timesteps(self, total_timesteps: int) -> None:
        """Set the training length (primitive steps) that the adaptive mode paces the budget over.

        :param total_timesteps: > 0
        """
        if isinstance(total_timesteps, bool) or not isinstance(total_timesteps, (int, np.integer)) or total_timesteps < 1:
            raise ValueError(f"total_timesteps must be an integer > 0, got {total_timesteps!r}")
        self.total_timesteps = int(total_timesteps)

    def allowance(self, num_timesteps: int) -> int:
        """Questions the adaptive mode may have asked by ``num_timesteps``: floor(budget * progress)."""
        if self.total_timesteps is None:
            raise ValueError(
                "mode='adaptive' needs total_timesteps: pass it to QuerySelector or call set_total_timesteps()"
            )
        progress = min(1.0, num_timesteps / self.total_timesteps)
        return min(self._budget, math.floor(self._budget * progress + 1e-9))

    def idle(self, num_timesteps: int) -> bool:
        """Whether a call at ``num_timesteps`` can ask nothing (the adaptive and paced modes with a quota of 0): the
        call is then counted as :meth:`select` counts it (the steps between calls) and the caller need not compute
        the episode's confidences; False in the fixed mode and wherever a question may be asked."""
        if self.mode == "fixed":
            return False
        if self.allowance(num_timesteps) - self._used > 0:
            return False
        self._n_calls += 1
        self.current_threshold = math.inf
        return True

    def select(
        self,
        confidences: np.ndarray,
        goals: np.ndarray,
        q_values: np.ndarray,
        num_timesteps: int = 0,
        exclude: Optional[np.ndarray] = None,
        unasked: Optional[np.ndarray] = None,
    ) -> list[tuple[int, int]]:
        """Choose which of an episode's (s, g) tuples to ask about (Algorithm 1, line 26).

        :param confidences: ``c(s, g)`` per tuple (N,), higher = less sure (eq. 4)
        :param goals: the sub-goal ``g`` chosen in each tuple (N,), ids in [0, G)
        :param q_values: the meta-controller's Q-values over sub-goals per tuple (N, G); invalid
            sub-goals as ``-inf`` (NaN is treated the same way)
        :param num_timesteps: primitive steps done so far (>= 0; used by the adaptive mode)
        :param exclude: optional boolean (N, G): pairs (tuple, g2) never to ask (already asked); ``g2`` is then the
            best sub-goal not excluded, and a tuple with none left is not askable
        :param unasked: optional boolean (G,): the sub-goals no question has named yet; with ``second="unasked"``,
            ``g2`` is the best of them by Q-value where a tuple has one (not excluded, valid, other than ``g``)
        :return: ``[(tuple_index, g2), ...]`` in tuple order, ``g2`` the best sub-goal other than
            ``g`` by Q-value; tuples without any other valid sub-goal are never asked. At most
            ``remaining`` entries (``used`` grows by their number).
        """
        confidences = np.asarray(confidences, dtype=np.float64)
        goals = np.asarray(goals)
        q_values = np.asarray(q_values, dtype=np.float64)
        if confidences.ndim != 1:
            raise ValueError(f"confidences must have shape (N,), got {confidences.shape}")
        n = confidences.shape[0]
        if goals.shape != (n,):
            raise ValueError(f"goals must have shape ({n},) like confidences, got {goals.shape}")
        if q_values.ndim != 2 or q_values.shape[0] != n:
            raise ValueError(f"q_values must have shape ({n}, G), got {q_values.shape}")
        if n and not np.issubdtype(goals.dtype, np.integer):
            raise ValueError(f"goals must hold integer sub-goal ids, got dtype {goals.dtype}")
        n_goals = q_values.shape[1]
        if n and (goals.min() < 0 or goals.max() >= n_goals):
            raise ValueError(f"goals must be sub-goal ids in [0, {n_goals}), got {goals.min()}..{goals.max()}")
        if np.isnan(confidences).any():
            raise ValueError("confidences contain NaN")
        if num_timesteps < 0:
            raise ValueError(f"num_timesteps must be >= 0, got {num_timesteps}")
        if self.mode != "fixed" and self.total_timesteps is None:
            self.allowance(num_timesteps)  # raises with the fix
        if n == 0:
            return []

        second, askable = self._seconds(goals, q_values, exclude, unasked)
        c = confidences[askable]

        if self.mode == "fixed":
            quota = max(0, self.remaining)
            chosen = askable[c > self.threshold]  # line 26: c(s, g) > t_qry
        else:
            self._window.extend(c.tolist())
            self._n_calls += 1
            quota = max(0, self.allowance(num_timesteps) - self._used)
            steps_per_call = num_timesteps / self._n_calls
            last_call = self.total_timesteps - num_timesteps < steps_per_call
            if quota == 0 or len(askable) == 0:
                self.current_threshold = math.inf
                chosen = askable[:0]
            else:
                if last_call:  # no later call expected: spend the quota on this episode's least confident tuples
                    self.current_threshold = float(np.sort(c)[::-1][min(quota, len(c)) - 1])
                else:
                    fraction = min(1.0, quota / len(askable))
                    self.current_threshold = float(np.quantile(np.fromiter(self._window, float), 1.0 - fraction))
                asked = c >= self.current_threshold
                if self.mode == "paced":  # and only where unsure: c(s, g) > t_qry
                    self.current_threshold = max(self.current_threshold, self.threshold)
                    asked &= c > self.threshold
                chosen = askable[asked]
        if len(chosen) > quota:  # keep the least confident (highest c); ties go to the earlier tuple
            order = np.argsort(-confidences[chosen], kind="stable")
            chosen = np.sort(chosen[order[:quota]])
        self._used += len(chosen)
        return [(int(i), int(second[i])) for i in chosen]

    def seconds(self, goals: np.ndarray, q_values: np.ndarray, exclude: Optional[np.ndarray] = None,
                unasked: Optional[np.ndarray] = None) -> np.ndarray:
        """The sub-goal ``g2`` that :meth:`select` would compare each tuple's ``g`` with (its arguments as there),
        -1 where a tuple has no other sub-goal to compare: with ``reading="pair"`` the caller measures the spread of
        the question's answer before selecting."""
        goals, q_values = np.asarray(goals), np.asarray(q_values, dtype=np.float64)
        if q_values.ndim != 2 or goals.shape != (q_values.shape[0],):
            raise ValueError(f"goals (N,) and q_values (N, G) must agree, got {goals.shape} and {q_values.shape}")
        second, askable = self._seconds(goals, q_values, exclude, unasked)
        result = np.full(len(goals), -1, dtype=np.int64)
        result[askable] = second[askable]
        return result

    def _seconds(self, goals: np.ndarray, q_values: np.ndarray, exclude: Optional[np.ndarray],
                 unasked: Optional[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """``g2`` of every tuple and the indices of the tuples that have one (:meth:`select`)."""
        n, n_goals = q_values.shape
        # g2: the meta-controller's second choice, the highest-Q sub-goal other than g
        others = np.where(np.isnan(q_values), -np.inf, q_values)
        others[np.arange(n), goals] = -np.inf
        if exclude is not None:
            exclude = np.asarray(exclude, dtype=bool)
            if exclude.shape != q_values.shape:
                raise ValueError(f"exclude must have the shape of q_values {q_values.shape}, got {exclude.shape}")
            others[exclude] = -np.inf
        second = others.argmax(axis=1)
        if self.second == "unasked" and unasked is not None:
            unasked = np.asarray(unasked, dtype=bool)
            if unasked.shape != (n_goals,):
                raise ValueError(f"unasked must have shape ({n_goals},), one flag a sub-goal, got {unasked.shape}")
            new = np.where(unasked[None, :], others, -np.inf)
            has_new = new.max(axis=1) > -np.inf
            second = np.where(has_new, new.argmax(axis=1), second)
        return second, np.flatnonzero(others[np.arange(n), second] > -np.inf)

    def refund(self, n: int) -> None:
        """Give back ``n`` questions that :meth:`select` counted but that were not asked."""
        if not 0 <= n <= self._used:
            raise ValueError(f"refund must be in [0, used={self._used}], got {n}")
        self._used -= int(n)

    def state_dict(self) -> dict[str, Any]:
        """The selector's progress: questions used, the adaptive window and threshold, the training length."""
        return {
            "used": self._used,
            "window": list(self._window),
            "n_calls": self._n_calls,
            "current_threshold": self.current_threshold,
            "total_timesteps": self.total_timesteps,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` saved (budget, threshold and mode stay as constructed)."""
        used = int(state["used"])
        if used < 0:
            raise ValueError(f"used must be >= 0, got {used}")
        self._used = used
        self._window = deque((float(c) for c in state["window"]), maxlen=self.quantile_window)
        self._n_calls = int(state.get("n_calls", 0))
        self.current_threshold = float(state["current_threshold"])
        if state.get("total_timesteps") is not None:
            self.set_total_timesteps(int(state["total_timesteps"]))
