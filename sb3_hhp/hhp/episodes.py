"""HhP's work between episodes (Algorithm 1, lines 24-29 and 35), as named steps of the algorithm.

After each finished episode, before the meta-controller's N_opt updates, :meth:`BetweenEpisodes.after_episode`
runs, in Algorithm 1's order:

- :meth:`~BetweenEpisodes.ask_preferences`: returns of the episode's choices (line 24), MC-dropout confidence
  (line 25), questions for the least confident choices within the budget (line 26);
- :meth:`~BetweenEpisodes.receive_answers`: answers into the durable store and the predictor, 4 epochs of
  Bradley-Terry training when labels arrived (line 27);
- :meth:`~BetweenEpisodes.discover_subgoals`: the first sub-goal (line 5) and CSD (line 29);
- :meth:`~BetweenEpisodes.update_curiosity`: the RND update (line 35; Omega refreshes every T steps as they pass);
- the sub-goal gallery for the labeling app, every ``gallery_every`` episodes (:meth:`~BetweenEpisodes.subgoal_records`);

and, when ``learn`` starts, :meth:`~BetweenEpisodes.resume_preferences` feeds the predictor what the store holds.
"""

import hashlib
from collections import Counter
from collections.abc import Hashable
from typing import Any

import numpy as np
import torch as th

from sb3_hhp.hierarchy.options import EpisodeTrace
from sb3_hhp.preferences.types import Query


def _key_json(key: object) -> list:
    return list(key) if isinstance(key, tuple) else [key]


def question_state_id(predictor_input: np.ndarray) -> str:
    """An id of a state as the preference predictor reads it: states with the same id are one question's state."""
    return hashlib.sha1(np.ascontiguousarray(predictor_input).tobytes()).hexdigest()[:20]


def question_signature(state_id: str, goal1_key: Hashable, goal2_key: Hashable) -> str:
    """A question: its state's id and the unordered pair of its sub-goals' keys."""
    first, second = sorted((repr(goal1_key), repr(goal2_key)))
    return f"{state_id}|{first}|{second}"


