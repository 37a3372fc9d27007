"""The learners' input encoders of (H, W, C) grids of codes: the view's cells, the overview's blocks, one-hot
indicators and the places of the set ones, a first layer's product with them, and the three chained (GridInput)."""

import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_hhp.hierarchy.encoders import GridInput, Indicators, OneHotCodes, Overview, view_cells

GRID = spaces.Box(0, 10, (7, 7, 3), np.uint8)


def test_the_view_crop_picks_the_central_cells_and_inner_all_but_the_outermost_ring() -> None:
    """On a 5 x 7 grid whose cell (r, c) holds 10 r + c: view=3 is rows 1-3 and columns 2-4, view=1 the centre,
    "inner" rows 1-3 and columns 1-5; no view is the whole grid."""
    space = spaces.Box(0, 100, (5, 7, 2), np.uint8)
    grid = np.zeros((5, 7, 2), np.uint8)
    grid[..., 0] = 10 * np.arange(5)[:, None] + np.arange(7)[None, :]
    assert GridInput(space, view=3).crop(grid)[..., 0].tolist() == [[12, 13, 14], [22, 23, 24], [32, 33, 34]]
    assert GridInput(space, view=1).crop(grid[None])[..., 0].tolist() == [[[23]]]
    inner = GridInput(space, view="inner")
    assert inner.crop(grid)[..., 0].tolist() == [[11, 12, 13, 14, 15], [21, 22, 23, 24, 25], [31, 32, 33, 34, 35]]
    assert inner.space.shape == (3, 5, 2) and view_cells(space, None) is None
    np.testing.assert_array_equal(GridInput(space).crop(grid), grid)


def test_one_hot_of_a_known_grid_gives_its_indicators() -> None:
    """Codes [[2, 4], [], [1, 2]]: channel 0's codes 2 and 4, channel 1 left out, channel 2's codes 1 and 2, four
    indicators a cell, in that order; a code not listed sets none. A count n lists the codes 0 to n - 1."""
    space = spaces.Box(0, 10, (1, 4, 3), np.uint8)
    grid = np.array([[[2, 7, 1], [4, 0, 2], [5, 3, 0], [2, 9, 0]]], np.uint8)
    codes = OneHotCodes(space, [[2, 4], [], [1, 2]])
    assert codes.n_indicators == 4
    assert codes.encode(grid).tolist() == [[[1, 0, 1, 0], [0, 1, 0, 1], [0, 0, 0, 0], [1, 0, 0, 0]]]
    counted = OneHotCodes(space, [3, 0, 2])  # codes 0, 1, 2 of channel 0; 0, 1 of channel 2
    assert counted.encode(grid).tolist() == [[[0, 0, 1, 0, 1], [0, 0, 0, 0, 0], [0, 0, 0, 1, 0], [0, 0, 1, 1, 0]]]
    # the places of the set indicators in the flattened output, then the padding (its size, 16)
    assert codes.places(grid).tolist() == [0, 2, 5, 7, 12, 16, 16, 16]


@pytest.mark.parametrize("codes, match", [([2, 2], "for each of the observation's 3"), ([[2, 2], [], []], "distinct"),
                                          ([0, 0, []], "not all empty"), ([255, 255, 72], "combine")])
