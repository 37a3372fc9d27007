"""The synthetic oracle of section 5.1 / 5.2.3: preferences from the agent's own experience.

A network with the preference predictor's architecture, its last layer followed by a rectifier,
regresses the average undiscounted return obtained by the agent when it starts in state ``s``
aiming for sub-goal ``g``; the oracle prefers the sub-goal with the higher estimate.
"""

import copy
import math
import warnings
from collections.abc import Sequence
from typing import Any, Optional, Union

import gymnasium
import numpy as np
import torch
import torch.nn.functional as F
from stable_baselines3.common.utils import get_device

from sb3_hhp.oracles.base import Answer, Label, Oracle, Query
from sb3_hhp.preferences.predictor import PreferenceNetwork, check_int
from sb3_hhp.preferences.seeding import OwnRandomState


class SyntheticOracle(OwnRandomState, Oracle):
    """Prefer the sub-goal with the higher estimated average return (no discount) from the state.

    :meth:`observe` stores ``(s, g, R)`` triples in a FIFO buffer (``R``: the undiscounted return the
    agent obtained from ``s`` while aiming for ``g``); :meth:`train` fits the network
    ``V(s, g) ~ E[R | s, g]`` by mean squared error (call it after each episode: the paper runs 4
    epochs on a 500K buffer). :meth:`~sb3_hhp.oracles.base.Oracle.answer` compares ``V(s, g1)`` and ``V(s, g2)`` with dropout off.

    The network is :class:`~sb3_hhp.preferences.predictor.PreferenceNetwork` (same architecture and
    hyperparameters as the preference predictor) with a linear output: the paper's ReLU output (``head="relu"``)
    estimates every return >= 0, so with rewards that can be negative (Fetch's -1 per step, Pong's and Boxing's
    points lost) it would see every return as 0 and answer EQUAL.

    Randomness (initial weights, dropout, minibatch order) comes from the oracle's own generators,
    derived from ``seed``; the global torch RNG is neither read (when ``seed`` is given) nor changed.

    :param observation_space: the Box space of states and goal observations
    :param hidden_dim: units of the fully connected layers (>= 1; paper: 256)
    :param dropout: dropout probability in [0, 1) during training (paper: 0.1)
    :param learning_rate: Adam learning rate, > 0 (paper: 1e-3)
    :param batch_size: minibatch size, >= 1 (paper: 128)
    :param n_epochs: epochs over the buffer per :meth:`train` call, >= 1 (paper: 4)
    :param buffer_size: capacity of the FIFO buffer of (s, g, R), >= 1 (paper: 500K); memory grows with use
    :param equal_tolerance: estimates closer than this (in return units, >= 0) give EQUAL
    :param device: torch device ("cpu", "cuda", "auto")
    :param seed: seed of the oracle's generators; None draws one from the global torch RNG
    :param name: annotator name recorded with every answer
    :param head: output activation of the network: "linear" (default), "relu" (the paper's) or "sigmoid"
    :param architecture: "auto", "cnn" or "mlp" (see :class:`~sb3_hhp.preferences.predictor.PreferenceNetwork`)
    """

    def __init__(
        self,
        observation_space: gymnasium.spaces.Box,
        hidden_dim: int = 256,
        dropout: float = 0.1,
        learning_rate: float = 1e-3,
        batch_size: int = 128,
        n_epochs: int = 4,
        buffer_size: int = 500_000,
        equal_tolerance: float = 1e-3,
        device: Union[str, torch.device] = "cpu",
        seed: Optional[int] = None,
        name: str = "synthetic",
        head: str = "linear",
        architecture: str = "auto",
    ) -> None:
        super().__init__(name)
        for arg, value in (("batch_size", batch_size), ("n_epochs", n_epochs), ("buffer_size", buffer_size)):
            check_int(arg, value, 1)
        if not float(learning_rate) > 0:
            raise ValueError(f"learning_rate must be > 0, got {learning_rate!r}")
        if not float(equal_tolerance) >= 0:
            raise ValueError(f"equal_tolerance must be >= 0 (return units), got {equal_tolerance!r}")
        if seed is not None:
            check_int("seed", seed, 0)
        self.observation_space = observation_space
        self.learning_rate = float(learning_rate)
        self.batch_size = int(batch_size)
        self.n_epochs = int(n_epochs)
        self.buffer_size = int(buffer_size)
        self.equal_tolerance = float(equal_tolerance)
        self.device = get_device(device)

        self._init_random_state(seed)
        # PreferenceNetwork validates the space, hidden_dim, dropout, head and architecture
        with self._torch_rng():
            self.network = PreferenceNetwork(observation_space, hidden_dim, dropout, head, architecture)
        self.network.to(self.device).eval()
        self.optimizer = torch.optim.Adam(self.network.parameters(), lr=self.learning_rate)

        # FIFO buffer of (s, g, R); the arrays grow (doubling) up to buffer_size, so memory follows use
        shape, dtype = observation_space.shape, observation_space.dtype
        capacity = min(self.buffer_size, 1024)
        self._states = np.zeros((capacity, *shape), dtype=dtype)
        self._goals = np.zeros((capacity, *shape), dtype=dtype)
        self._returns = np.zeros(capacity, dtype=np.float32)
        self._pos = 0
        self._size = 0
        self._unseen = 0  # triples observed since the last train_on_new
        self._warned_negative = False

    # ------------------------------------------------------------------ randomness
    # ------------------------------------------------------------------ the buffer
    def __len__(self) -> int:
        return self._size

    def _grow(self, needed: int) -> None:
        capacity = len(self._returns)
        if needed <= capacity or capacity == self.buffer_size:
            return
        new_capacity = min(self.buffer_size, max(needed, 2 * capacity))
        # only while growing: the buffer has never wrapped yet, so _pos == _size
        for attr in ("_states", "_goals", "_returns"):
            old = getattr(self, attr)
            new = np.zeros((new_capacity, *old.shape[1:]), dtype=old.dtype)
            new[: self._size] = old[: self._size]
            setattr(self, attr, new)

    def observe(self, states: np.ndarray, goals: np.ndarray, returns: np.ndarray) -> None:
        """Store experience: the agent, in ``states[i]`` and aiming for the sub-goal observed as ``goals[i]``,
        then obtained the undiscounted return ``returns[i]`` (e.g. the sum of extrinsic rewards to the
        episode's end). The oldest triples are dropped beyond ``buffer_size``.

        :param states: raw states ``(N, *obs_shape)``
        :param goals: raw goal observations ``(N, *obs_shape)``
        :param returns: undiscounted returns (N,)
        """
        shape = tuple(self.observation_space.shape)
        states, goals = np.asarray(states), np.asarray(goals)
        returns = np.asarray(returns, dtype=np.float32).reshape(-1)
        for arg, array in (("states", states), ("goals", goals)):
            if array.shape[1:] != shape or array.shape[0] != len(returns):
                raise ValueError(
                    f"{arg} must have shape (N, {', '.join(map(str, shape))}) with N = len(returns) = {len(returns)}, "
                    f"got {array.shape}"
                )
        if not np.all(np.isfinite(returns)):
            raise ValueError("returns must be finite numbers")
        if self.network.head_name == "relu" and not self._warned_negative and np.any(returns < 0):
            self._warned_negative = True
            warnings.warn(
                "SyntheticOracle observed negative returns but its ReLU head only predicts values >= 0; "
                "use head='linear' (or shift the returns) for tasks with negative rewards"
            )
        # keep only the newest buffer_size triples of this call
        states, goals, returns = states[-self.buffer_size :], goals[-self.buffer_size :], returns[-self.buffer_size :]
        self._grow(self._size + len(returns))
        capacity = len(self._returns)
        indices = (self._pos + np.arange(len(returns))) % capacity
        self._states[indices] = states
        self._goals[indices] = goals
        self._returns[indices] = returns
        self._pos = int((self._pos + len(returns)) % capacity)
        self._size = min(self._size + len(returns), capacity)
        self._unseen = min(self._unseen + len(returns), self._size)

    # ------------------------------------------------------------------ training
    def train(self, n_epochs: Optional[int] = None) -> float:
        """Fit ``V(s, g)`` to the stored returns: minibatch Adam on the mean squared error.

        :param n_epochs: passes over the buffer (>= 1); None uses ``self.n_epochs`` (paper: 4)
        :return: the mean squared error over the minibatches of this call (nan, and nothing trained,
            when the buffer is empty)
        """
        if n_epochs is None:
            n_epochs = self.n_epochs
        check_int("n_epochs", n_epochs, 1)
        if self._size == 0:
            return math.nan
        batches = []
        for _ in range(n_epochs):
            order = self._np_rng.permutation(self._size)
            batches.extend(order[start : start + self.batch_size] for start in range(0, self._size, self.batch_size))
        return self._fit(batches)

    def train_on_new(self) -> float:
        """``n_epochs`` passes' worth of minibatches over the triples observed since the last call, each minibatch drawn
        at random from the whole buffer: a call costs what arrived, not the buffer's size (training calls it after
        every episode, where :meth:`train`'s passes over the whole buffer would cost more with every episode).

        :return: the mean squared error over the minibatches (nan, and nothing trained, when nothing new arrived)
        """
        new, self._unseen = self._unseen, 0
        if new == 0:
            return math.nan
        n_batches = math.ceil(self.n_epochs * new / self.batch_size)
        size = min(self.batch_size, self._size)
        return self._fit([self._np_rng.choice(self._size, size=size, replace=False) for _ in range(n_batches)])

    def _fit(self, batches: Sequence[np.ndarray]) -> float:
        """Adam steps on the mean squared error, one per minibatch of buffer indices; their mean loss."""
        total_loss, total_count = 0.0, 0
        self.network.train()
        try:
            with self._torch_rng():
                for indices in batches:
                    states = torch.as_tensor(self._states[indices], device=self.device)
                    goals = torch.as_tensor(self._goals[indices], device=self.device)
                    targets = torch.as_tensor(self._returns[indices], device=self.device)
                    loss = F.mse_loss(self.network(states, goals), targets)
                    self.optimizer.zero_grad()
                    loss.backward()
                    self.optimizer.step()
                    total_loss += loss.item() * len(indices)
                    total_count += len(indices)
        finally:
            self.network.eval()
        return total_loss / total_count

    # ------------------------------------------------------------------ answering
    def predict(self, states: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Estimated average undiscounted returns ``V(s, g)`` without dropout.

        :param states: raw states ``(N, *obs_shape)``
        :param goals: raw goal observations ``(N, *obs_shape)``
        :return: estimates, shape (N,)
        """
        self.network.eval()
        with torch.no_grad():
            states_t = torch.as_tensor(np.asarray(states), device=self.device)
            goals_t = torch.as_tensor(np.asarray(goals), device=self.device)
            return self.network(states_t, goals_t).cpu().numpy()

    def _compare(self, value1: float, value2: float) -> Label:
        if abs(value1 - value2) <= self.equal_tolerance:
            return Label.EQUAL
        return Label.FIRST if value1 > value2 else Label.SECOND

    def answer(self, query: Query) -> Label:
        states = np.stack([query.state, query.state])
        values = self.predict(states, np.stack([query.goal1_obs, query.goal2_obs]))
        return self._compare(float(values[0]), float(values[1]))

    def submit(self, queries: Sequence[Query]) -> None:
        """Answer all queries at once, with one batched forward pass."""
        if len(queries) == 0:
            return
        states = np.stack([query.state for query in queries])
        values1 = self.predict(states, np.stack([query.goal1_obs for query in queries]))
        values2 = self.predict(states, np.stack([query.goal2_obs for query in queries]))
        for query, value1, value2 in zip(queries, values1, values2):
            self._ready.append(Answer(query.query_id, self._compare(float(value1), float(value2)), self.name))

    # ------------------------------------------------------------------ save / load
    def state_dict(self, include_buffer: bool = False) -> dict[str, Any]:
        """Network, optimizer and generator states; the (possibly large) buffer only if asked.

        :param include_buffer: also save the stored (s, g, R) triples (as SB3 saves replay buffers
            only on request)
        """
        state: dict[str, Any] = {
            "network": copy.deepcopy(self.network.state_dict()),
            "optimizer": copy.deepcopy(self.optimizer.state_dict()),
            **self._random_state_dict(),
        }
        if include_buffer:
            # in storage order, with the write position, so that a resumed run draws the same minibatches
            state["buffer"] = {
                "states": torch.from_numpy(self._states[: self._size].copy()),
                "goals": torch.from_numpy(self._goals[: self._size].copy()),
                "returns": torch.from_numpy(self._returns[: self._size].copy()),
                "pos": self._pos,
                "buffer_size": self.buffer_size,
            }
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` saved (same observation space and network sizes)."""
        if "buffer" in state and int(state["buffer"]["buffer_size"]) != self.buffer_size:
            raise ValueError(
                f"The saved buffer was made with buffer_size={state['buffer']['buffer_size']}, this oracle has "
                f"{self.buffer_size}: build it with the same buffer_size"
            )
        self.network.load_state_dict(state["network"])
        self.optimizer.load_state_dict(state["optimizer"])
        self._load_random_state_dict(state)
        if "buffer" in state:
            buffer = state["buffer"]
            size = len(buffer["returns"])
            capacity = max(size, min(self.buffer_size, 1024))
            for attr, key in (("_states", "states"), ("_goals", "goals"), ("_returns", "returns")):
                old = getattr(self, attr)
                new = np.zeros((capacity, *old.shape[1:]), dtype=old.dtype)
                new[:size] = buffer[key].numpy()
                setattr(self, attr, new)
            self._size, self._pos = size, int(buffer["pos"])
        self.network.eval()