class BetweenEpisodes:
    """The between-episode steps of :class:`~sb3_hhp.hhp.hhp.HhP` (a mixin: they read the model's components)."""

    #: episodes between two writes of the sub-goal gallery into the store (when it is a file)
    gallery_every = 10

    def after_episode(self: Any, trace: EpisodeTrace) -> None:
        """Everything Algorithm 1 does between an episode and the meta-controller's updates."""
        self.ask_preferences(trace)
        # the facts a question carries are recorded at each choice only while questions can still be asked
        self.options.record_privileged = self.oracle is not None and self.query_selector.remaining > 0
        self.receive_answers()
        self.discover_subgoals(trace)
        self.update_curiosity(trace)
        self._episodes_done = getattr(self, "_episodes_done", 0) + 1
        if self.preference_db is not None and self.subgoals and self._episodes_done % self.gallery_every == 0:
            self.subgoal_table.put(self.subgoal_records())

    # ------------------------------------------------------------------ preferences (lines 24-27)
    def ask_preferences(self: Any, trace: EpisodeTrace) -> None:
        """Ask the oracle about the episode's least confident sub-goal choices, within the budget."""
        oracle = self.oracle
        if oracle is None or not trace.high_goals:
            return
        states, goals, goal_obs = np.stack(trace.high_obs), np.asarray(trace.high_goals), self.goal_obs
        if hasattr(oracle, "observe"):  # the synthetic oracle learns average returns from experience
            returns = np.cumsum(np.asarray(trace.high_returns)[::-1])[::-1]  # line 24, undiscounted
            oracle.observe(states[: len(returns)], goal_obs[goals[: len(returns)]], returns)
            oracle.train_on_new()  # updates in proportion to the new triples (design decisions: synthetic oracle)
        if self.query_selector.remaining == 0 or len(self.subgoals) < 2 or None in trace.high_privileged:
            return  # no budget, nothing to compare, or an episode played while no question could be asked
        if self.query_selector.idle(self.num_timesteps):
            return  # the questions are up with the paced allowance: no confidence is needed
        # a question is (an equivalent state, an unordered pair of sub-goals): states the predictor reads alike are
        # equivalent, and a question asked before (in this run or one it resumes) is never asked again
        inputs = self.predictor_inputs(states)
        state_ids = [question_state_id(x) for x in inputs]
        keys = self.subgoal_set.keys
        unique = sorted({(state_ids[i], int(goals[i])): i for i in range(len(goals) - 1, -1, -1)}.values())
        states, goals, inputs = states[unique], goals[unique], inputs[unique]
        state_ids = [state_ids[i] for i in unique]
        with th.no_grad():
            q_values = self._q_values(self.policy.obs_to_tensor(states)[0]).cpu().numpy()
        q_values[~np.broadcast_to(self.action_mask(states), q_values.shape)] = -np.inf  # g2 among the choosable sub-goals
        asked = self.asked_signatures
        exclude = np.zeros(q_values.shape, dtype=bool)
        for row, goal in enumerate(goals):
            for second in range(len(keys)):
                exclude[row, second] = question_signature(state_ids[row], keys[goal], keys[second]) in asked
        success = self.success_goal if self.success_bonus == "best" else None
        if success is not None:  # the task's own goal is judged by the extrinsic reward alone: never in a question
            exclude[:, success] = True
            exclude[goals == success] = True
        unasked = None
        if self.query_selector.second == "unasked":
            named = self.asked_goal_keys
            unasked = np.zeros(q_values.shape[1], dtype=bool)  # the meta-controller's room for more sub-goals: invalid
            unasked[: len(keys)] = [key not in named for key in keys]
        second_inputs = None
        if self.query_selector.reading == "pair":  # the spread of the question's answer: g2 first
            seconds = self.query_selector.seconds(goals, q_values, exclude=exclude, unasked=unasked)
            second_inputs = self.predictor_inputs(goal_obs[np.where(seconds >= 0, seconds, goals)])  # no g2: unasked
        confidences = self.predictor.confidence(inputs, self.predictor_inputs(goal_obs[goals]), second_inputs)  # l. 25
        self.last_confidences = confidences
        selected = self.query_selector.select(confidences, goals, q_values, num_timesteps=self.num_timesteps,
                                              exclude=exclude, unasked=unasked)
        queries, repeated = [], 0
        for index, second in selected:  # line 26
            signature = question_signature(state_ids[index], keys[goals[index]], keys[second])
            if signature in asked:  # the same pair asked from another tuple of this episode
                repeated += 1
                continue
            asked.add(signature)
            self.asked_goal_keys.update((keys[goals[index]], keys[second]))
            query = self._query(trace, states, goals, index, second, unique[index])
            query.info["signature"] = signature
            queries.append(query)
        self.query_selector.refund(repeated)
        for query in queries:  # durable before anyone answers
            self.store.add_query(query)
            self.pending_queries[query.query_id] = query
        if queries:
            oracle.submit(queries)

    @property
    def asked_signatures(self: Any) -> set[str]:
        """The questions asked so far (:func:`question_signature`), read from the store once per ``learn``."""
        if getattr(self, "_asked_signatures", None) is None:
            signatures = set()
            for query_id in self.store.asked_ids():
                query = self.store.get_query(query_id)
                signature = query.info.get("signature")
                if signature is None and max(query.goal1, query.goal2) < len(self.subgoals):  # asked before signatures
                    state_id = question_state_id(self.predictor_inputs(np.asarray(query.state)[None])[0])
                    signature = question_signature(state_id, self.subgoals[query.goal1].key, self.subgoals[query.goal2].key)
                if signature is not None:
                    signatures.add(signature)
            self._asked_signatures = signatures
        return self._asked_signatures

    @property
    def asked_goal_keys(self: Any) -> set:
        """The keys of the sub-goals that the questions asked so far named, read from the store once per ``learn``."""
        if getattr(self, "_asked_goal_keys", None) is None:
            self._asked_goal_keys = {self.subgoals[goal].key for *goals, _ in self.store.question_goals()
                                     for goal in goals if goal < len(self.subgoals)}
        return self._asked_goal_keys

    def _query(self: Any, trace: EpisodeTrace, states: np.ndarray, goals: np.ndarray, index: int, second: int,
               choice: int) -> Query:
        """The question about tuple ``index`` (the episode's choice ``choice``) and the sub-goal ``second``."""
        goal_space, subgoals = self.goal_space, self.subgoals
        first = int(goals[index])
        facts = goal_space.facts(trace.high_privileged[choice])
        state_image = trace.high_images[choice] if choice < len(trace.high_images) else None
        if state_image is None and goal_space.draws_from_facts:
            state_image = goal_space.image_in_state(facts)
        if state_image is None:
            state_image = goal_space.image_of(states[index])
        return Query(
            state=states[index], goal1=first, goal2=second,
            goal1_obs=subgoals[first].obs, goal2_obs=subgoals[second].obs,
            state_image=state_image, goal1_image=subgoals[first].image, goal2_image=subgoals[second].image,
            info={
                "state": facts,
                "goal1_key": _key_json(subgoals[first].key),
                "goal2_key": _key_json(subgoals[second].key),
                "goal1_name": goal_space.describe(subgoals[first].key),
                "goal2_name": goal_space.describe(subgoals[second].key),
                **goal_space.query_info(states[index], subgoals[first].obs, subgoals[second].obs),
                **({"goal1_state": goal_space.facts(subgoals[first].snapshot),
                    "goal2_state": goal_space.facts(subgoals[second].snapshot)}
                   if subgoals[first].snapshot is not None and subgoals[second].snapshot is not None else {}),
            },
        )

    def receive_answers(self: Any) -> int:
        """Store the oracle's new answers, feed them to the predictor and train it when labels arrived
        (line 27: 4 epochs on R); the number of labels that taught something."""
        if self.oracle is None:
            return 0
        new_labels = 0
        for answer in self.oracle.collect():
            if answer.query_id in self.consumed_query_ids:
                continue
            query = self.pending_queries.pop(answer.query_id, None) or self.store.get_query(answer.query_id)
            if self.store.get_answer(answer.query_id) is None:
                self.store.add_answer(answer.query_id, answer.label, answer.annotator, answer.answered_at)
            self.consumed_query_ids.add(answer.query_id)
            new_labels += int(self.add_preference(query, answer.label))
        if new_labels:
            self.last_predictor_stats = self.predictor.train()
        return new_labels

    # ------------------------------------------------------------------ sub-goals (lines 5 and 29)
    def discover_subgoals(self: Any, trace: EpisodeTrace) -> list[int]:
        """The first sub-goal (a random state of the first episode, line 5), then CSD's discoveries (line 29);
        the ids of the sub-goals added."""
        if not trace.low_obs:
            return []
        goal_space = self.goal_space
        states, keys, snapshots = trace.low_states(), trace.low_keys, trace.low_privileged
        if len(snapshots) == len(states):  # questions will carry a sub-goal's facts: only states with them
            usable = np.flatnonzero([snapshot is not None for snapshot in snapshots])
            states, keys, snapshots = states[usable], [keys[i] for i in usable], [snapshots[i] for i in usable]
            if not len(states):
                return []
        else:
            snapshots = [None] * len(states)
        if len(self.subgoals) == 0:  # line 5: a random visited state
            index = int(self.discovery.rng.integers(len(states)))
            return [self.add_subgoal(keys[index], states[index], goal_space.image_of(states[index]), source="random",
                                     snapshot=snapshots[index])]
        if self.discovery_strategy == "none" or trace.random:
            return []
        rho = None
        if self.discovery.strategy == "csd":
            rho = self.rnd.novelty_progress(states) if self.rnd is not None else np.zeros(len(states))
        chosen = self.discovery.select(states, keys, rho, self.subgoal_set.visits, self.subgoal_set.keys, self.goal_obs)
        return [self.add_subgoal(keys[index], states[index], goal_space.image_of(states[index]),
                                 source=self.discovery.strategy, snapshot=snapshots[index]) for index in chosen]

    # ------------------------------------------------------------------ curiosity (line 35)
    def update_curiosity(self: Any, trace: EpisodeTrace, n_epochs: int = 1) -> None:
        """Train the RND predictor on the episode's states."""
        if self.rnd is None or not trace.low_obs:
            return
        loss = self.rnd.update(trace.low_states(), n_epochs=n_epochs)
        self.logger.record("hhp/rnd_loss", loss)

    # ------------------------------------------------------------------ resuming, the gallery
    def resume_preferences(self: Any) -> int:
        """Feed the predictor every answered label of the store it has not seen yet, and count every
        question already asked against the budget, so a resumed run loses no label and asks nothing twice."""
        self._asked_signatures = self._asked_goal_keys = None  # read again from the store
        added = 0
        for _, query, answer in self.store.answers_since(0):
            if query.query_id in self.consumed_query_ids:
                continue
            self.consumed_query_ids.add(query.query_id)
            added += int(self.add_preference(query, answer.label))
        state = self.query_selector.state_dict()
        asked = self.store.count_asked()
        if asked > state["used"]:
            state["used"] = min(asked, self.query_budget)
            self.query_selector.load_state_dict(state)
        if added:
            self.last_predictor_stats = self.predictor.train()
        return added

    def subgoal_records(self: Any) -> list[dict[str, Any]]:
        """One record per sub-goal for the gallery: id, image, when found, success rate, recent choices, mean score."""
        counts = Counter(self.recent_choices)
        records = []
        goal_obs = self.predictor_inputs(self.goal_obs) if self.subgoals else None
        states = np.stack(self._last_trace.high_obs) if self._last_trace.high_obs else None
        states = None if states is None else self.predictor_inputs(states)
        for goal_id, goal in enumerate(self.subgoals):
            mean_score = None
            if states is not None and len(self.predictor) > 0:
                mean_score = float(np.mean(self.predictor.score(states, np.repeat(goal_obs[goal_id : goal_id + 1], len(states), 0))))
            records.append(
                dict(
                    id=goal_id,
                    image=goal.image if goal.image is not None else np.zeros((8, 8, 3), np.uint8),
                    found_at=int(goal.found_at),
                    success_rate=self.subpolicies.success_rate(goal_id) if goal_id < len(self.subpolicies) else None,
                    chosen_recently=int(counts.get(goal_id, 0)),
                    mean_score=mean_score,
                    name=self.goal_space.describe(goal.key),
                )
            )
        return records
