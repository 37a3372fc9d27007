"""What the sub-goal learners read of an observation: input encoders of ``(H, W, C)`` grids of integer codes.

MiniGrid's egocentric canvas (:class:`~sb3_hhp.goals.minigrid.MiniGridEgocentricObs`) is the grid they were made for,
but nothing here knows MiniGrid: any Box of shape ``(H, W, C)`` can be cropped to its central cells (:func:`view_cells`),
summarised by blocks (:class:`Overview`) and read as one-hot indicators of listed codes (:class:`OneHotCodes`);
:class:`GridInput` chains the three as ``subgoal_learner_kwargs`` ``view``, ``overview`` and ``one_hot`` select them,
and :class:`Indicators` is a first layer's product with one-hot inputs held as the places of their set indicators.

They live here, beside the learners of :mod:`sb3_hhp.hierarchy.learners` that read them, rather than in
:mod:`sb3_hhp.goals`, because they are no part of a goal space: a goal space says which situations are the same
sub-goal and compares their keys; these say what a network reads, and the goal space, the meta-controller and RND
keep reading the whole observation. They are plain NumPy encoders rather than SB3 features extractors because the
stacked learners apply them before the replay keeps the result: the places of the set indicators are computed once
per stored state (:meth:`SharedReplay.keep_encoded <sb3_hhp.hierarchy.replay.SharedReplay.keep_encoded>`), not in
every forward pass of every update as a ``BaseFeaturesExtractor`` would be; any other policy can use them as an
observation wrapper does, on the arrays it is given.
"""

from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch as th
from gymnasium import spaces
from torch.nn import functional as F


def grid_shape(space: spaces.Space, option: str) -> tuple[int, ...]:
    """The shape ``(H, W, C)`` of ``space``, which the learners' ``option`` reads as cells; refused otherwise."""
    shape = getattr(space, "shape", None)
    if not isinstance(space, spaces.Box) or shape is None or len(shape) != 3:
        raise ValueError(f"{option} needs (H, W, C) observations, such as MiniGrid's egocentric canvas; got {space}: "
                         f"leave {option} out (None)")
    return shape


