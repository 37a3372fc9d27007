"""The SB3 callbacks that do HhP's work between episodes (Algorithm 1, lines 24-29 and 35).

With ``train_freq=(1, "episode")`` a rollout is one episode, so ``_on_rollout_end`` runs once per
episode, after the episode and before the meta-controller's N_opt updates (``HhP.train``):

- :class:`PreferenceQueryCallback`: returns of the episode's choices (line 24), MC-dropout confidence
  (line 25), questions for the least confident choices within the budget (line 26), answers into the
  durable store and the predictor, 4 epochs of Bradley-Terry training when labels arrived (line 27);
- :class:`SubgoalDiscoveryCallback`: the first sub-goal (line 5) and CSD (line 29);
- :class:`CuriosityUpdateCallback`: the RND update and the Omega refresh (line 35);
- :class:`GalleryCallback`: the sub-goal gallery data for the labeling app, every few episodes.
"""

from typing import TYPE_CHECKING, Optional

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback, ProgressBarCallback

from sb3_hhp.oracles.base import Query

if TYPE_CHECKING:
    from sb3_hhp.hhp.hhp import HhP


def _key_json(key: object) -> list:
    return list(key) if isinstance(key, tuple) else [key]


class PreferenceQueryCallback(BaseCallback):
    """Asks the oracle about the episode's least confident sub-goal choices and trains the predictor."""

    model: "HhP"

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        model = self.model
        oracle = model.oracle
        if oracle is None or model.hierarchy is None:
            return
        trace = model.hierarchy.last_trace
        if trace.high_goals:
            states = np.stack(trace.high_obs)
            goals = np.asarray(trace.high_goals)
            goal_obs = model.goal_obs
            if hasattr(oracle, "observe"):  # the synthetic oracle learns average returns from experience
                returns = np.cumsum(np.asarray(trace.high_returns)[::-1])[::-1]  # line 24, undiscounted
                oracle.observe(states, goal_obs[goals], returns)
                oracle.train()
            self._ask(states, goals, goal_obs, trace)
        self._receive()

    def _ask(self, states: np.ndarray, goals: np.ndarray, goal_obs: np.ndarray, trace) -> None:
        model = self.model
        if model.query_selector.remaining == 0 or len(model.subgoals) < 2:
            return
        confidences = model.predictor.confidence(model.predictor_inputs(states), model.predictor_inputs(goal_obs[goals]))  # line 25, eq. 4
        model.last_confidences = confidences
        with th.no_grad():
            obs_tensor, _ = model.policy.obs_to_tensor(states)
            q_values = model.q_net(obs_tensor).cpu().numpy()
        q_values[~np.broadcast_to(model.action_mask(states), q_values.shape)] = -np.inf  # g2 among the choosable sub-goals
        selected = model.query_selector.select(confidences, goals, q_values, num_timesteps=model.num_timesteps)
        if not selected:
            return
        goal_space, subgoals = model.goal_space, model.subgoals
        queries = []
        for index, second in selected:  # line 26
            first = int(goals[index])
            state_image = trace.high_images[index] if index < len(trace.high_images) else None
            if state_image is None:
                state_image = goal_space.image_of(states[index])
            queries.append(
                Query(
                    state=states[index], goal1=first, goal2=int(second),
                    goal1_obs=subgoals[first].obs, goal2_obs=subgoals[second].obs,
                    state_image=state_image, goal1_image=subgoals[first].image, goal2_image=subgoals[second].image,
                    info={
                        "state": trace.high_privileged[index],
                        "goal1_key": _key_json(subgoals[first].key),
                        "goal2_key": _key_json(subgoals[second].key),
                        "goal1_name": goal_space.describe(subgoals[first].key),
                        "goal2_name": goal_space.describe(subgoals[second].key),
                        **goal_space.query_info(states[index], subgoals[first].obs, subgoals[second].obs),
                    },
                )
            )
        for query in queries:  # durable before anyone answers
            model.store.add_query(query)
            model.pending_queries[query.query_id] = query
        model.oracle.submit(queries)

    def _receive(self) -> None:
        model = self.model
        new_labels = 0
        for answer in model.oracle.collect():
            if answer.query_id in model.consumed_query_ids:
                continue
            query = model.pending_queries.pop(answer.query_id, None) or model.store.get_query(answer.query_id)
            if model.store.get_answer(answer.query_id) is None:
                model.store.add_answer(answer.query_id, answer.label, answer.annotator, answer.answered_at)
            model.consumed_query_ids.add(answer.query_id)
            new_labels += int(model.add_preference(query, answer.label))
        if new_labels:  # line 27: 4 epochs on R
            model.last_predictor_stats = model.predictor.train()


class SubgoalDiscoveryCallback(BaseCallback):
    """Adds the first sub-goal (a random state of the first episode) and then CSD's discoveries."""

    model: "HhP"

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        model = self.model
        hierarchy = model.hierarchy
        if hierarchy is None:
            return
        trace = hierarchy.last_trace
        if not trace.low_obs:
            return
        goal_space = model.goal_space
        states = np.stack(trace.low_obs)
        if hierarchy.n_subgoals == 0:  # line 5: a random visited state
            index = int(model.discovery.rng.integers(len(states)))
            model.add_subgoal(trace.low_keys[index], states[index], goal_space.image_of(states[index]), source="random")
            return
        if model.discovery_strategy == "none":
            return
        rho = None
        if model.discovery.strategy == "csd":
            rho = model.rnd.novelty_progress(states) if model.rnd is not None else np.zeros(len(states))
        chosen = model.discovery.select(
            states, trace.low_keys, rho, hierarchy.visits, [goal.key for goal in hierarchy.subgoals], model.goal_obs
        )
        for index in chosen:  # line 29
            model.add_subgoal(trace.low_keys[index], states[index], goal_space.image_of(states[index]),
                              source=model.discovery.strategy)


class CuriosityUpdateCallback(BaseCallback):
    """Trains the RND predictor on the episode's states (Omega refreshes every T steps as they pass)."""

    model: "HhP"

    def __init__(self, n_epochs: int = 1) -> None:
        super().__init__()
        self.n_epochs = n_epochs

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        model = self.model
        if model.rnd is None or model.hierarchy is None or not model.hierarchy.last_trace.low_obs:
            return
        loss = model.rnd.update(np.stack(model.hierarchy.last_trace.low_obs), n_epochs=self.n_epochs)  # line 35
        self.logger.record("hhp/rnd_loss", loss)


class GalleryCallback(BaseCallback):
    """Writes the sub-goal gallery (images, success rates, recent choices, scores) into the store."""

    model: "HhP"

    def __init__(self, every_episodes: int = 10) -> None:
        super().__init__()
        self.every_episodes = every_episodes
        self._episodes = 0

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        self._episodes += 1
        if self._episodes % self.every_episodes == 0 and self.model.subgoals:
            self.model.store.put_subgoals(self.model.subgoal_records())


class PrimitiveStepProgressBar(ProgressBarCallback):
    """SB3's progress bar, counting primitive env steps rather than sub-goal choices."""

    def _on_step(self) -> bool:
        self.pbar.update(self.model.num_timesteps - self.pbar.n)
        return True


def hhp_callbacks(model: "HhP", gallery_every: Optional[int] = 10) -> list[BaseCallback]:
    """The callbacks HhP runs between episodes, in Algorithm 1's order."""
    callbacks: list[BaseCallback] = [PreferenceQueryCallback(), SubgoalDiscoveryCallback(), CuriosityUpdateCallback()]
    if gallery_every and model.preference_db is not None:
        callbacks.append(GalleryCallback(gallery_every))
    return callbacks
