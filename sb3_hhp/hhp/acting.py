"""How HhP acts: the meta-controller's choice of sub-goals and :meth:`~sb3_hhp.hhp.acting.HierarchicalActing.predict`'s primitive actions.

``predict`` carries each env's sub-goal and its step count in SB3's ``state`` (as RecurrentPPO carries LSTM states),
so SB3's ``evaluate_policy`` works unchanged; a new sub-goal is chosen at an episode start, when the current one is
reached, or when it gives up (``terminal(s, g)``: :func:`~sb3_hhp.hierarchy.options.option_terminal`, the one test
that training shares). With ``break_cycles`` a greedy policy back in an observation takes the best choice, and the
best action, it has not taken there yet.
"""

import hashlib
from typing import Optional, Union

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_hhp.dqn.dqn import DoubleDQN
from sb3_hhp.hierarchy.options import option_terminal

#: the choices of an episode ``predict`` remembers per env with ``break_cycles`` (a loop of choices is a few long)
CHOICE_MEMORY = 64


def observation_digests(batch: np.ndarray) -> list[bytes]:
    """A 16-byte digest (blake2b) of each observation of a batch: how the masks' cache and the deterministic policy's
    memory of visited states tell observations apart without keeping them."""
    return [hashlib.blake2b(obs.tobytes(), digest_size=16).digest() for obs in batch]


