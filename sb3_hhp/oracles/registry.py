"""Oracles by name, for ``HhP(oracle="scripted")`` and ``python -m sb3_hhp.train --oracle NAME``."""

import inspect
from typing import Any, Optional

from gymnasium import spaces

from sb3_hhp.goals.base import GoalSpace
from sb3_hhp.goals.image import MONTEZUMA
from sb3_hhp.oracles.base import Oracle

#: the names :func:`make_oracle` builds an oracle from ("auto": "scripted" where the task has a scripted oracle, else
#: "synthetic")
ORACLE_NAMES = ("scripted", "noisy-scripted", "synthetic", "auto", "web", "terminal", "none")


def has_scripted_oracle(goal_space: GoalSpace) -> bool:
    """Whether a scripted oracle answers for ``goal_space``: MiniGrid's, Fetch's, and the image goal space's where it
    is bound to Montezuma's Revenge."""
    return goal_space.name in ("minigrid", "fetch") or (goal_space.name == "image"
                                                          and getattr(goal_space, "game", None) == MONTEZUMA)


def make_oracle(
    name: str,
    goal_space: GoalSpace,
    observation_space: spaces.Space,
    store: Any = None,
    seed: Optional[int] = None,
    **kwargs: Any,
) -> Optional[Oracle]:
    """Build the oracle called ``name`` for a goal space.

    :param name: one of :data:`~sb3_hhp.oracles.registry.ORACLE_NAMES`
    :param goal_space: the goal space of the task (decides which scripted oracle applies: MiniGrid's, Fetch's, or
        Montezuma's Revenge's for an :class:`~sb3_hhp.goals.image.ImageGoalSpace` bound to it)
    :param observation_space: observations the synthetic oracle's network reads
    :param store: the preference store (the web oracle's queue)
    :param seed: seed of random oracles
    :param kwargs: passed to the oracle (e.g. ``rho`` for "noisy-scripted")
    """
    if name not in ORACLE_NAMES:
        raise ValueError(f"Unknown oracle {name!r}: use one of {', '.join(ORACLE_NAMES)} or pass an Oracle instance")
    if name == "none":
        return None
    if name == "auto":
        name = "scripted" if has_scripted_oracle(goal_space) else "synthetic"
    if name in ("scripted", "noisy-scripted"):
        rho = kwargs.pop("rho", 0.1)
        if goal_space.name == "minigrid":
            from sb3_hhp.oracles.scripted import MiniGridScriptedOracle

            matched = {option: getattr(goal_space, option, False)  # the goal space's key options, which it must match
                       for option in ("count_open_doors", "mark_blockers", "color_relation",
                                     "mark_target")}
            matched["use_color"] = goal_space.color_option
            oracle: Oracle = MiniGridScriptedOracle(**matched, **_checked(MiniGridScriptedOracle, name, kwargs,
                                                                          tuple(matched)))
        elif goal_space.name == "fetch":
            from sb3_hhp.oracles.fetch import FetchScriptedOracle

            oracle = FetchScriptedOracle(**_checked(FetchScriptedOracle, name, kwargs))
        elif goal_space.name == "image":
            game = getattr(goal_space, "game", None)
            if game != MONTEZUMA:
                served = f"the ALE game {game!r}" if game else "this env (not an ALE game, or a goal space not bound to one)"
                raise ValueError(
                    f"There is no scripted oracle for the 'image' goal space on {served}: only ALE Montezuma's Revenge "
                    "has one (an ImageGoalSpace bound to it, ImageGoalSpace.bind(env)); use 'synthetic', 'web' or 'terminal'"
                )
            from sb3_hhp.oracles.montezuma import MontezumaScriptedOracle

            oracle = MontezumaScriptedOracle(**_checked(MontezumaScriptedOracle, name, kwargs))
        else:
            raise ValueError(
                f"There is no scripted oracle for the {goal_space.name!r} goal space: use 'synthetic', 'web' or 'terminal'"
            )
        if name == "noisy-scripted":
            from sb3_hhp.oracles.noisy import NoisyOracle

            oracle = NoisyOracle(oracle, rho=rho, seed=seed)
        return oracle
    if name == "synthetic":
        from sb3_hhp.oracles.synthetic import SyntheticOracle

        return SyntheticOracle(observation_space, seed=seed,
                               **_checked(SyntheticOracle, name, kwargs, ("observation_space", "seed")))
    if name == "web":
        from sb3_hhp.oracles.web import WebOracle

        if store is None:
            raise ValueError("The web oracle needs a preference store (preference_db=PATH)")
        return WebOracle(store, **_checked(WebOracle, name, kwargs, ("store",)))
    from sb3_hhp.oracles.terminal import TerminalOracle

    return TerminalOracle(**_checked(TerminalOracle, name, kwargs))


def _checked(cls: type, name: str, kwargs: dict[str, Any], given: tuple[str, ...] = ()) -> dict[str, Any]:
    """``kwargs`` after checking that ``cls`` (the oracle ``name`` builds) takes each (``given``: set here, not by the
    caller); a clear error naming the ones it does not take and the ones it does."""
    accepted = set(inspect.signature(cls.__init__).parameters) - {"self", *given}
    unknown = sorted(set(kwargs) - accepted)
    if unknown:
        raise ValueError(f"The {name!r} oracle ({cls.__name__}) takes no {', '.join(map(repr, unknown))} "
                         f"(query_kwargs['oracle_kwargs']); it takes {', '.join(sorted(accepted)) or 'none'}")
    return kwargs
