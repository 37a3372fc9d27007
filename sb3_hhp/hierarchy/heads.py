"""The sub-goal learners as heads of one network: a shared trunk, a linear head per sub-goal, one batch for all.

:class:`GoalHeadsQNetwork` is ``Q(s, g, a)`` for every sub-goal at once (as h-DQN's controller is one network for
every goal); :class:`SharedHeadsDQN` trains it with :class:`~sb3_hhp.hierarchy.learners.StackedDQN`'s interface
(``subgoal_learner_kwargs=dict(kind="heads")``), one prioritized batch relabelled for every sub-goal, one ``torch.optim.Adam`` step.
"""

from collections.abc import Hashable
from typing import Any, Optional

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import preprocess_obs
from stable_baselines3.common.torch_layers import create_mlp
from stable_baselines3.dqn.policies import DQNPolicy
from torch.nn import functional as F

from sb3_hhp.hierarchy.learners import StackedDQN
from sb3_hhp.hierarchy.learner_kwargs import check_learners_state


class GoalHeadsQNetwork(th.nn.Module):
    """``Q(s, g, a)`` for every sub-goal ``g``: SB3's features extractor and MLP trunk, shared, then one linear
    head per sub-goal (as h-DQN's controller is one network for every goal). Heads are stored stacked,
    ``capacity`` of them; ``grow`` makes room for more.

    :param features_extractor: SB3's features extractor (FlattenExtractor, NatureCNN, ...)
    :param net_arch: hidden layer sizes of the trunk
    :param activation_fn: the trunk's activation
    :param n_actions: primitive actions
    :param capacity: heads allocated
    :param observation_space: the space the network reads (for SB3's preprocessing)
    :param normalize_images: divide image observations by 255
    """

    def __init__(self, features_extractor: th.nn.Module, net_arch: list[int], activation_fn: type[th.nn.Module],
                 n_actions: int, capacity: int, observation_space: spaces.Space, normalize_images: bool = True) -> None:
        super().__init__()
        self.features_extractor = features_extractor
        self.trunk = th.nn.Sequential(*create_mlp(features_extractor.features_dim, -1, list(net_arch), activation_fn))
        self.hidden_dim = net_arch[-1] if net_arch else features_extractor.features_dim
        self.n_actions = n_actions
        self.observation_space = observation_space
        self.normalize_images = normalize_images
        self.head_weight = th.nn.Parameter(th.zeros(capacity, n_actions, self.hidden_dim))
        self.head_bias = th.nn.Parameter(th.zeros(capacity, n_actions))

    @property
    def capacity(self) -> int:
        return self.head_weight.shape[0]

    def init_head(self, goal: int, generator: Optional[th.Generator] = None) -> None:
        """A fresh head for sub-goal ``goal`` (nn.Linear's default initialisation)."""
        bound = 1.0 / np.sqrt(self.hidden_dim)
        with th.no_grad():
            self.head_weight[goal] = (th.rand(self.head_weight.shape[1:], generator=generator) * 2 - 1) * bound
            self.head_bias[goal] = (th.rand(self.head_bias.shape[1:], generator=generator) * 2 - 1) * bound

    def grow(self, capacity: int) -> None:
        with th.no_grad():
            weight = th.zeros(capacity, *self.head_weight.shape[1:], device=self.head_weight.device)
            bias = th.zeros(capacity, self.n_actions, device=self.head_bias.device)
            weight[: self.capacity], bias[: self.capacity] = self.head_weight, self.head_bias
        self.head_weight, self.head_bias = th.nn.Parameter(weight), th.nn.Parameter(bias)

    def features(self, obs: th.Tensor) -> th.Tensor:
        obs = preprocess_obs(obs, self.observation_space, normalize_images=self.normalize_images)
        return self.trunk(self.features_extractor(obs))

    def forward(self, obs: th.Tensor, goals: Optional[th.Tensor] = None) -> th.Tensor:
        """Q-values ``(N, capacity, A)`` of every head, or ``(N, A)`` of head ``goals[i]`` for ``obs[i]``."""
        features = self.features(obs)
        if goals is None:
            return th.einsum("nh,cah->nca", features, self.head_weight) + self.head_bias
        return th.einsum("nh,nah->na", features, self.head_weight[goals]) + self.head_bias[goals]


