"""The sub-goal learners' keyword arguments: the paper's (section 5.1), the default, and their checks.

``HhP(subpolicy_kwargs=...)`` and ``subgoal_learner_kwargs`` (``sb3_hhp/hyperparams/hhp.yml``) reach the learners of
:mod:`sb3_hhp.hierarchy.learners` and :mod:`sb3_hhp.hierarchy.heads` through these: merged over the defaults and
checked once, with errors that say what to give instead, before any network is built.
"""

from typing import Any, Optional, Sequence

import numpy as np

#: subpolicy keyword arguments the stacked learner reads (SB3 DQN's names), and those it accepts and ignores
USED = {
    "learning_rate", "buffer_size", "learning_starts", "batch_size", "gamma", "train_freq", "gradient_steps", "policy_kwargs",
    "target_update_interval", "exploration_initial_eps", "exploration_final_eps", "n_steps", "replay_buffer_kwargs",
    "max_grad_norm", "double_q", "prioritized_replay_alpha", "prioritized_replay_beta", "prioritized_replay_eps",
}
IGNORED = {"exploration_fraction", "optimize_memory_usage", "tau", "prioritized_replay"}


#: the paper's sub-goal learner (section 5.1): Adam lr 1e-3, batch 128, 256x256 units, an update every step,
#: replay of 50K, one-step targets; a target network every 250 of a sub-goal's learning ticks (2,000 in the paper:
#: a sub-goal lives a few thousand steps). ``HhP(..., subpolicy_kwargs=PAPER_SUBPOLICY_KWARGS)`` selects it.
PAPER_SUBPOLICY_KWARGS: dict[str, Any] = dict(
    learning_rate=1e-3, buffer_size=50_000, learning_starts=500, batch_size=128, gamma=0.99, train_freq=1,
    gradient_steps=1, policy_kwargs=dict(net_arch=[256, 256]), target_update_interval=250, n_steps=1,
    replay_buffer_kwargs=dict(),
)

#: the default sub-goal learner, measured to learn MiniGrid (DoorKey-5x5 to 8x8; design decisions): 64x64 units,
#: an update of batch 32 every 4 primitive steps, 8-step returns with gamma 0.9 and the behaviour's return as a
#: lower bound, Adam lr 1e-4, a target network every 10,000 steps
DEFAULT_SUBPOLICY_KWARGS: dict[str, Any] = dict(
    learning_rate=1e-4, buffer_size=50_000, learning_starts=100, batch_size=32, gamma=0.9, train_freq=4,
    gradient_steps=1, policy_kwargs=dict(net_arch=[64, 64]), target_update_interval=10_000, n_steps=8,
    replay_buffer_kwargs=dict(off_policy_lower_bound=True),
)


def default_subpolicy_kwargs() -> dict[str, Any]:
    """The defaults of every sub-goal learner's keyword argument (:data:`DEFAULT_SUBPOLICY_KWARGS` over the rest)."""
    return dict(
        exploration_initial_eps=1.0, exploration_final_eps=0.05, max_grad_norm=10.0, double_q=True,
        prioritized_replay_alpha=0.6, prioritized_replay_beta=0.4, prioritized_replay_eps=1e-6,
        **{key: (dict(value) if isinstance(value, dict) else value) for key, value in DEFAULT_SUBPOLICY_KWARGS.items()},
    )


def checked_subpolicy_kwargs(subpolicy_kwargs: Optional[dict[str, Any]]) -> dict[str, Any]:
    """``subpolicy_kwargs`` (SB3 DQN's names) over :func:`default_subpolicy_kwargs`, checked: names the learners take
    (:data:`USED`; ``IGNORED`` accepted), a constant learning rate and whole step counts."""
    unknown = set(subpolicy_kwargs or {}) - USED - IGNORED
    if unknown:
        raise ValueError(f"Unknown subpolicy_kwargs {sorted(unknown)}: the sub-goal learners take {sorted(USED)}")
    kw = {**default_subpolicy_kwargs(), **(subpolicy_kwargs or {})}
    if callable(kw["learning_rate"]):
        raise ValueError("subpolicy_kwargs['learning_rate'] must be a number (schedules are not supported)")
    for name in ("train_freq", "gradient_steps", "target_update_interval", "batch_size"):
        if isinstance(kw[name], (tuple, list)) or int(kw[name]) < 1:
            raise ValueError(f"subpolicy_kwargs['{name}'] must be an integer >= 1 (counted in steps), got {kw[name]!r}")
    return kw


def lower_bound_option(kw: dict[str, Any], subpolicy_kwargs: Optional[dict[str, Any]]) -> bool:
    """Whether the learners' replay adds the lower bound (``replay_buffer_kwargs['off_policy_lower_bound']`` of the
    checked ``kw``; the default's is an n-step return, dropped for one-step returns unless asked for)."""
    replay_kwargs = dict(kw.get("replay_buffer_kwargs") or {})
    if int(kw["n_steps"]) < 2 and "replay_buffer_kwargs" not in (subpolicy_kwargs or {}):
        replay_kwargs.pop("off_policy_lower_bound", None)
    lower_bound = bool(replay_kwargs.pop("off_policy_lower_bound", False))
    if replay_kwargs:
        raise ValueError(f"Unknown subpolicy replay_buffer_kwargs {sorted(replay_kwargs)}: only off_policy_lower_bound")
    return lower_bound


def check_optional_count(name: str, value: Any) -> None:
    """``subgoal_learner_kwargs[name]``: a whole number >= 1, or None."""
    if value is not None and (isinstance(value, bool) or int(value) != value or value < 1):
        raise ValueError(f"{name} (subgoal_learner_kwargs) must be an integer >= 1 or None, got {value!r}")


def check_range(target_range: Optional[Sequence[float]]) -> Optional[tuple[float, float]]:
    """``subgoal_learner_kwargs['target_range']``: two finite numbers, low below high, or None."""
    if target_range is None:
        return None
    try:
        low, high = (float(value) for value in target_range)
    except (TypeError, ValueError):
        raise ValueError(f"target_range (subgoal_learner_kwargs) must be two numbers (low, high), e.g. [-1.0, 1.0] for "
                         f"the returns of eq. 5 with alpha 0, got {target_range!r}") from None
    if not (np.isfinite(low) and np.isfinite(high) and low < high):
        raise ValueError(f"target_range (subgoal_learner_kwargs) must be finite with low < high, got {target_range!r}")
    return low, high


def check_learners_state(state: Any, learner: str, kind: str) -> None:
    """Refuse a saved ``state`` of sub-goal learners that ``learner`` (kind ``kind`` of ``subgoal_learner_kwargs``)
    did not write: a clear error, not a failure somewhere inside torch."""
    if not isinstance(state, dict) or state.get("format") != f"sb3_hhp.{learner}":
        raise ValueError(f"These sub-goal learners were not saved by {learner} (subgoal_learner_kwargs kind={kind!r}): "
                         "load the model with the subgoal_learner_kwargs kind it was trained with")
