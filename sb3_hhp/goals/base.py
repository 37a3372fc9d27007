"""The goal-space abstraction: what a sub-goal is in a domain.

A goal space maps an observation to a hashable *sub-goal key* (``key``), decides ``done(s, g)``
(:meth:`GoalSpace.achieved`), measures how similar a candidate is to the stored sub-goals
(:meth:`GoalSpace.similarity`, used by the discovery gate ``b_similarity``) and renders the
image that a person is shown. Networks see the observation recorded where a sub-goal was found.
"""

from abc import ABC, abstractmethod
from collections.abc import Callable, Hashable, Sequence
from typing import Any, Optional

import gymnasium as gym
import numpy as np

#: the key of the "task solved" situation: the episode ended with a positive extrinsic reward
SUCCESS_KEY: tuple = ("success",)


class GoalSpace(ABC):
    """One domain's notion of a sub-goal."""

    #: short name used in configs (``goal_space="minigrid"``)
    name: str = "base"
    #: whether a :meth:`snapshot` is cheap enough to take at every primitive step: then each sub-goal keeps the facts
    #: of the state it was found in, and a question carries them as ``info["goal1_state"]`` / ``["goal2_state"]``
    facts_per_step: bool = False

    @classmethod
    @abstractmethod
    def supports(cls, env: gym.Env) -> bool:
        """Whether this goal space can be used with ``env`` (its observation space and base env)."""

    def bind(self, env: gym.Env) -> None:
        """Learn once what this goal space needs of the env it serves (an env it :meth:`supports`), and check its
        settings against it; raises ``ValueError`` when they do not fit. Default: nothing to learn."""

    def learner_input(self, observation_space: gym.spaces.Space) -> Optional[dict[str, Any]]:
        """The sub-goal learners' ``view``, ``overview`` and ``one_hot`` that ``"auto"`` in ``subgoal_learner_kwargs``
        stands for on this goal space's env (observations of ``observation_space``); None: it derives none (the
        default)."""
        return None

    def learner_codes(self) -> Optional[Callable[[np.ndarray], np.ndarray]]:
        """What the sub-goal learners read in place of observations ``(..., H, W, C)``, as a function of them, where it
        differs from the observations (the learners apply it before their ``view``, ``overview`` and ``one_hot``);
        None: the observations themselves (the default)."""
        return None

    @abstractmethod
    def key(self, obs: np.ndarray) -> Hashable:
        """The sub-goal key of an observation (the situation it shows)."""

    def terminal_key(self, obs: np.ndarray, reward: float, terminated: bool) -> Hashable:
        """The key reached by a transition: :data:`~sb3_hhp.goals.base.SUCCESS_KEY` when the task was solved, else ``key(obs)``."""
        if terminated and reward > 0:
            return SUCCESS_KEY
        return self.key(obs)

    def discoverable(self, key: Hashable) -> bool:
        """Whether a state of key ``key`` may become a sub-goal (CSD and the random strategy ask before the visit
        and similarity gates). Default: every key."""
        return True

    def achieved(self, key: Hashable, goal_key: Hashable) -> bool:
        """``done(s, g)``: the state's key equals the sub-goal's key."""
        return key == goal_key

    def choosable(self, key: Hashable, goal_key: Hashable, present: Optional[frozenset] = None) -> bool:
        """Whether the meta-controller may choose ``goal_key`` in a state of key ``key`` (with
        ``mask_subgoals``): not when it is already achieved there, since running its subpolicy would
        only leave the sub-goal to come back to it. Domains may rule out more. ``present``: what
        :meth:`present` says of the state (None: unknown)."""
        return not self.achieved(key, goal_key)

    def action_mask(self, obs: np.ndarray) -> Optional[np.ndarray]:
        """The primitive actions the sub-goal learners may take in each state of ``obs`` (a batch with any leading
        shape), as booleans ``(*leading, n_actions)``; None: every action (the default)."""
        return None

    def carried_counterfactual(self, goal_key: Hashable, obs: np.ndarray, actions: np.ndarray,
                               next_obs: np.ndarray) -> Optional[tuple[np.ndarray, np.ndarray, np.ndarray, list]]:
        """Transitions ``obs -> next_obs`` (batches ``(m, *obs_shape)``, actions ``(m,)``) made with empty hands, as
        they would have gone carrying what ``goal_key`` carries, where that changes nothing else: ``(usable (m,),
        obs', next_obs', keys of the usable rows of next_obs')``; None where the goal space has no such notion or
        ``goal_key`` carries nothing (the default)."""
        return None

    def present(self, obs: np.ndarray) -> Optional[frozenset]:
        """What is in the state beyond its key, as far as :meth:`choosable` uses it (None: nothing; the
        default). States with equal keys and equal ``present`` get the same mask."""
        return None

    def present_batch(self, observations: np.ndarray) -> list[Optional[frozenset]]:
        """:meth:`present` of each observation of a batch ``(N, *obs_shape)`` (a goal space may do them at once)."""
        return [self.present(obs) for obs in observations]

    def features(self, obs: np.ndarray) -> Optional[np.ndarray]:
        """A compact description of a batch of observations ``(B, *obs_shape)`` as float vectors ``(B, F)``
        that recurs across layouts, for the preference predictor (``HhP(predictor_kwargs=dict(input="auto"))``);
        None (the default): the predictor reads the observations themselves."""
        return None

    def features_dim(self, observation_space: gym.spaces.Box) -> Optional[int]:
        """The length F of :meth:`features` for observations of ``observation_space`` (None: no features)."""
        sample = self.features(np.zeros((1, *observation_space.shape), dtype=observation_space.dtype))
        return None if sample is None else int(sample.shape[1])

    def similarity(self, key: Hashable, obs: np.ndarray, goal_keys: Sequence[Hashable], goal_obs: np.ndarray) -> np.ndarray:
        """Similarity in [0, 1] of a candidate to every stored sub-goal (default: equal keys -> 1, else 0)."""
        return np.array([1.0 if key == other else 0.0 for other in goal_keys], dtype=np.float64)

    def privileged(self, env: gym.Env) -> dict[str, Any]:
        """Privileged facts about the current state for scripted oracles (never shown to people), as JSON values."""
        return {}

    def snapshot(self, env: gym.Env) -> Any:
        """What :meth:`privileged` needs of the current state, kept compact: training takes one at every sub-goal
        choice while questions remain, and turns into facts (:meth:`facts`) only those a question is asked about.
        Default: the facts themselves."""
        return self.privileged(env)

    def facts(self, snapshot: Any) -> dict[str, Any]:
        """The privileged facts (JSON values) of a :meth:`snapshot`."""
        return dict(snapshot)

    def query_info(self, state: np.ndarray, goal1_obs: np.ndarray, goal2_obs: np.ndarray) -> dict[str, Any]:
        """Facts a scripted oracle reads off a question's state and its two sub-goals' observations, added
        to the question's ``info`` (JSON values; default: none)."""
        return {}

    def render(self, env: gym.Env) -> Optional[np.ndarray]:
        """An RGB image of the current state for people (None when the env cannot render)."""
        try:
            frame = env.unwrapped.render() if getattr(env.unwrapped, "render_mode", None) == "rgb_array" else None
        except Exception:  # rendering is a convenience: never let it stop training
            frame = None
        return None if frame is None else np.asarray(frame, dtype=np.uint8)

    def image_of(self, obs: np.ndarray) -> Optional[np.ndarray]:
        """An RGB image of an observation for people (None when the observation cannot be drawn)."""
        return None

    def describe(self, key: Hashable) -> str:
        """A short human-readable name of a sub-goal key."""
        return str(key)

    def key_from_json(self, value: Any) -> Hashable:
        """The sub-goal key stored as JSON in a question's ``info`` (a tuple key comes back as a list)."""
        return tuple(value) if isinstance(value, list) else value

    #: whether :meth:`image_in_state` draws a state from its privileged facts: then a question's state image is drawn
    #: from the facts of that choice, and training renders nothing at its choices (a render per choice costs
    #: 1.3-2.6 ms on MiniGrid, more than the rest of a primitive step)
    draws_from_facts: bool = False

    def image_in_state(self, state: dict[str, Any], key: Optional[Hashable] = None) -> Optional[np.ndarray]:
        """An RGB image of the state whose privileged facts (:meth:`privileged`) are ``state``, drawn the
        same way for every question; with ``key``, the part of that state the sub-goal concerns stands
        out, so a person sees the sub-goal in the layout in front of them. None (the default): this goal
        space cannot draw from those facts, and people see the sub-goal's own image."""
        return None