class HierarchicalActing:
    """The acting of :class:`~sb3_hhp.hhp.hhp.HhP` (a mixin: it reads the model's meta-controller, sub-goals and learners)."""

    #: states whose key and reach (:meth:`action_mask`) are kept; the cache is emptied when a batch would overfill it
    present_cache_size = 100_000

    def action_mask(self, observations: Union[np.ndarray, dict[str, np.ndarray]]) -> Optional[np.ndarray]:
        """The sub-goals the meta-controller may choose in each state: the existing ones, and with
        ``mask_subgoals`` only those the goal space calls choosable from the state's key (a state where
        none is keeps every existing sub-goal)."""
        valid = self._valid_actions
        if valid is None or not self.mask_subgoals or isinstance(observations, dict):
            return valid
        batch = self._env_layout(np.asarray(observations)).astype(self.primitive_observation_space.dtype, copy=False)
        goal_keys = [goal.key for goal in self.subgoals]
        rows = np.empty((len(batch), len(valid)), dtype=bool)
        digests = observation_digests(batch)  # 16 bytes, not 6.6 KB (47x47x3)
        unseen = {digest: i for i, digest in enumerate(digests) if digest not in self._present_cache}
        if unseen:  # key and present of a state, reused whenever the same observation recurs; new ones in one batch
            if len(self._present_cache) + len(unseen) > self.present_cache_size:
                self._present_cache.clear()  # and every state of the batch is new again
                unseen = {digest: i for i, digest in enumerate(digests)}
            index = list(unseen.values())
            for digest, i, present in zip(unseen, index, self.goal_space.present_batch(batch[index])):
                self._present_cache[digest] = (self.goal_space.key(batch[i]), present)
        for i, digest in enumerate(digests):
            key, present = self._present_cache[digest]
            row = self._mask_cache.get((key, present))
            if row is None:
                row = valid.copy()
                row[: len(goal_keys)] = [self.goal_space.choosable(key, goal_key, present) for goal_key in goal_keys]
                row = row if row.any() else valid
                self._mask_cache[(key, present)] = row
            rows[i] = row
        return rows

    def choose_subgoals(self, obs: np.ndarray, learning_starts: int = 0, deterministic: bool = False) -> np.ndarray:
        """The meta-controller's sub-goal for each state of ``obs`` (env layout), in one batched forward: at random
        among the choosable sub-goals before ``learning_starts``, else epsilon-greedy (Algorithm 1 line 11)."""
        if self.num_timesteps < learning_starts and not deterministic:
            return self._random_actions(len(obs), self.action_mask(obs))
        actions, _ = DoubleDQN.predict(self, obs, deterministic=deterministic)
        return np.asarray(actions, dtype=np.int64).reshape(len(obs))

    def _env_layout(self, obs: np.ndarray) -> np.ndarray:
        """Observations in the env's layout: images that come channel first (an env wrapped in SB3's
        VecTransposeImage, as RL Zoo's evaluation envs are) are turned back to the env's channel-last frames."""
        shape = self.primitive_observation_space.shape
        if len(shape) == 3 and obs.shape[-3:] != shape and obs.shape[-3:] == (shape[2], shape[0], shape[1]):
            return np.moveaxis(obs, -3, -1)
        return obs

    def predict(
        self,
        observation: Union[np.ndarray, dict[str, np.ndarray]],
        state: Optional[tuple[np.ndarray, ...]] = None,
        episode_start: Optional[np.ndarray] = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, Optional[tuple[np.ndarray, ...]]]:
        """Primitive actions. ``state`` = (current sub-goal per env, primitive steps spent on it, then what
        ``break_cycles`` remembers: digests of the observations the sub-goal's walk was in and the actions taken there,
        digests of the observations of the episode's last choices and the sub-goals chosen there, the number of
        choices), so SB3's ``evaluate_policy`` works unchanged: a new sub-goal is chosen at an episode start, when the
        current one is reached, or when it gives up after ``max_subgoal_steps`` (a deterministic meta-controller then
        takes its best *other* sub-goal). With ``break_cycles``, the policy back in an observation takes the best
        choice, and the best action, it has not taken there yet, or (``deterministic=False``) with probability epsilon
        a random one."""
        obs = self._env_layout(np.asarray(observation))
        vectorized = obs.shape != self.primitive_observation_space.shape
        batch = obs if vectorized else obs[None]
        n_envs = batch.shape[0]
        if state is None:
            goals, steps = np.full(n_envs, -1, dtype=np.int64), np.zeros(n_envs, dtype=np.int64)
        else:
            goals, steps = np.array(state[0], dtype=np.int64), np.array(state[1], dtype=np.int64)
        walk = int(self.max_subgoal_steps)
        shapes = [(n_envs, walk)] * 2 + [(n_envs, CHOICE_MEMORY)] * 2 + [(n_envs,)]
        if state is not None and len(state) == 7 and all(np.shape(part) == shape for part, shape in zip(state[2:], shapes)):
            memory = [np.array(part, dtype=np.int64) for part in state[2:]]
        else:
            memory = [np.zeros(shape, dtype=np.int64) for shape in shapes]
        visited, taken, chosen_at, chosen_goals, n_chosen = memory
        if episode_start is not None:
            goals[np.asarray(episode_start, dtype=bool)] = -1
            n_chosen[np.asarray(episode_start, dtype=bool)] = 0
        subgoals = self.subgoals
        if not subgoals:
            actions = np.stack([self.primitive_action_space.sample() for _ in range(n_envs)])
            return (actions if vectorized else actions[0]), (goals, steps, *memory)
        remember = self.break_cycles
        here = np.array([int.from_bytes(digest[:8], "little", signed=True) for digest in observation_digests(batch)],
                        dtype=np.int64) if remember else None
        renew, reached = [], np.zeros(n_envs, dtype=bool)
        for i in range(n_envs):
            goal = goals[i]
            if goal < 0:
                renew.append(i)
                continue
            # the key training's options end on: "task solved" where the goal space reads it off the state (Fetch)
            key = self.goal_space.terminal_key(batch[i], 0.0, False)
            achieved, gave_up = option_terminal(self.goal_space, key, subgoals[goal].key, int(steps[i]),
                                                self.max_subgoal_steps)
            reached[i] = achieved and steps[i] > 0
            if gave_up or reached[i]:
                renew.append(i)
        if renew:
            renew = np.asarray(renew)
            greedy = deterministic or remember  # the rules below, then (stochastic) epsilon-random choices
            chosen, _ = DoubleDQN.predict(self, batch[renew], deterministic=greedy)
            if greedy and len(subgoals) > 1:
                # not chosen again at once: a sub-goal that just gave up (a greedy meta-controller would repeat the same
                # failing choice until the episode ends), and with break_cycles any sub-goal chosen before in this
                # observation in this episode (a greedy policy back in a state goes round the same loop of choices)
                excluded = np.zeros((len(renew), len(subgoals)), dtype=bool)
                failed = (goals[renew] >= 0) & (steps[renew] >= self.max_subgoal_steps) & ~reached[renew]
                excluded[np.flatnonzero(failed), goals[renew][failed]] = True
                if remember:
                    known = np.minimum(n_chosen[renew], CHOICE_MEMORY)
                    same = (chosen_at[renew] == here[renew, None]) & (np.arange(CHOICE_MEMORY) < known[:, None])
                    rows, columns = np.nonzero(same)
                    excluded[rows, chosen_goals[renew][rows, columns]] = True
                chosen = self._other_choices(batch[renew], chosen, excluded)
            if not deterministic and remember:  # each env's choice random with probability epsilon, as DQN explores
                explore = np.random.rand(len(renew)) < self.exploration_rate
                if explore.any():  # among the choosable sub-goals, as choose_subgoals explores (None: the valid ones)
                    chosen[explore] = self._random_actions(int(explore.sum()), self.action_mask(batch[renew][explore]))
            goals[renew] = chosen
            steps[renew] = 0
            visited[renew], taken[renew] = 0, -1  # a new walk
            if remember:
                slot = n_chosen[renew] % CHOICE_MEMORY
                chosen_at[renew, slot], chosen_goals[renew, slot] = here[renew], chosen
                n_chosen[renew] += 1
        if remember and isinstance(self.primitive_action_space, spaces.Discrete):
            # a walk back in an observation passes over the actions it took there before
            at = np.minimum(steps, walk - 1)  # steps < max_subgoal_steps here: a walk that long gave up above
            rows, columns = np.nonzero((visited == here[:, None]) & (np.arange(walk) < at[:, None]))
            avoid = np.zeros((n_envs, int(self.primitive_action_space.n)), dtype=bool)
            avoid[rows, taken[rows, columns]] = True
            actions = self.subpolicies.act(goals, batch, deterministic=deterministic, avoid=avoid)
            visited[np.arange(n_envs), at], taken[np.arange(n_envs), at] = here, actions
        else:
            actions = self.subpolicies.act(goals, batch, deterministic=deterministic)
        steps += 1
        return (actions if vectorized else actions[0]), (goals, steps, *memory)

    def _other_choices(self, batch: np.ndarray, chosen: np.ndarray, excluded: np.ndarray) -> np.ndarray:
        """The greedy meta-controller's choices ``chosen`` in the states ``batch``, where a row of ``excluded`` rules
        sub-goals out, replaced by its best choosable sub-goal not ruled out (kept where every choosable one is)."""
        rows = np.flatnonzero(excluded.any(axis=1))
        if not len(rows):
            return chosen
        with th.no_grad():
            q_values = self._q_values(self.policy.obs_to_tensor(batch[rows])[0]).cpu().numpy()[:, : excluded.shape[1]]
        mask = self.action_mask(batch[rows])
        if mask is not None:  # one row per state, or one row for all (mask_subgoals=False)
            q_values[~np.broadcast_to(mask, (len(rows), mask.shape[-1]))[:, : excluded.shape[1]]] = -np.inf
        q_values[excluded[rows]] = -np.inf
        chosen = np.array(chosen, copy=True)
        left = np.isfinite(q_values).any(axis=1)
        chosen[rows[left]] = q_values[left].argmax(axis=1)
        return chosen