def test_one_hot_codes_that_cannot_be_read_are_refused(codes, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        OneHotCodes(GRID, codes)


def test_an_overview_reads_each_block_of_cells_as_its_cell_of_highest_first_code() -> None:
    """Overview(block=3) of a 7 x 7 grid: 3 x 3 blocks of 3 x 3 cells, the middle block centred on the middle cell,
    the edge padded with code 0; each block is the first cell, row by row, of the highest code in channel 0, with all
    its channels; an 8 x 8 grid is padded unevenly to 9 x 9."""
    overview = Overview(GRID, 3)
    assert overview.blocks == (3, 3) and overview.pads == ((1, 1), (1, 1)) and overview.shape == (3, 3, 3)
    grid = np.ones((7, 7, 3), np.uint8)
    grid[..., 1:] = 0
    grid[3, 3] = [5, 4, 0]  # the centre: the middle block
    grid[0, 6] = [8, 1, 0]  # a corner: the top right block (rows -1..1, columns 5..7 of the grid)
    grid[5, 0], grid[6, 1] = [4, 2, 2], [4, 3, 1]  # two of one code in the bottom left block: the first row's wins
    grid[2, 2] = [2, 5, 0]  # the middle block's corner: below the centre's 5
    got = overview(np.stack([grid, grid]))
    assert got.shape == (2, 3, 3, 3) and np.array_equal(got[0], got[1])
    expected = np.ones((3, 3, 3), np.uint8)
    expected[..., 1:] = 0
    expected[1, 1], expected[0, 2], expected[2, 0] = [5, 4, 0], [8, 1, 0], [4, 2, 2]
    assert got[0].tolist() == expected.tolist()
    empty = overview(np.zeros((7, 7, 3), np.uint8))
    assert not empty.any()  # padding and unseen cells alike: code 0
    uneven = Overview(spaces.Box(0, 10, (8, 8, 3), np.uint8), 3)
    assert uneven.blocks == (3, 3) and uneven.pads == ((0, 1), (0, 1))
    marked = np.zeros((8, 8, 3), np.uint8)
    marked[7, 7, 0] = 9  # the last cell: the bottom right block, which the padding completes
    assert uneven(marked)[..., 0].tolist() == [[0, 0, 0], [0, 0, 0], [0, 0, 9]]


def rows(weight: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """First layers ``(T, H, size)`` as the table Indicators reads, and each learner's first row: a learner's ``size``
    rows (its weights transposed), then a zero row."""
    t, h, size = weight.shape
    table = th.zeros((t, size + 1, h), dtype=weight.dtype)
    table[:, :size] = weight.transpose(1, 2)
    return table.view(-1, h), th.arange(t) * (size + 1)


def test_the_places_of_set_indicators_are_the_one_hot_inputs_and_a_first_layer_reads_them_as_the_dense_product() -> None:
    """OneHotCodes.places gives, per observation, the places of the indicators encode sets in its flattened output,
    increasing, then the input size as padding up to one place per used channel of every cell; Indicators.linear is
    each learner's x @ W.T + b at those inputs (the padding cut or not), read from the weights kept as rows, and
    Indicators.add_outer adds x.T @ g to those rows (a first layer's gradient) and leaves the zero rows zero."""
    space = spaces.Box(0, 10, (5, 4, 3), np.uint8)
    cells = np.random.default_rng(1).integers(0, 11, (2, 6, 5, 4, 3)).astype(np.uint8)
    cells[0, 0] = 0  # an observation with no listed code: no indicator set
    for listed in ([[2, 4, 5, 6], [], [1, 2]], [11, 6, 3], [[7, 3], 2, 0]):
        codes = OneHotCodes(space, listed)
        dense = codes.encode(cells).reshape(2, 6, -1)
        size = dense.shape[-1]
        places = codes.places(cells)
        assert places.shape == (2, 6, 5 * 4 * len(codes.channels)) and places.dtype == np.int16
        for row, row_places in zip(dense.reshape(12, -1), places.reshape(12, -1)):
            assert row_places.tolist() == np.flatnonzero(row).tolist() + [size] * (len(row_places) - int(row.sum()))
        generator = th.Generator().manual_seed(0)
        weight, bias = th.randn(2, 5, size, generator=generator), th.randn(2, 5, generator=generator)
        x = th.as_tensor(dense)
        expected = th.baddbmm(bias.unsqueeze(1), x, weight.transpose(1, 2))
        grad = th.randn(2, 6, 5, generator=generator)
        most = int((dense > 0).sum(-1).max())
        for kept in (places, places[..., :most]):
            inputs = Indicators(th.as_tensor(kept.astype(np.int64)), size)
            table, starts = rows(weight)
            assert table.shape == (2 * (size + 1), 5) and starts.tolist() == [0, size + 1]
            th.testing.assert_close(inputs.linear(table, starts, bias), expected, rtol=1e-5, atol=1e-5)
            th.testing.assert_close(inputs[:, 2:].linear(table, starts, bias), expected[:, 2:], rtol=1e-5, atol=1e-5)
            # the second learner's rows alone, at another place in a larger table
            wide = th.cat([th.zeros(3, 5), table[size + 1 :]])
            th.testing.assert_close(inputs[1:].linear(wide, th.tensor([3]), bias[1:]), expected[1:], rtol=1e-5, atol=1e-5)
            gradient = th.ones_like(table)
            gradient[starts + size] = 0.0
            inputs.add_outer(grad, gradient, starts)
            expected_gradient = th.bmm(x.transpose(1, 2), grad)  # (2, size, 5): x.T @ g as rows
            th.testing.assert_close(gradient.view(2, size + 1, 5)[:, :size], 1.0 + expected_gradient, rtol=1e-5, atol=1e-5)
            assert not gradient[starts + size].any()  # the padding's rows stay zero
            # learners whose rows do not lie evenly spaced (the second first, 3 rows in): added row by row
            uneven = th.ones((2 * (size + 1) + 3, 5))
            uneven_starts = th.tensor([size + 4, 0])
            uneven[uneven_starts + size] = 0.0
            inputs.add_outer(grad, uneven, uneven_starts)
            th.testing.assert_close(uneven[size + 4 : 2 * size + 4], 1.0 + expected_gradient[0], rtol=1e-5, atol=1e-5)
            th.testing.assert_close(uneven[:size], 1.0 + expected_gradient[1], rtol=1e-5, atol=1e-5)
            assert not uneven[uneven_starts + size].any() and (uneven[size + 1 : size + 4] == 1.0).all()


def test_grid_input_chains_the_view_the_overview_and_one_hot_and_says_the_space_it_gives() -> None:
    """view=3, overview=3 and one_hot on 7 x 7 grids: the 3 x 3 central cells, then the 3 x 3 blocks, 18 cells in one
    row, each as its indicators; ``space`` is the shape of what encode gives; places are OneHotCodes' of the crop."""
    grids = np.random.default_rng(0).integers(0, 11, (4, 7, 7, 3)).astype(np.uint8)
    listed = [[2, 4, 5], [], [1]]
    grid_input = GridInput(GRID, view=3, overview=3, one_hot=listed)
    cells = np.concatenate([grids[:, 2:5, 2:5].reshape(4, 1, 9, 3), Overview(GRID, 3)(grids).reshape(4, 1, 9, 3)], axis=2)
    np.testing.assert_array_equal(grid_input.crop(grids), cells)
    codes = OneHotCodes(GRID, listed)
    np.testing.assert_array_equal(grid_input.encode(grids), codes.encode(cells))
    assert grid_input.space.shape == (1, 18, 4) == grid_input.encode(grids).shape[1:]
    np.testing.assert_array_equal(grid_input.places(grids), codes.places(cells))
    with pytest.raises(ValueError, match="one_hot"):
        GridInput(GRID, view=3).places(grids)