def view_cells(space: spaces.Space, view: Optional[int | str]) -> Optional[tuple[slice, slice]]:
    """The central ``view`` x ``view`` cells of ``(H, W, C)`` observations of ``space`` (rows, columns), after checking
    that ``view`` can be read there; ``"inner"``: every cell but the outermost ring (on MiniGrid's egocentric canvas
    the ring where only the grid's border wall ever shows: :func:`~sb3_hhp.goals.minigrid.egocentric_size`); None
    without a view."""
    if view is None:
        return None
    inner = isinstance(view, str) and view == "inner"
    if not inner and (isinstance(view, bool) or not isinstance(view, (int, np.integer)) or view < 1 or view % 2 == 0):
        raise ValueError(f"view (subgoal_learner_kwargs) must be an odd integer >= 1 (cells around the centre) or "
                         f"'inner' (all but the outermost ring), got {view!r}")
    shape = grid_shape(space, "view")
    side = min(shape[0], shape[1])
    if inner:
        if side < 3:
            raise ValueError(f"view 'inner' needs observations of at least 3 x 3 cells, got {shape[0]} x {shape[1]}: "
                             "leave view out (None)")
        return slice(1, shape[0] - 1), slice(1, shape[1] - 1)
    if view > side:
        raise ValueError(f"view {view} is larger than the observation's {shape[0]} x {shape[1]} cells: use at most "
                         f"{side if side % 2 else side - 1}, or None for all")
    return tuple(slice(length // 2 - view // 2, length // 2 + view // 2 + 1) for length in shape[:2])


class Overview:
    """A coarse copy of a whole ``(H, W, C)`` observation: ``block`` x ``block`` cells, the middle block centred on the
    middle cell (MiniGrid's egocentric canvas: the agent), each block read as its most salient cell, the one with the
    highest code in the first channel (MiniGrid: the object type, whose codes rank lava, goal squares, boxes, balls,
    keys and doors above walls, floor and unseen cells), with all its channels; the edge is padded with code 0 (MiniGrid:
    unseen). A learner that reads a small view of the cells around the agent learns from it in which direction an
    object beyond that view lies.

    :param space: the observations' space (a Box of shape ``(H, W, C)``)
    :param block: the side of a block, odd, >= 3
    """

    def __init__(self, space: spaces.Space, block: Any) -> None:
        if isinstance(block, bool) or not isinstance(block, (int, np.integer)) or block < 3 or block % 2 == 0:
            raise ValueError(f"overview (subgoal_learner_kwargs) must be an odd integer >= 3 (the side of the blocks "
                             f"of cells it reads as one), got {block!r}")
        shape = grid_shape(space, "overview")
        self.block = int(block)
        # an odd number of blocks that covers each side, the middle block centred on the middle cell
        self.blocks = tuple(2 * (-(-length // self.block) // 2) + 1 for length in shape[:2])
        extra = [count * self.block - length for count, length in zip(self.blocks, shape[:2])]
        self.pads = tuple((more // 2, more - more // 2) for more in extra)
        self.shape = (*self.blocks, shape[2])

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """``(..., H, W, C)`` observations as ``(..., blocks, blocks, C)``: each block's most salient cell."""
        lead, (rows, columns), b = obs.shape[:-3], self.blocks, self.block
        padded = np.pad(obs, [(0, 0)] * len(lead) + list(self.pads) + [(0, 0)])
        cells = padded.reshape(*lead, rows, b, columns, b, obs.shape[-1])
        cells = np.moveaxis(cells, -4, -3).reshape(*lead, rows, columns, b * b, obs.shape[-1])
        salient = np.argmax(cells[..., 0], axis=-1)  # the first of the highest codes, row by row
        return np.take_along_axis(cells, salient[..., None, None], axis=-2)[..., 0, :]


class OneHotCodes:
    """Each channel ``c`` of ``(H, W, C)`` uint8 codes as one-hot indicators of the codes ``codes[c]`` (a count ``n``:
    the codes 0 to n - 1; a list: those codes, in its order; 0 or ``[]``: the channel left out), checked against
    ``space``; a code not listed reads as all zeros. :meth:`encode` looks each cell's combination of listed codes up
    in one table of their indicator rows (a few times faster than an indicator array per channel).

    :param space: the observations' space (a uint8 Box of shape ``(H, W, C)``)
    :param codes: one entry per channel
    """

    #: most combinations of listed codes (with "none listed") the lookup table holds
    MAX_COMBINATIONS = 65_536

    def __init__(self, space: spaces.Space, codes: Sequence[Any]) -> None:
        shape = getattr(space, "shape", None)
        if not isinstance(space, spaces.Box) or len(shape) != 3 or space.dtype != np.uint8:
            raise ValueError(f"one_hot (subgoal_learner_kwargs) needs (H, W, C) uint8 observations of integer codes, "
                             f"such as MiniGrid's egocentric canvas; got {space}: leave one_hot out (None)")
        channels = [self._listed(entry) for entry in codes] if isinstance(codes, (list, tuple)) else None
        if channels is None or len(channels) != shape[2] or None in channels or not any(channels):
            raise ValueError(f"one_hot (subgoal_learner_kwargs) must give, for each of the observation's {shape[2]} "
                             f"channels, its codes: a count n (codes 0 to n - 1, n from 0 to 256; 0 leaves the channel "
                             f"out) or a list of distinct codes 0-255 (MiniGrid: [11, 6, 3] for every object, colour and "
                             f"state), not all empty; got {codes!r}")
        used = [(channel, listed) for channel, listed in enumerate(channels) if listed]
        sizes = [len(listed) + 1 for _, listed in used]  # each channel's listed codes and "none listed"
        combinations = int(np.prod(sizes))
        if combinations > self.MAX_COMBINATIONS:
            raise ValueError(f"one_hot (subgoal_learner_kwargs) lists codes that combine {combinations} ways over the "
                             f"channels (at most {self.MAX_COMBINATIONS}): list fewer codes")
        self.n_indicators = sum(size - 1 for size in sizes)
        self.channels = []  # (channel, its code -> place among its listed codes, stride in the combined index)
        stride = 1
        for (channel, listed), size in zip(used, sizes):
            place = np.full(256, size - 1, dtype=np.int32)
            place[listed] = np.arange(len(listed))
            self.channels.append((channel, place, stride))
            stride *= size
        self.table = np.zeros((combinations, self.n_indicators), dtype=np.float32)  # combination -> indicators
        combination = np.arange(combinations)
        offset = 0
        for (_, place, stride), size in zip(self.channels, sizes):
            index = (combination // stride) % size
            listed_here = index < size - 1
            self.table[combination[listed_here], offset + index[listed_here]] = 1.0
            offset += size - 1

    @staticmethod
    def _listed(entry: Any) -> Optional[list[int]]:
        """The codes of one channel's entry, None where it is malformed."""
        if isinstance(entry, (int, np.integer)) and not isinstance(entry, bool) and 0 <= entry <= 256:
            return list(range(int(entry)))
        if (isinstance(entry, (list, tuple)) and len(set(entry)) == len(entry)
                and all(isinstance(code, (int, np.integer)) and not isinstance(code, bool) and 0 <= code <= 255
                        for code in entry)):
            return [int(code) for code in entry]
        return None

    def encode(self, cells: np.ndarray) -> np.ndarray:
        """``(..., H, W, C)`` uint8 codes as ``(..., H, W, n_indicators)`` float32 indicators."""
        index = None
        for channel, place, stride in self.channels:
            part = np.take(place, cells[..., channel])
            part = part * stride if stride > 1 else part
            index = part if index is None else index + part
        return np.take(self.table, index, axis=0)

    def places(self, cells: np.ndarray) -> np.ndarray:
        """Where the indicators that :meth:`encode` sets lie in its output flattened per observation (``H * W *
        n_indicators`` places): ``(..., H * W * channels used)``, the most a cell's codes can set, each observation's
        places first in increasing order, then ``H * W * n_indicators`` (padding); int16 where that fits, else int32.
        A first layer reads them as a sum of its weights' columns (:class:`Indicators`): a MiniGrid observation has a
        few dozen indicators set among ~1,000."""
        lead, (h, w) = cells.shape[:-3], cells.shape[-3:-1]
        size = h * w * self.n_indicators
        indicators = self.encode(cells).reshape(-1, size)
        rows, columns = np.nonzero(indicators)  # row by row, each row's in increasing order
        counts = np.bincount(rows, minlength=len(indicators))
        out = np.full((len(indicators), h * w * len(self.channels)), size,
                      dtype=np.int16 if size <= np.iinfo(np.int16).max else np.int32)
        out[rows, np.arange(len(rows)) - (np.cumsum(counts) - counts)[rows]] = columns
        return out.reshape(*lead, out.shape[-1])


class Indicators:
    """One-hot inputs ``(T, N, size)`` held as the places of their set indicators (``(T, N, P)``, padded with
    ``size``: :meth:`OneHotCodes.places`): what a first layer reads as sums of its weights' columns.

    Learner ``t``'s first layer is read as rows of a table ``(R, H)``: input ``i``'s weights in row ``starts[t] + i``
    and zeros in row ``starts[t] + size``, where the padding points (the stacked learners keep their first layers so,
    ``StackedDQN._layout``)."""

    def __init__(self, places: th.Tensor, size: int) -> None:
        self.places, self.size = places, size

    def __getitem__(self, index: Any) -> "Indicators":
        """The inputs ``index`` of the leading ``(T, N)`` axes."""
        return Indicators(self.places[index], self.size)

    def linear(self, table: th.Tensor, starts: th.Tensor, bias: th.Tensor) -> th.Tensor:
        """``x @ W[t].T + b[t]`` of each learner ``t`` at its inputs (``W[t]``: the rows of ``table`` from
        ``starts[t]``, ``bias`` ``(T, H)``): each output the sum of the rows at the set places, one ``embedding_bag``
        (the padding sums the zero row; its ``padding_idx`` is several times slower)."""
        places = self.places + starts.view(-1, 1, 1)
        out = F.embedding_bag(places.reshape(-1, places.shape[-1]), table, mode="sum")
        return out.view(*places.shape[:2], table.shape[1]) + bias.unsqueeze(1)

    def add_outer(self, grad: th.Tensor, table: th.Tensor, starts: th.Tensor) -> None:
        """``x[t].T @ grad[t]`` (``grad`` ``(T, N, H)``) added to learner ``t``'s rows of ``table`` (as :meth:`linear`
        reads them): the gradient of a first layer kept as rows; the zero rows stay zero. The one-hot inputs are
        written out and multiplied in one batched product, added in place where the learners' rows lie evenly spaced
        (the stacked learners' gradients), else added row by row: a sparse sum over the set places (``index_add_``)
        took ~4x as long on KeyCorridorS4R3's learners (~100 set places of 867 inputs, batch 32)."""
        t, n, width = grad.shape
        x = th.zeros((t, n, self.size + 1), dtype=grad.dtype, device=grad.device)
        x.scatter_add_(2, self.places, th.ones((), dtype=grad.dtype, device=grad.device).expand(self.places.shape))
        product = (x[..., : self.size].transpose(1, 2), grad)  # (T, size, N) @ (T, N, H): the padding's column cut
        first = int(starts[0]) if t else 0
        stride = int(starts[1] - starts[0]) if t > 1 else self.size + 1
        even = bool((starts == first + stride * th.arange(t, device=starts.device)).all())
        if table.is_contiguous() and stride >= self.size and even:  # the learners' rows as one strided view
            offset = table.storage_offset() + first * width
            table.as_strided((t, self.size, width), (stride * width, width, 1), offset).baddbmm_(*product)
        else:
            rows = starts.view(-1, 1) + th.arange(self.size, device=starts.device)
            table.index_add_(0, rows.reshape(-1), th.bmm(*product).reshape(-1, width))


class GridInput:
    """What a network reads of observations of ``space``: with ``view``, only the central cells (:func:`view_cells`);
    with ``overview``, those cells and the overview's blocks (:class:`Overview`) in one row of cells ``(1, cells, C)``;
    with ``one_hot``, every cell's codes as indicators (:class:`OneHotCodes`); with none of them, the observation as it
    is (any space).

    :param space: the observations' space
    :param view: ``subgoal_learner_kwargs['view']``: an odd number of central cells, ``"inner"`` or None
    :param overview: ``subgoal_learner_kwargs['overview']``: the side of the overview's blocks (odd, >= 3) or None
    :param one_hot: ``subgoal_learner_kwargs['one_hot']``: the codes of each channel read as indicators, or None
    :param codes: what is read in place of the observations, as a function of them (the same shape and dtype), applied
        first: the goal space's :meth:`~sb3_hhp.goals.base.GoalSpace.learner_codes`; None: the observations
    """

    codes: Optional[Callable[[np.ndarray], np.ndarray]] = None  # what an input pickled before the option reads

    def __init__(self, space: spaces.Space, view: Optional[int | str] = None, overview: Optional[int] = None,
                 one_hot: Optional[Sequence[Any]] = None,
                 codes: Optional[Callable[[np.ndarray], np.ndarray]] = None) -> None:
        self.codes = codes
        self.cells = view_cells(space, view)
        self.overview = None if overview is None else Overview(space, overview)
        self.one_hot = None if one_hot is None else OneHotCodes(space, one_hot)
        read = space  # the space of what crop() gives
        if self.cells is not None:
            read = spaces.Box(space.low[self.cells], space.high[self.cells], dtype=space.dtype)
        if self.overview is not None:  # the blocks after the cells, in one row of cells
            cells = int(np.prod(read.shape[:2])) + int(np.prod(self.overview.shape[:2]))
            read = spaces.Box(space.low.min(), space.high.max(), (1, cells, read.shape[2]), dtype=space.dtype)
        if self.one_hot is not None:
            read = spaces.Box(0.0, 1.0, (*read.shape[:2], self.one_hot.n_indicators), np.float32)
        #: the space of what :meth:`encode` gives (what a network reads)
        self.space = read

    def crop(self, obs: np.ndarray) -> np.ndarray:
        """The cells of observations ``(..., H, W, C)`` that are read: the central cells with a ``view``, else all;
        with an ``overview``, those cells and the overview's blocks in one row ``(..., 1, cells, C)``."""
        if self.codes is not None:
            obs = self.codes(obs)
        cells = obs if self.cells is None else obs[(..., *self.cells, slice(None))]
        if self.overview is None:
            return cells
        lead, channels = obs.shape[:-3], obs.shape[-1]
        return np.concatenate([cells.reshape(*lead, 1, -1, channels),
                               self.overview(obs).reshape(*lead, 1, -1, channels)], axis=-2)

    def encode(self, obs: np.ndarray, cropped: bool = False) -> np.ndarray:
        """What a network reads of observations (``cropped``: already :meth:`crop`-ped): the cells, as indicators with
        ``one_hot``."""
        obs = obs if cropped else self.crop(obs)
        return obs if self.one_hot is None else self.one_hot.encode(obs)

    def places(self, obs: np.ndarray) -> np.ndarray:
        """With ``one_hot``, the places of the indicators :meth:`encode` sets (:meth:`OneHotCodes.places`)."""
        if self.one_hot is None:
            raise ValueError("places() reads one-hot indicators: give one_hot")
        return self.one_hot.places(self.crop(obs))
