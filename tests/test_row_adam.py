"""Adam over the rows of stacked tensors (RowAdam): each row's step is torch.optim.Adam's on that row alone, with its
own step count and moments, and the rows not in a step do not move."""

import pytest
import torch as th

from sb3_hhp.hierarchy.row_adam import RowAdam


def stacked(rows: int, size: int, seed: int = 0) -> tuple[th.Tensor, ...]:
    generator = th.Generator().manual_seed(seed)
    params = th.randn(rows, size, generator=generator)
    return params, th.zeros_like(params), th.zeros_like(params), th.zeros(rows)


def test_a_rows_update_equals_torch_adam_on_that_row_and_the_other_rows_stay() -> None:
    """Row 1 trained in steps 1, 3 and 4, rows 0 and 2 in others: row 1 ends where torch.optim.Adam takes a parameter of
    its values after three steps on the same gradients (its bias correction counts its own steps), to 1e-6; row 3,
    never in a step, keeps its values, moments and step count exactly."""
    params, exp_avg, exp_avg_sq, steps = stacked(4, 50)
    reference = th.nn.Parameter(params[1].clone())
    optimizer = th.optim.Adam([reference], lr=0.01, betas=(0.9, 0.999), eps=1e-8)
    untouched = params[3].clone()
    adam = RowAdam(params, exp_avg, exp_avg_sq, steps, lr=0.01)
    generator = th.Generator().manual_seed(1)
    plan = [[1], [0, 2], [1, 2], [0, 1]]
    for rows in plan:
        grad = th.randn(len(rows), 50, generator=generator)
        adam.step(rows, grad)
        if 1 in rows:
            reference.grad = grad[rows.index(1)].clone()
            optimizer.step()
    th.testing.assert_close(params[1], reference.detach(), rtol=0, atol=1e-6)
    state = optimizer.state[reference]
    th.testing.assert_close(exp_avg[1], state["exp_avg"], rtol=0, atol=1e-6)
    th.testing.assert_close(exp_avg_sq[1], state["exp_avg_sq"], rtol=0, atol=1e-9)
    assert steps.tolist() == [2.0, 3.0, 2.0, 0.0]  # each row's own count
    assert th.equal(params[3], untouched) and not exp_avg[3].any() and not exp_avg_sq[3].any()
    assert all(row.grad is None for row in adam.rows)  # no gradient left to a later step


def test_rows_are_the_stacked_tensors_and_bad_steps_are_refused() -> None:
    params, exp_avg, exp_avg_sq, steps = stacked(2, 5)
    adam = RowAdam(params, exp_avg, exp_avg_sq, steps, lr=0.1)
    adam.step([0], th.ones(1, 5))
    assert exp_avg[0].abs().sum() > 0 and steps[0] == 1  # updated in place, in the stacked tensors
    tiny = th.full((2, 5), 1e-39)  # subnormal in float32
    exp_avg.copy_(tiny)
    adam.flush_subnormals()
    assert not exp_avg.any()
    with pytest.raises(ValueError, match="distinct"):
        adam.step([0, 0], th.ones(2, 5))
    with pytest.raises(ValueError, match="one step count a row"):
        RowAdam(params, exp_avg, exp_avg_sq, th.zeros(3), lr=0.1)
