"""CSD's choice of new sub-goals (section 4.2.1, Algorithm 1 line 29): the lowest novelty progress, the visit and
similarity gates, and the states of a solved task (sb3_hhp.discovery.csd)."""

from collections import Counter

import numpy as np
import pytest

from sb3_hhp.discovery.csd import SubgoalDiscovery
from sb3_hhp.goals.base import SUCCESS_KEY, GoalSpace

class KeyedSpace(GoalSpace):
    """A goal space whose states are their own keys (the default similarity: equal keys -> 1)."""

    name = "keyed"

    @classmethod
    def supports(cls, env) -> bool:
        return False

    def key(self, obs):
        return obs


KEYS = ["a", "b", "c", "d", "e", "f", "g", "h", "i", "j"]


def _select(discovery: SubgoalDiscovery, keys: list, rho: np.ndarray, visits: Counter, goal_keys: list = ()) -> list:
    states = np.arange(len(keys), dtype=np.float32)[:, None]
    goal_obs = np.zeros((len(goal_keys), 1), dtype=np.float32)
    return discovery.select(states, keys, rho, visits, list(goal_keys), goal_obs)


def test_csd_takes_the_lowest_novelty_progress_that_passes_the_gates() -> None:
    """percentile 20 of 10 states: the two lowest rho are the candidates; the lowest is taken unless a gate stops it."""
    discovery = SubgoalDiscovery(KeyedSpace(), percentile=20, min_visits=2, max_new=2, seed=0)
    rho = np.array([0.5, -0.9, 0.1, -0.3, 0.2, 0.3, 0.4, 0.6, 0.7, -0.8])  # lowest: b (-0.9), then j (-0.8)
    visits = Counter({key: 5 for key in KEYS})
    assert _select(discovery, KEYS, rho, visits) == [1, 9]
    assert _select(discovery, KEYS, rho, Counter({**visits, "b": 1})) == [9]  # b visited once: below min_visits
    assert _select(discovery, KEYS, rho, visits, goal_keys=["j"]) == [1]  # j is a sub-goal already (similarity 1)
    assert _select(SubgoalDiscovery(KeyedSpace(), percentile=20, max_new=1, seed=0), KEYS, rho, visits) == [1]
    # the third lowest (d, -0.3) is outside the 20th percentile: never a candidate
    assert _select(discovery, KEYS, rho, visits, goal_keys=["b", "j"]) == []


def test_a_solved_task_and_optionally_the_state_before_it_are_always_candidates() -> None:
    """The success state is a candidate whatever its rho; with ``before_success``, so is the state visited just
    before it (here "h", whose rho is high), through the same gates."""
    keys = KEYS[:8] + ["h2", SUCCESS_KEY]
    rho = np.array([0.5, -0.9, 0.1, -0.3, 0.2, 0.3, 0.4, 0.6, 0.7, 0.8])
    visits = Counter({key: 5 for key in keys})
    plain = SubgoalDiscovery(KeyedSpace(), percentile=10, max_new=3, seed=0)
    assert _select(plain, keys, rho, visits) == [9, 1]  # success first, then the lowest rho
    before = SubgoalDiscovery(KeyedSpace(), percentile=10, max_new=3, seed=0, before_success=True)
    assert _select(before, keys, rho, visits) == [9, 8, 1]
    assert _select(before, keys, rho, visits, goal_keys=[SUCCESS_KEY, "h2"]) == [1]
    assert _select(before, keys, rho, Counter({**visits, "h2": 1})) == [9, 1]  # the visit gate holds for it too
    # an episode solved at its first recorded state has no state before it in the trace
    assert _select(before, [SUCCESS_KEY, "a"], np.array([0.9, 0.1]), visits) == [0, 1]


