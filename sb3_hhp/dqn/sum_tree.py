"""Array-based binary sum tree for proportional prioritized replay (Schaul et al., 2016).

The tree holds ``capacity`` non-negative priorities in its leaves. Every internal node stores the
sum (and, in two parallel arrays, the minimum positive value and the maximum) of its children, so
the total, the extreme priorities and a draw proportional to priority all cost O(log capacity).
Updates and draws are vectorised over a whole batch: the only Python loop runs over the depth of
the tree, never over the batch.
"""

import numpy as np


class SumTree:
    """
    Binary sum tree over ``capacity`` priorities, stored in flat arrays.

    Node ``1`` is the root, node ``k`` has children ``2k`` and ``2k + 1``, and leaf ``i`` lives at
    node ``size + i`` where ``size`` is the smallest power of two ``>= capacity``. Padding leaves
    (``i >= capacity``) hold priority 0 and are never drawn.

    :param capacity: Number of leaves (stored priorities), ``>= 1``.
    """

    def __init__(self, capacity: int) -> None:
        if isinstance(capacity, bool) or not isinstance(capacity, (int, np.integer)):
            raise ValueError(f"capacity must be an int >= 1, got {capacity!r}")
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self._size = 1 << int(np.ceil(np.log2(self.capacity))) if self.capacity > 1 else 1
        self._depth = int(np.log2(self._size))
        self._sum = np.zeros(2 * self._size, dtype=np.float64)
        # Smallest *positive* priority below each node (empty leaves count as +inf), used for the
        # normalisation of importance-sampling weights.
        self._min = np.full(2 * self._size, np.inf, dtype=np.float64)
        self._max = np.zeros(2 * self._size, dtype=np.float64)

    @property
    def total(self) -> float:
        """Sum of all priorities."""
        return float(self._sum[1])

    @property
    def max_priority(self) -> float:
        """Largest stored priority (0.0 when every priority is 0)."""
        return float(self._max[1])

    @property
    def min_priority(self) -> float:
        """Smallest strictly positive stored priority (``inf`` when every priority is 0)."""
        return float(self._min[1])

    def __len__(self) -> int:
        return self.capacity

    def _check_indices(self, indices: np.ndarray) -> np.ndarray:
        indices = np.asarray(indices)
        if indices.size and not np.issubdtype(indices.dtype, np.integer):
            raise ValueError(f"indices must be integers, got dtype {indices.dtype}")
        indices = indices.astype(np.int64).reshape(-1)
        if indices.size and (indices.min() < 0 or indices.max() >= self.capacity):
            raise ValueError(f"indices must lie in [0, {self.capacity}), got min {indices.min()}, max {indices.max()}")
        return indices

    def priorities(self, indices: np.ndarray) -> np.ndarray:
        """
        Stored priorities of some leaves.

        :param indices: Leaf indices in ``[0, capacity)``, any shape.
        :return: Their priorities, float64, flattened to shape ``(len(indices),)``.
        """
        return self._sum[self._size + self._check_indices(indices)].copy()

    def __getitem__(self, indices: np.ndarray | int) -> np.ndarray | float:
        if np.ndim(indices) == 0:
            return float(self.priorities(np.array([indices]))[0])
        return self.priorities(np.asarray(indices))

    def update(self, indices: np.ndarray, priorities: np.ndarray | float) -> None:
        """
        Set the priorities of some leaves and refresh their ancestors.

        When an index appears several times, the last of its priorities wins (as in a sequence of
        single updates).

        :param indices: Leaf indices in ``[0, capacity)``, shape ``(n,)``.
        :param priorities: Finite priorities ``>= 0``, shape ``(n,)`` or a scalar for all.
        """
        indices = self._check_indices(indices)
        priorities = np.broadcast_to(np.asarray(priorities, dtype=np.float64), indices.shape).reshape(-1)
        if indices.size == 0:
            return
        if not np.all(np.isfinite(priorities)) or np.any(priorities < 0):
            bad = priorities[~(np.isfinite(priorities) & (priorities >= 0))]
            raise ValueError(f"priorities must be finite and >= 0, got {bad[:5]}")
        if indices.size == 1:
            self._update_one(int(indices[0]), float(priorities[0]))
            return
        # Keep the last occurrence of every repeated index: fancy assignment does not
        # guarantee which duplicate is written last.
        reversed_unique, first_in_reversed = np.unique(indices[::-1], return_index=True)
        priorities = priorities[::-1][first_in_reversed]
        indices = reversed_unique
        nodes = indices + self._size
        self._sum[nodes] = priorities
        self._max[nodes] = priorities
        self._min[nodes] = np.where(priorities > 0, priorities, np.inf)
        # Level by level up to the root. Repeated parents receive identical values, so duplicates
        # in `nodes` are harmless from here on.
        for _ in range(self._depth):
            nodes = nodes >> 1
            left, right = 2 * nodes, 2 * nodes + 1
            self._sum[nodes] = self._sum[left] + self._sum[right]
            self._max[nodes] = np.maximum(self._max[left], self._max[right])
            self._min[nodes] = np.minimum(self._min[left], self._min[right])

    def _update_one(self, leaf: int, priority: float) -> None:
        """Scalar path of :meth:`update` for one leaf (the per-step ``add`` of a replay buffer)."""
        node = leaf + self._size
        self._sum[node] = priority
        self._max[node] = priority
        self._min[node] = priority if priority > 0 else np.inf
        node >>= 1
        while node:
            left = 2 * node
            self._sum[node] = self._sum[left] + self._sum[left + 1]
            self._max[node] = max(self._max[left], self._max[left + 1])
            self._min[node] = min(self._min[left], self._min[left + 1])
            node >>= 1

    def sample(self, batch_size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """
        Draw leaves with probability proportional to their priority, by stratified sampling.

        The total is cut into ``batch_size`` equal segments and one value is drawn uniformly in
        each; every value is then located by a descent from the root, all values at once.

        :param batch_size: Number of draws, ``>= 1``.
        :param rng: Source of randomness.
        :return: ``(indices, priorities)``: leaf indices (int64) and their priorities (float64),
            both of shape ``(batch_size,)``.
        """
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        total = self.total
        if not total > 0:
            raise ValueError("cannot sample from a sum tree whose priorities are all 0; add or update priorities first")
        segment = total / batch_size
        values = (np.arange(batch_size) + rng.random(batch_size)) * segment
        nodes = np.ones(batch_size, dtype=np.int64)
        for _ in range(self._depth):
            left = 2 * nodes
            left_sum = self._sum[left]
            # Go right when the value lies beyond the left subtree, unless rounding pushed it past
            # an empty right subtree: then the left one (necessarily non-empty) is the answer.
            go_right = (values >= left_sum) & (self._sum[left + 1] > 0)
            values = np.where(go_right, values - left_sum, values)
            nodes = np.where(go_right, left + 1, left)
        return nodes - self._size, self._sum[nodes].copy()