class SharedHeadsDQN(StackedDQN):
    """Every sub-goal's Double DQN learner as one head of a :class:`GoalHeadsQNetwork`, over one shared replay.

    One update draws one prioritized batch of primitive transitions and relabels it for every sub-goal (eq. 5, 6
    and each sub-goal's n-step return, when drawn): the trunk runs once on the batch whatever the number of
    sub-goals K, so the cost of a primitive step barely grows with K. A transition's priority is its largest
    absolute TD error over the sub-goals. ``train_freq``, ``gradient_steps`` and ``target_update_interval``
    count primitive steps (of all envs); ``train_shared`` has no effect (every head learns at every update).
    Arguments as :class:`~sb3_hhp.hierarchy.learners.StackedDQN`.
    """

    _shared_priorities = True
    _encoded_replay = False  # its update reads the observations through the trunk (:meth:`train`)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        if kwargs.get("carry_relabel"):
            raise ValueError("carry_relabel (subgoal_learner_kwargs) changes each sub-goal's own batch: it needs "
                             "subgoal_learner_kwargs kind='stacked' (the heads learner draws one batch for all)")
        super().__init__(*args, **kwargs)
        policy = self._make_policy()
        policy_kwargs = {k: v for k, v in dict(self.kwargs["policy_kwargs"] or {}).items() if k != "optimizer_kwargs"}
        net_arch = policy_kwargs.get("net_arch", [64, 64])
        self.network = GoalHeadsQNetwork(policy.q_net.features_extractor, net_arch, policy.q_net.activation_fn,
                                         int(self.action_space.n), 4, policy.q_net.observation_space,
                                         policy.q_net.normalize_images).to(self.device)
        self.target_network = GoalHeadsQNetwork(policy.q_net_target.features_extractor, net_arch,
                                                policy.q_net.activation_fn, int(self.action_space.n), 4,
                                                policy.q_net.observation_space, policy.q_net.normalize_images).to(self.device)
        self.target_network.load_state_dict(self.network.state_dict())
        self.optimizer = th.optim.Adam(self.network.parameters(), lr=self.lr)
        self.n_train_calls = 0

    def add(self, goal_key: Hashable) -> int:
        goal = len(self)
        if goal >= self.network.capacity:
            self._grow_heads(2 * self.network.capacity)
        generator = th.Generator().manual_seed((self.seed or 0) * 7919 + goal) if self.seed is not None else None
        self.network.init_head(goal, generator)
        with th.no_grad():
            self.target_network.head_weight[goal] = self.network.head_weight[goal]
            self.target_network.head_bias[goal] = self.network.head_bias[goal]
        return self._add_counters(goal_key)

    def _grow_heads(self, capacity: int) -> None:
        """More heads; Adam's moments of the old heads are kept, the new heads' start at zero."""
        old = {name: param for name, param in self.network.named_parameters()}
        old_state = {name: self.optimizer.state.get(param, {}) for name, param in old.items()}
        self.network.grow(capacity)
        self.target_network.grow(capacity)
        self.optimizer = th.optim.Adam(self.network.parameters(), lr=self.lr)
        for name, param in self.network.named_parameters():
            state = old_state[name]
            if not state:
                continue
            if name.startswith("head_"):
                state = dict(state)
                for moment in ("exp_avg", "exp_avg_sq"):
                    grown = th.zeros_like(param)
                    grown[: state[moment].shape[0]] = state[moment]
                    state[moment] = grown
            self.optimizer.state[param] = state

    def q_values(self, goals: np.ndarray, obs: np.ndarray) -> th.Tensor:
        with th.no_grad():
            return self.network(self._tensor(np.asarray(obs)), th.as_tensor(np.asarray(goals, dtype=np.int64), device=self.device))

    def observe(self, obs: np.ndarray, actions: np.ndarray, next_obs: np.ndarray, keys: list, terminated: np.ndarray,
                truncated: np.ndarray, gave_up: np.ndarray, acting: np.ndarray, intrinsic: np.ndarray) -> None:
        replay = self.replay
        key_ids = np.array([replay.key_id(key) for key in keys], dtype=np.int32)
        acting = np.asarray(acting, dtype=np.int64)
        replay.add(obs, actions, next_obs, key_ids, terminated, truncated, gave_up, acting, intrinsic)
        np.add.at(self.own_steps, acting[acting >= 0], 1)
        before = int(self.ticks[0]) if len(self) else 0
        self.ticks += len(acting)  # every head counts every primitive step
        now = before + len(acting)
        rounds = (now // self.train_freq - before // self.train_freq) * self.gradient_steps
        ready = replay.size() * replay.n_envs >= max(self.learning_starts, self.batch_size)
        if len(self) and ready:
            for _ in range(rounds):
                self.train(np.arange(len(self)))
        if now // self.target_update_interval > before // self.target_update_interval:
            self.target_network.load_state_dict(self.network.state_dict())

    def train(self, goals: np.ndarray) -> float:
        """One gradient step of the network for every sub-goal of ``goals`` on one shared, relabelled batch."""
        replay, n_steps, batch_size = self.replay, self.replay.n_steps, self.batch_size
        goals = np.asarray(goals, dtype=np.int64)
        leaves, probabilities = replay.trees.sample(np.array([0]), batch_size, replay._rng)
        leaves, weights = leaves[0], replay.importance_weights(probabilities[0])
        rows, cols = np.divmod(leaves, replay.n_envs)
        grid = (len(goals), batch_size)
        row_grid, col_grid = np.broadcast_to(rows, grid), np.broadcast_to(cols, grid)
        goal_grid = np.broadcast_to(goals[:, None], grid)
        (returns, last, discounts, dones), behaviour = replay.n_step_returns(row_grid, col_grid, goal_grid,
                                                                             behaviour=replay.lower_bound)
        closings = [((last - rows) % replay.capacity, returns, discounts, dones)]
        if behaviour is not None:
            b_returns, b_last, b_discounts, b_dones = behaviour
            closings.append(((b_last - rows) % replay.capacity, b_returns, b_discounts, b_dones))
        # the states closing the returns lie among the n transitions after each drawn one: the network runs once
        # on the distinct ones, whatever the number of sub-goals
        pairs = np.concatenate([np.arange(batch_size) * n_steps + offset for offset, *_ in closings], axis=0)
        distinct, inverse = np.unique(pairs, return_inverse=True)
        inverse = inverse.reshape(len(closings), *grid)
        draw, offset = np.divmod(distinct, n_steps)
        next_obs_np = replay.next_observations[(rows[draw] + offset) % replay.capacity, cols[draw]]
        next_obs = self._tensor(next_obs_np)
        as_t = lambda x: th.as_tensor(x, device=self.device)  # noqa: E731
        heads = as_t(goals)[:, None]
        with th.no_grad():
            next_q_target = self.target_network(next_obs)  # (U, capacity, A)
            next_q_online = self.network(next_obs) if self.double_q else next_q_target
            allowed = self._allowed(next_obs_np)
            if allowed is not None:  # the max of the target over the actions a learner may take there
                next_q_online = next_q_online.masked_fill(~allowed[:, None, :], -th.inf)  # (U, capacity, A)
            y = None
            for k, (_, k_returns, k_discounts, k_dones) in enumerate(closings):
                index = as_t(inverse[k])
                online, target = next_q_online[index, heads], next_q_target[index, heads]  # (T, B, A)
                next_q = target.gather(-1, online.argmax(-1, keepdim=True))[..., 0]
                y_k = as_t(k_returns) + as_t(k_discounts) * (1 - as_t(k_dones)) * next_q
                y = y_k if y is None else th.maximum(y, y_k)  # the behaviour's return is a lower bound
            y = self._in_range(y)
        q_all = self.network(self._tensor(replay.observations[rows, cols]))  # (B, capacity, A)
        actions = as_t(replay.actions[rows, cols].reshape(batch_size).astype(np.int64))
        q = q_all[:, as_t(goals), :].gather(-1, actions[:, None, None].expand(-1, len(goals), 1))[..., 0].T  # (T, B)
        mask = as_t(np.ones(grid, dtype=np.float32) if replay.share_experience
                    else (replay.acting[rows, cols][None, :] == goals[:, None]).astype(np.float32))
        elementwise = F.smooth_l1_loss(q, y, reduction="none") * as_t(weights)[None, :] * mask
        loss = (elementwise.sum(dim=1) / mask.sum(dim=1).clamp(min=1)).sum()  # each sub-goal's own mean, summed
        self.optimizer.zero_grad()
        loss.backward()
        th.nn.utils.clip_grad_norm_(self.network.parameters(), self.max_grad_norm)
        self.optimizer.step()
        td_errors = ((y - q).detach().abs() * mask).amax(dim=0).cpu().numpy()
        replay.update_priorities(np.array([0]), leaves[None, :], td_errors[None, :])
        self.n_updates[goals] += 1
        self.n_train_calls += 1
        self.last_loss = float(loss.detach()) / max(1, len(goals))
        return self.last_loss

    def policy(self, goal: int) -> DQNPolicy:
        """Sub-goal ``goal``'s learner as an SB3 ``DQNPolicy``: the shared trunk and its own head as the last layer, on the
        learners' device."""
        policy = self._make_policy()
        for q_net, network in ((policy.q_net, self.network), (policy.q_net_target, self.target_network)):
            state = {f"features_extractor.{k}": v for k, v in network.features_extractor.state_dict().items()}
            state.update({f"q_net.{k}": v for k, v in network.trunk.state_dict().items()})
            state[f"q_net.{len(network.trunk)}.weight"] = network.head_weight[goal].detach().clone()
            state[f"q_net.{len(network.trunk)}.bias"] = network.head_bias[goal].detach().clone()
            q_net.load_state_dict(state)
        return policy

    def state_dict(self) -> dict[str, Any]:
        return {
            "format": "sb3_hhp.SharedHeadsDQN", "capacity": self.network.capacity,
            "network": self.network.state_dict(), "target_network": self.target_network.state_dict(),
            "optimizer": self.optimizer.state_dict(), **self._counters(),
        }

    def load_state_dict(self, state: Any) -> None:
        check_learners_state(state, "SharedHeadsDQN", "heads")
        for key in state["goal_keys"]:
            self.add(key)
        if self.network.capacity < state["capacity"]:
            self._grow_heads(state["capacity"])
        try:
            self.network.load_state_dict(state["network"])
            self.target_network.load_state_dict(state["target_network"])
        except RuntimeError as error:
            raise ValueError("The saved sub-goal learners have another network than subpolicy_kwargs builds: load the "
                             f"model with the subpolicy_kwargs it was trained with ({error})") from error
        self.optimizer.load_state_dict(state["optimizer"])
        self._load_counters(state)
