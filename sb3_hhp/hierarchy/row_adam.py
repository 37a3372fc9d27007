"""Adam for learners stacked as the rows of one tensor: each row its own step count and moments.

The stacked sub-goal learners (:class:`~sb3_hhp.hierarchy.learners.StackedDQN`) keep every sub-goal's parameters as
one row of a ``(capacity, P)`` tensor, and Adam's two moments and step counts beside it in tensors of the same rows.
An update trains some of the rows: each of them takes the Adam step of its own learner, with its own step count
(torch's Adam counts it before the update, so bias correction follows each sub-goal's own updates), and the rows
not in the batch do not move, nor do their moments or step counts.

:class:`RowAdam` is ``torch.optim.Adam`` over the rows themselves (views of the stacked tensor, which are leaf tensors
torch's optimizers take), its state for each row set to the views of that row in the stacked moments and step
counts: the stacked tensors stay what the learners save, load and grow, and torch's Adam updates them in place. A
row whose ``grad`` is None in a step is skipped, as torch's optimizers skip any such parameter. The step is torch's
fused kernel (one call for every row of the step) on CPUs and CUDA devices, its ``foreach`` implementation elsewhere.

Speed (the DoorKey-8x8 entry's learners: 12 sub-goals, ``train_rounds`` of two rounds of 6 learners of 64x64 units
reading the inner 11 x 11 x 3 cells, batch 32, one torch thread, a shared 2-core CPU at load 1-3; medians of 7
alternating runs of the old and the new code): the Adam step alone took 0.46 ms where torch's private
``_fused_adam_`` called directly took 0.36 ms (1.29x; with ``one_hot=[[2, 4, 5, 6], [], [1, 2]]`` 0.78 against 0.56 ms,
1.39x: ``Optimizer.step``'s Python, its hooks and the loop over the rows, around the same kernel), while the whole
update took 7.0 against 7.5 ms (one-hot: 10.1 against 11.4 ms), the difference within the machine's noise: the
public path costs at most a few per cent of a learner update.
"""

from typing import Sequence

import torch as th

#: added to and taken from Adam's moments: what lies below its last bit (~1e-37) becomes 0, never subnormal
_TINY = 1e-30


class RowAdam:
    """``torch.optim.Adam`` over the rows of ``params``, with the rows of ``exp_avg``, ``exp_avg_sq`` and ``steps`` as
    each row's state (views: the stacked tensors are updated in place). Build a new one when the tensors are
    reallocated (the learners grow).

    :param params: ``(capacity, P)`` the learners' parameters, a row each
    :param exp_avg: ``(capacity, P)`` Adam's first moments
    :param exp_avg_sq: ``(capacity, P)`` Adam's second moments
    :param steps: ``(capacity,)`` each row's Adam step count (float32, on the parameters' device, as torch's fused
        Adam keeps it)
    :param lr: the learning rate (> 0)
    :param betas: Adam's decay rates of the two moments
    :param eps: Adam's epsilon
    """

    def __init__(self, params: th.Tensor, exp_avg: th.Tensor, exp_avg_sq: th.Tensor, steps: th.Tensor, lr: float,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> None:
        if not (params.shape == exp_avg.shape == exp_avg_sq.shape and steps.shape == params.shape[:1]):
            raise ValueError(f"RowAdam needs moments of the parameters' shape {tuple(params.shape)} and one step count "
                             f"a row, got {tuple(exp_avg.shape)}, {tuple(exp_avg_sq.shape)} and {tuple(steps.shape)}")
        self.exp_avg, self.exp_avg_sq = exp_avg, exp_avg_sq
        self.rows = list(params.unbind(0))
        fused = params.device.type in ("cpu", "cuda")
        self.optimizer = th.optim.Adam(self.rows, lr=lr, betas=betas, eps=eps, fused=fused, foreach=None if fused else True)
        for row, first, second, step in zip(self.rows, exp_avg.unbind(0), exp_avg_sq.unbind(0), steps.unbind(0)):
            self.optimizer.state[row] = {"step": step, "exp_avg": first, "exp_avg_sq": second}

    def step(self, rows: Sequence[int], grad: th.Tensor) -> None:
        """One Adam step of the rows ``rows`` (distinct) on their gradients ``grad`` ``(len(rows), P)``; the other rows
        are left as they are."""
        if len(rows) != len(grad) or len(set(int(row) for row in rows)) != len(rows):
            raise ValueError(f"RowAdam.step needs one gradient row per distinct row, got rows {list(rows)} and "
                             f"{len(grad)} gradients")
        trained = [self.rows[int(row)] for row in rows]
        for row, row_grad in zip(trained, grad.unbind(0)):
            row.grad = row_grad
        try:
            self.optimizer.step()
        finally:
            for row in trained:
                row.grad = None

    def flush_subnormals(self) -> None:
        """Moments that decay towards 0 (inputs that are always 0) become subnormal floats, which CPUs multiply several
        times slower: adding and taking away a small normal number sends anything below its last bit to exactly 0."""
        for moment in (self.exp_avg, self.exp_avg_sq):
            moment.add_(_TINY).sub_(_TINY)