def test_the_percentile_of_new_states_ranks_only_what_could_become_a_sub_goal() -> None:
    """A long episode spent mostly in sub-goals' situations ("a", "b"): with percentile 10 of all 20 states the two
    candidates are "a" states and nothing is added; ranked among the states that could become a new sub-goal ("n" and
    "m" are not sub-goals; "m" was visited once), the lowest of those ("n", rho 0.2, 8th lowest of the 20) is added."""
    keys = ["a"] * 10 + ["b"] * 6 + ["n", "n", "m", "n"]
    rho = np.array([-0.9, -0.8, -0.7, -0.6, -0.5, -0.4, -0.3, -0.2, -0.1, 0.0,
                    0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 0.3, 0.2, -0.95, 0.4])
    visits = Counter({"a": 50, "b": 50, "n": 3, "m": 1})
    plain = SubgoalDiscovery(KeyedSpace(), percentile=10, seed=0)
    assert _select(plain, keys, rho, visits, goal_keys=["a", "b"]) == []
    new = SubgoalDiscovery(KeyedSpace(), percentile=10, seed=0, percentile_of="new")
    assert _select(new, keys, rho, visits, goal_keys=["a", "b"]) == [17]
    # the percentile is of the new states' count: 3 "n" states, percentile 50 -> the two lowest of them, max_new 2
    two = SubgoalDiscovery(KeyedSpace(), percentile=50, max_new=2, seed=0, percentile_of="new")
    assert _select(two, keys, rho, visits, goal_keys=["a", "b"]) == [17]  # the second candidate has the same key
    assert _select(two, keys, rho, Counter({**visits, "m": 2}), goal_keys=["a", "b"]) == [18, 17]
    # nothing new in the episode: nothing added
    assert _select(new, keys, rho, visits, goal_keys=["a", "b", "n"]) == []


def test_random_discovery_passes_the_same_gates() -> None:
    discovery = SubgoalDiscovery(KeyedSpace(), strategy="random", max_new=10, seed=0)
    visits = Counter({key: 5 for key in KEYS})
    chosen = _select(discovery, KEYS, None, Counter({**visits, "c": 1}), goal_keys=["a"])
    assert sorted(KEYS[index] for index in chosen) == [key for key in KEYS if key not in ("a", "c")]


class RegionSpace(KeyedSpace):
    """Keys "a" to "e" may become sub-goals, the others lie outside the task's region."""

    def discoverable(self, key) -> bool:
        return key == SUCCESS_KEY or key in "abcde"


def test_only_keys_the_goal_space_lets_in_become_sub_goals() -> None:
    """The lowest rho ("j", then "b") and the 20 % of the new states: "j" is outside, so "b" is taken; under "new" the
    percentile ranks the keys that may become sub-goals only; the random strategy and the task solved likewise."""
    rho = np.array([0.5, -0.8, 0.1, -0.3, 0.2, 0.3, 0.4, 0.6, 0.7, -0.9])
    visits = Counter({key: 5 for key in KEYS})
    assert _select(SubgoalDiscovery(KeyedSpace(), percentile=20, seed=0), KEYS, rho, visits) == [9]
    assert _select(SubgoalDiscovery(RegionSpace(), percentile=20, seed=0), KEYS, rho, visits) == [1]
    # of the 5 keys let in, percentile 20 ranks one: "b" (-0.8); "d" (-0.3) comes second
    new = SubgoalDiscovery(RegionSpace(), percentile=20, seed=0, percentile_of="new")
    assert _select(new, KEYS, rho, visits) == [1]
    assert _select(new, KEYS, rho, visits, goal_keys=["b"]) == [3]
    random = SubgoalDiscovery(RegionSpace(), strategy="random", max_new=10, seed=0)
    assert sorted(KEYS[index] for index in _select(random, KEYS, None, visits)) == list("abcde")
    solved = ["f", "g", SUCCESS_KEY]
    assert _select(SubgoalDiscovery(RegionSpace(), percentile=10, seed=0), solved, np.array([-0.5, 0.1, 0.9]),
                   Counter({**visits, SUCCESS_KEY: 5})) == [2]


@pytest.mark.parametrize("kwargs", [dict(strategy="novelty"), dict(percentile=0), dict(min_visits=0),
                                    dict(similarity_threshold=1.5), dict(max_new=0),
                                    dict(percentile_of="all")])
def test_bad_settings_are_refused(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        SubgoalDiscovery(KeyedSpace(), **kwargs)
