"""The preference predictor: Bradley-Terry loss (eq. 1, 2), MC-dropout confidence (eq. 4), architecture."""

import io
import itertools
import math
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from torch import nn

from sb3_hhp.oracles.base import Label
from sb3_hhp.preferences.predictor import PreferenceNetwork, PreferencePredictor

torch.set_num_threads(1)

VECTOR_SPACE = gym.spaces.Box(-10.0, 10.0, shape=(4,), dtype=np.float32)


def make_predictor(**kwargs) -> PreferencePredictor:
    params = dict(hidden_dim=32, n_masks=50, batch_size=16, buffer_size=64, seed=0)
    params.update(kwargs)
    return PreferencePredictor(params.pop("observation_space", VECTOR_SPACE), **params)


def random_obs(rng: np.random.Generator, n: int, space: gym.spaces.Box = VECTOR_SPACE) -> np.ndarray:
    if space.dtype == np.uint8:
        return rng.integers(0, 256, size=(n, *space.shape), dtype=np.uint8)
    return rng.normal(size=(n, *space.shape)).astype(space.dtype)


# ---------------------------------------------------------------- eq. 1-2: the Bradley-Terry loss


def bradley_terry_by_hand(score1: np.ndarray, score2: np.ndarray, targets: np.ndarray) -> float:
    """Eq. 1 with eq. 2 written out with math.exp / math.log, one tuple at a time."""
    losses = []
    for p1, p2, (v0, v1) in zip(score1.astype(float), score2.astype(float), targets):
        prob_first = math.exp(p1) / (math.exp(p1) + math.exp(p2))  # eq. 2
        prob_second = math.exp(p2) / (math.exp(p2) + math.exp(p1))
        losses.append(-(math.log(prob_first) * v0 + math.log(prob_second) * v1))  # eq. 1
    return float(np.mean(losses))


@pytest.mark.parametrize(
    "labels",
    [[Label.FIRST] * 3, [Label.SECOND] * 3, [Label.EQUAL] * 3, [Label.FIRST, Label.SECOND, Label.EQUAL]],
)
def test_loss_is_bradley_terry_cross_entropy(labels):
    rng = np.random.default_rng(1)
    predictor = make_predictor(dropout=0.1)
    n = len(labels)
    states, goals1, goals2 = (random_obs(rng, n) for _ in range(3))
    targets = np.array([{Label.FIRST: (1, 0), Label.SECOND: (0, 1), Label.EQUAL: (0.5, 0.5)}[v] for v in labels])

    score1 = predictor.score(states, goals1)
    score2 = predictor.score(states, goals2)
    expected = bradley_terry_by_hand(score1, score2, targets)

    predictor.network.eval()  # the network's own scores, without dropout
    with torch.no_grad():
        loss = predictor.loss(
            torch.as_tensor(states), torch.as_tensor(goals1), torch.as_tensor(goals2), torch.as_tensor(targets)
        )
    assert loss.item() == pytest.approx(expected, rel=1e-5, abs=1e-6)


def test_loss_is_stable_for_large_scores():
    # log-softmax, not log(exp / sum exp): a 1000-point score gap gives a finite loss of ~1000.
    predictor = make_predictor(dropout=0.0)
    x = np.zeros((1, 4), dtype=np.float32)

    def score_by_goal(states, goals):  # a stand-in network: the score is the goal's first entry
        return goals[:, 0].float()

    predictor.network.forward = score_by_goal
    goal_high, goal_low = np.full((1, 4), 1000.0, np.float32), np.zeros((1, 4), np.float32)
    loss = predictor.loss(*(torch.as_tensor(a) for a in (x, goal_low, goal_high)), torch.tensor([[1.0, 0.0]]))
    assert torch.isfinite(loss) and loss.item() == pytest.approx(1000.0)


def test_add_drops_incomparable_and_parses_labels():
    rng = np.random.default_rng(0)
    predictor = make_predictor()
    s, g1, g2 = random_obs(rng, 3)
    assert predictor.add(s, g1, g2, Label.INCOMPARABLE) is False
    assert predictor.add(s, g1, g2, "cant tell") is False
    assert len(predictor) == 0
    assert predictor.add(s, g1, g2, "first") is True
    assert predictor.add(s, g1, g2, 1) is True
    assert predictor.add(s, g1, g2, Label.EQUAL) is True
    assert len(predictor) == 3
    with pytest.raises(ValueError, match="Unknown preference label"):
        predictor.add(s, g1, g2, "maybe")
    with pytest.raises(ValueError, match="observation shape"):
        predictor.add(s[:2], g1, g2, Label.FIRST)


def test_buffer_is_fifo_with_capacity_buffer_size():
    predictor = make_predictor(buffer_size=3)
    goal = np.zeros(4, np.float32)
    for i in range(5):
        predictor.add(np.full(4, i, np.float32), goal, goal, Label.FIRST)
    assert len(predictor) == 3
    kept = sorted(predictor.state_dict()["buffer"]["states"][:, 0].tolist())
    assert kept == [2.0, 3.0, 4.0]  # the two oldest were pushed out


def test_training_recovers_a_ranking_of_five_goals():
    rng = np.random.default_rng(0)
    goals = rng.normal(size=(5, 4)).astype(np.float32)
    true_rank = np.array([3, 0, 4, 1, 2])  # higher is better
    predictor = make_predictor(dropout=0.1, seed=3, learning_rate=3e-3)
    assert math.isnan(predictor.train()["loss"])  # empty buffer: a no-op
    state = rng.normal(size=4).astype(np.float32)
    for i, j in itertools.permutations(range(5), 2):  # every ordered pair, labelled by the true rank
        predictor.add(state, goals[i], goals[j], Label.FIRST if true_rank[i] > true_rank[j] else Label.SECOND)
    assert len(predictor) == 20
    first = predictor.train()
    for _ in range(30):
        stats = predictor.train()
    assert stats["loss"] < first["loss"]
    assert stats["accuracy"] == 1.0

    scores = predictor.score(state, goals)  # one state paired with every goal
    assert scores.shape == (5,)
    np.testing.assert_array_equal(np.argsort(scores), np.argsort(true_rank))


def test_equal_labels_pull_scores_together():
    # With (0.5, 0.5) targets the optimum is p_hat(s, g1) = p_hat(s, g2): "equal" teaches something.
    rng = np.random.default_rng(0)
    predictor = make_predictor(dropout=0.0, seed=1, learning_rate=3e-3)
    state, goal1, goal2 = random_obs(rng, 3)
    goal1 = goal1 * 3
    gap_before = abs(float(np.diff(predictor.score(np.stack([state, state]), np.stack([goal1, goal2])))[0]))
    predictor.add(state, goal1, goal2, Label.EQUAL)
    for _ in range(50):
        predictor.train()
    gap_after = abs(float(np.diff(predictor.score(np.stack([state, state]), np.stack([goal1, goal2])))[0]))
    assert gap_after < 0.1 * gap_before


# ---------------------------------------------------------------- eq. 4: MC-dropout confidence


class QueueNetwork(nn.Module):
    """A stand-in network: row r of every call scores 10 * state[0] + the next value of a fixed sequence."""

    def __init__(self, noise: np.ndarray) -> None:
        super().__init__()
        self.noise = torch.as_tensor(noise, dtype=torch.float32)
        self.calls: list[int] = []

    def forward(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        start = sum(self.calls)
        self.calls.append(states.shape[0])
        assert self.training, "MC dropout needs dropout active"
        return 10.0 * states[:, 0] + self.noise[start : start + states.shape[0]]


@pytest.mark.parametrize("spread", ["var", "std"])
def test_confidence_is_eq4_over_batched_masks(spread):
    n_inputs, n_masks, mask_batch_size = 7, 9, 20
    rng = np.random.default_rng(0)
    noise = rng.normal(size=n_inputs * n_masks)
    predictor = make_predictor(n_masks=n_masks, mask_batch_size=mask_batch_size, spread=spread)
    predictor.network = QueueNetwork(noise)
    states = np.arange(n_inputs * 4, dtype=np.float32).reshape(n_inputs, 4)  # distinct state[0] per input
    goals = random_obs(rng, n_inputs)

    confidence = predictor.confidence(states, goals)

    # eq. 4 by hand: the predictions of input i are its n_masks consecutive rows.
    p_dj = noise.reshape(n_inputs, n_masks)
    p = p_dj.mean(axis=1, keepdims=True)
    c = ((p_dj - p) ** 2).mean(axis=1)
    expected = c if spread == "var" else np.sqrt(c)
    np.testing.assert_allclose(confidence, expected, rtol=1e-4, atol=1e-6)
    # batched, not one call per mask: ceil(63 / 20) = 4 calls of at most 20 rows
    assert predictor.network.calls == [20, 20, 20, 3]


def test_confidence_runs_the_masks_once_per_distinct_input():
    """Equal (state, goal) inputs share one spread: the masks run on each distinct input once (an episode revisits
    the same described state with the same sub-goal many times), and each copy gets the spread of its input."""
    n_masks = 5
    noise = np.random.default_rng(0).normal(size=2 * n_masks)
    predictor = make_predictor(n_masks=n_masks, mask_batch_size=100)
    predictor.network = QueueNetwork(noise)
    a, b = np.zeros(4, np.float32), np.ones(4, np.float32)
    goal = np.full(4, 2.0, np.float32)
    confidence = predictor.confidence(np.stack([a, b, a, a]), np.stack([goal] * 4))
    assert predictor.network.calls == [2 * n_masks]  # 2 distinct inputs, not 4
    p_dj = noise.reshape(2, n_masks)  # rows of input a (first seen) then of input b
    expected = np.sqrt(((p_dj - p_dj.mean(axis=1, keepdims=True)) ** 2).mean(axis=1))
    np.testing.assert_allclose(confidence, expected[[0, 1, 0, 0]], rtol=1e-4)


def test_an_input_met_again_keeps_its_spread_until_the_network_changes():
    """Eq. 4 is a property of the network and the input: measured once per version of the network, met again for free
    (late in a run, the same described states and sub-goals come back episode after episode)."""
    n_masks = 5
    noise = np.random.default_rng(0).normal(size=4 * n_masks)
    predictor = make_predictor(n_masks=n_masks, mask_batch_size=100)
    predictor.network = QueueNetwork(noise)
    a, b, c = np.zeros(4, np.float32), np.ones(4, np.float32), np.full(4, 3.0, np.float32)
    goal = np.full(4, 2.0, np.float32)
    first = predictor.confidence(np.stack([a, b]), np.stack([goal] * 2))
    again = predictor.confidence(np.stack([b, c, a]), np.stack([goal] * 3))
    assert predictor.network.calls == [2 * n_masks, n_masks]  # only c was new
    np.testing.assert_array_equal(again[[2, 0]], first)
    predictor.version += 1  # what training or loading does to the network
    predictor.confidence(a[None], goal[None])
    assert predictor.network.calls == [2 * n_masks, n_masks, n_masks]  # measured again under the new weights


def test_confidence_matches_explicit_stochastic_passes():
    rng = np.random.default_rng(0)
    predictor = make_predictor(dropout=0.2, n_masks=2000, spread="var", hidden_dim=64)
    states, goals = random_obs(rng, 3), random_obs(rng, 3)
    confidence = predictor.confidence(states, goals)

    network = predictor.network
    network.train()
    torch.manual_seed(123)
    with torch.no_grad():
        passes = torch.stack([network(torch.as_tensor(states), torch.as_tensor(goals)) for _ in range(2000)])
    network.eval()
    independent = torch.var(passes, dim=0, correction=0).numpy()  # eq. 4 with torch's variance
    np.testing.assert_allclose(confidence, independent, rtol=0.2)


def test_std_spread_is_the_square_root_of_eq4():
    rng = np.random.default_rng(0)
    states, goals = random_obs(rng, 6), random_obs(rng, 6)
    var = make_predictor(spread="var", seed=5).confidence(states, goals)
    std = make_predictor(spread="std", seed=5).confidence(states, goals)  # same seed: same masks
    assert np.all(var > 0)
    np.testing.assert_allclose(std**2, var, rtol=1e-4)


def test_confidence_without_dropout_is_zero():
    rng = np.random.default_rng(0)
    predictor = make_predictor(dropout=0.0)
    states, goals = random_obs(rng, 5), random_obs(rng, 5)
    confidence = predictor.confidence(states, goals)
    assert confidence.shape == (5,)
    assert np.all(confidence == 0.0)
    assert np.all(make_predictor(n_masks=1).confidence(states, goals) == 0.0)


@pytest.mark.parametrize("spread", ["var", "std"])
def test_confidence_is_higher_far_from_the_training_data(spread):
    rng = np.random.default_rng(0)
    predictor = make_predictor(spread=spread, n_masks=200, seed=2)
    cluster = lambda n: (0.1 * rng.normal(size=(n, 4))).astype(np.float32)  # noqa: E731
    for state, goal1, goal2 in zip(cluster(32), cluster(32), cluster(32)):
        predictor.add(state, goal1, goal2, Label.FIRST if goal1[0] > goal2[0] else Label.SECOND)
    for _ in range(10):
        predictor.train()
    near = predictor.confidence(cluster(50), cluster(50))
    far_states = (8.0 + rng.normal(size=(50, 4))).astype(np.float32)
    far_goals = (-8.0 + rng.normal(size=(50, 4))).astype(np.float32)
    far = predictor.confidence(far_states, far_goals)
    assert far.mean() > 3 * near.mean()
    assert np.median(far) > np.max(near)


def test_confidence_chunks_bound_the_rows_and_give_the_same_answer():
    rng = np.random.default_rng(0)
    states, goals = random_obs(rng, 5), random_obs(rng, 5)
    big = make_predictor(seed=4, mask_batch_size=10_000).confidence(states, goals)
    small = make_predictor(seed=4, mask_batch_size=7).confidence(states, goals)
    assert big.shape == small.shape == (5,)
    # different chunking draws different masks, but both estimate the same spread
    np.testing.assert_allclose(big, small, rtol=0.5)


# ---------------------------------------------------------------- the confidence of a question: P[g1 > g2] over masks


def test_the_answers_spread_is_that_of_eq2_averaged_over_the_masks():
    """With ``seconds``: P = the mean over masks of sigmoid(p_hat^{d_j}(s, g1) - p_hat^{d_j}(s, g2)), the two scores
    of mask j read from one call (the first goals' rows, then the seconds'), and the answer's spread sqrt(P (1 - P))
    (its variance with spread "var")."""
    n_inputs, n_masks = 3, 6
    noise = np.random.default_rng(0).normal(scale=2.0, size=2 * n_inputs * n_masks)
    states = np.arange(n_inputs * 4, dtype=np.float32).reshape(n_inputs, 4)  # distinct inputs, in their order
    goals, seconds = np.eye(4, dtype=np.float32)[:n_inputs], np.eye(4, dtype=np.float32)[1 : n_inputs + 1]
    first, second = noise[: n_inputs * n_masks], noise[n_inputs * n_masks :]
    answers = 1.0 / (1.0 + np.exp(-(first - second))).reshape(n_inputs, n_masks)  # eq. 2 under each mask
    p = answers.mean(axis=1)
    for spread, expected in (("std", np.sqrt(p * (1 - p))), ("var", p * (1 - p))):
        predictor = make_predictor(n_masks=n_masks, mask_batch_size=1_000, spread=spread)
        predictor.network = QueueNetwork(noise)
        confidence = predictor.confidence(states, goals, seconds)
        assert predictor.network.calls == [2 * n_inputs * n_masks]
        np.testing.assert_allclose(confidence, expected, rtol=1e-4)
    # the law of total variance: eq. 4 on the answers plus their mean Bernoulli variance
    np.testing.assert_allclose(p * (1 - p), answers.var(axis=1) + (answers * (1 - answers)).mean(axis=1), rtol=1e-9)


def test_a_question_shares_each_mask_between_its_two_sub_goals():
    """Mask j is the same for g1 and g2: two equal goal sets get equal scores mask by mask (independent masks would
    not), and a sub-goal compared with itself has the largest spread, 0.5."""
    rng = np.random.default_rng(0)
    predictor = make_predictor(dropout=0.2, n_masks=200)
    states, goals = torch.as_tensor(random_obs(rng, 5)), torch.as_tensor(random_obs(rng, 5))
    first, second = predictor._masked_scores(states, [goals, goals], 5)
    assert torch.equal(first, second) and first.std(dim=1).min() > 0  # dropout is on, one mask for both
    np.testing.assert_allclose(predictor.confidence(states.numpy(), goals.numpy(), goals.numpy()), 0.5, rtol=1e-6)


def test_the_answers_spread_keeps_its_scale_where_the_scores_grow():
    """Scores 100 times larger spread 100 times more (eq. 4 on p_hat), while the answer's spread stays a
    probability's, within [0, 0.5]; scores far apart make it small."""
    rng = np.random.default_rng(0)
    states, goals, seconds = random_obs(rng, 20), random_obs(rng, 20), random_obs(rng, 20)
    spreads = []
    for scale in (1.0, 100.0):
        predictor = make_predictor(dropout=0.2, n_masks=200, seed=3)
        with torch.no_grad():
            predictor.network.head[-1].weight.mul_(scale)
        spreads.append((predictor.confidence(states, goals), predictor.confidence(states, goals, seconds)))
    (score_1, pair_1), (score_100, pair_100) = spreads
    np.testing.assert_allclose(score_100, 100 * score_1, rtol=1e-3)
    assert np.all(pair_1 <= 0.5) and np.all(pair_100 <= 0.5)
    assert np.median(pair_100) < np.median(pair_1)  # the same orders, held more surely


def test_seconds_of_the_wrong_length_are_refused():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="seconds must have the length of goals"):
        make_predictor().confidence(random_obs(rng, 3), random_obs(rng, 3), random_obs(rng, 2))


def test_predictor_leaves_the_global_rng_alone_and_is_reproducible():
    rng = np.random.default_rng(0)
    states, goals = random_obs(rng, 4), random_obs(rng, 4)
    before = torch.get_rng_state()
    first = make_predictor(seed=9)
    c1 = first.confidence(states, goals)
    assert torch.equal(before, torch.get_rng_state())
    second = make_predictor(seed=9)
    np.testing.assert_array_equal(first.score(states, goals), second.score(states, goals))
    np.testing.assert_array_equal(c1, second.confidence(states, goals))


# ---------------------------------------------------------------- architecture (section 5.1)


def weight_layers_and_predecessors(network: nn.Module):
    for sequential in (m for m in network.modules() if isinstance(m, nn.Sequential)):
        children = list(sequential.children())
        for i, layer in enumerate(children):
            if isinstance(layer, (nn.Linear, nn.Conv2d)):
                yield layer, children[i - 1] if i > 0 else None


@pytest.mark.parametrize(
    "space, n_weight_layers",
    [
        (gym.spaces.Box(0, 255, (84, 84, 4), np.uint8), 9),  # 3 + 3 convs, 3 linears
        (gym.spaces.Box(-1.0, 1.0, (10,), np.float64), 7),  # 2 + 2 linears, 3 linears
        (gym.spaces.Box(0, 255, (7, 7, 3), np.uint8), 7),  # small image: mlp branches under "auto"
    ],
)
def test_dropout_before_every_weight_layer(space, n_weight_layers):
    network = PreferenceNetwork(space, hidden_dim=16, dropout=0.3)
    pairs = list(weight_layers_and_predecessors(network))
    n_all = sum(isinstance(m, (nn.Linear, nn.Conv2d)) for m in network.modules())
    assert len(pairs) == n_all == n_weight_layers
    for layer, before in pairs:
        assert isinstance(before, nn.Dropout) and before.p == 0.3, f"no Dropout before {layer}"


def test_cnn_branch_matches_the_paper_on_84x84x4():
    space = gym.spaces.Box(0, 255, (84, 84, 4), np.uint8)
    network = PreferenceNetwork(space, hidden_dim=256)
    assert network.architecture == "cnn"
    convs = [m for m in network.state_branch if isinstance(m, nn.Conv2d)]
    assert [(c.out_channels, c.kernel_size, c.stride, c.padding) for c in convs] == [
        (32, (8, 8), (4, 4), (1, 1)),
        (64, (4, 4), (2, 2), (1, 1)),
        (64, (3, 3), (1, 1), (1, 1)),
    ]
    shapes, side = [], 84
    for conv in convs:  # out = floor((in + 2 * padding - kernel) / stride) + 1
        side = (side + 2 * conv.padding[0] - conv.kernel_size[0]) // conv.stride[0] + 1
        shapes.append((conv.out_channels, side, side))
    assert shapes == [(32, 20, 20), (64, 10, 10), (64, 10, 10)]
    seen = []
    hooks = [c.register_forward_hook(lambda m, i, o: seen.append(tuple(o.shape[1:]))) for c in convs]
    obs = torch.randint(0, 256, (2, 84, 84, 4), dtype=torch.uint8)
    assert network(obs, obs).shape == (2,)
    for hook in hooks:
        hook.remove()
    assert seen == shapes
    linears = [m for m in network.head if isinstance(m, nn.Linear)]
    assert [(lin.in_features, lin.out_features) for lin in linears] == [(2 * 64 * 10 * 10, 256), (256, 256), (256, 1)]


def test_branches_have_separate_weights_and_channel_orders_agree():
    last = gym.spaces.Box(0, 255, (40, 40, 3), np.uint8)
    first = gym.spaces.Box(0, 255, (3, 40, 40), np.uint8)
    net_last = PreferenceNetwork(last, hidden_dim=16).eval()
    net_first = PreferenceNetwork(first, hidden_dim=16).eval()
    net_first.load_state_dict(net_last.state_dict())
    state_params = {p.data_ptr() for p in net_last.state_branch.parameters()}
    assert state_params.isdisjoint(p.data_ptr() for p in net_last.goal_branch.parameters())

    states = torch.randint(0, 256, (3, 40, 40, 3), dtype=torch.uint8)
    goals = torch.randint(0, 256, (3, 40, 40, 3), dtype=torch.uint8)
    with torch.no_grad():
        out_last = net_last(states, goals)
        out_first = net_first(states.permute(0, 3, 1, 2), goals.permute(0, 3, 1, 2))
        swapped = net_last(goals, states)
    torch.testing.assert_close(out_last, out_first)
    assert not torch.allclose(out_last, swapped)  # the state and goal branches differ


def test_images_are_scaled_to_unit_range():
    space = gym.spaces.Box(0, 255, (7, 7, 3), np.uint8)
    network = PreferenceNetwork(space)
    obs = torch.full((1, 7, 7, 3), 255, dtype=torch.uint8)
    assert network.preprocess(obs).max().item() == pytest.approx(1.0)


@pytest.mark.parametrize("head, low, high", [("sigmoid", 0.0, 1.0), ("relu", 0.0, math.inf)])
def test_heads(head, low, high):
    rng = np.random.default_rng(0)
    predictor = make_predictor(head=head)
    scores = predictor.score(10 * random_obs(rng, 64), 10 * random_obs(rng, 64))
    assert np.all(scores >= low) and np.all(scores <= high)


@pytest.mark.parametrize("space, head", [(VECTOR_SPACE, "linear"), (VECTOR_SPACE, "sigmoid"),
                                         (gym.spaces.Box(0, 255, (84, 84, 4), np.uint8), "linear")])
def test_score_matrix_is_score_on_every_pair(space, head):
    """The meta-controller's centred bonus reads every sub-goal of every sampled state through ``score_matrix``,
    which splits the head's first layer into state and goal halves: it must equal ``score`` pair by pair."""
    rng = np.random.default_rng(0)
    predictor = make_predictor(observation_space=space, head=head, mask_batch_size=7)  # chunks of one state
    for _ in range(20):  # trained weights, not the initial ones
        s, g1, g2 = random_obs(rng, 3, space)
        predictor.add(s, g1, g2, rng.choice([Label.FIRST, Label.SECOND]))
    predictor.train()
    states, goals = random_obs(rng, 5, space), random_obs(rng, 3, space)
    matrix = predictor.score_matrix(states, goals)
    pairs = predictor.score(np.repeat(states, 3, axis=0), np.tile(goals, (5,) + (1,) * len(space.shape)))
    assert matrix.shape == (5, 3)
    np.testing.assert_allclose(matrix, pairs.reshape(5, 3), rtol=1e-5, atol=1e-5)
    assert np.ptp(matrix) > 1e-4  # the scores differ: the comparison is not between constants


@pytest.mark.parametrize("n_labels, min_updates, expected", [(8, 0, 4), (8, 50, 50), (8, 49, 49), (40, 50, 51),
                                                             (40, 5, 12)])
def test_train_makes_at_least_min_updates_minibatch_updates(monkeypatch, n_labels, min_updates, expected):
    """``min_updates`` adds whole epochs until a call makes at least that many minibatch updates: 8 labels in minibatches
    of 16 are one update an epoch (4 epochs: 4 updates); 40 labels are 3 an epoch (4 epochs: 12; 50 asked: 17
    epochs, 51 updates)."""
    rng = np.random.default_rng(0)
    predictor = make_predictor(min_updates=min_updates)
    for _ in range(n_labels):
        s, g1, g2 = random_obs(rng, 3)
        predictor.add(s, g1, g2, Label.FIRST)
    steps = []
    step = predictor.optimizer.step
    monkeypatch.setattr(predictor.optimizer, "step", lambda *a, **k: steps.append(1) or step(*a, **k))
    predictor.train()
    assert len(steps) == expected


def test_min_updates_below_zero_is_refused():
    with pytest.raises(ValueError, match="min_updates"):
        make_predictor(min_updates=-1)


def test_min_updates_fits_labels_that_four_epochs_leave_unlearnt():
    """With a few labels, 4 epochs are 4 updates: labels against what the others teach stay unlearnt. 1,000 updates fit
    every label of the buffer."""
    rng = np.random.default_rng(3)
    goal_a, goal_b = random_obs(rng, 2)
    states = random_obs(rng, 8)
    labels = [Label.FIRST] * 6 + [Label.SECOND] * 2  # a preferred in six states, b in two
    accuracies = {}
    for min_updates in (0, 1000):
        predictor = make_predictor(min_updates=min_updates)
        for state, label in zip(states, labels):
            predictor.add(state, goal_a, goal_b, label)
            stats = predictor.train()  # once per answer, as HhP does
        accuracies[min_updates] = stats["accuracy"]
    assert accuracies[1000] == 1.0 and accuracies[0] < 1.0


def test_score_matrix_scores_each_distinct_state_once(monkeypatch):
    """A batch that repeats states (the meta-controller's samples of layout-free descriptions) is scored on its distinct
    states only, and each row gets its own state's scores: the same matrix as scoring every row."""
    rng = np.random.default_rng(1)
    predictor = make_predictor(head="linear")
    for _ in range(20):
        s, g1, g2 = random_obs(rng, 3)
        predictor.add(s, g1, g2, rng.choice([Label.FIRST, Label.SECOND]))
    predictor.train()
    distinct, goals = random_obs(rng, 4), random_obs(rng, 3)
    order = rng.integers(0, 4, 40)
    seen = []
    original = predictor.network.score_matrix
    monkeypatch.setattr(predictor.network, "score_matrix", lambda s, g: seen.append(len(s)) or original(s, g))
    matrix = predictor.score_matrix(distinct[order], goals)
    assert sum(seen) == len(np.unique(order))  # the network read each distinct state once
    expected = np.stack([predictor.score_matrix(distinct[i : i + 1], goals)[0] for i in order])
    np.testing.assert_allclose(matrix, expected, rtol=1e-6, atol=1e-7)
    assert np.ptp(matrix) > 1e-4


# ---------------------------------------------------------------- save / load, arguments


def test_state_dict_round_trip_is_exact():
    rng = np.random.default_rng(0)
    original = make_predictor(seed=1)
    for _ in range(20):
        s, g1, g2 = random_obs(rng, 3)
        original.add(s, g1, g2, rng.choice([Label.FIRST, Label.SECOND, Label.EQUAL]))
    original.train()
    buffer = io.BytesIO()
    torch.save(original.state_dict(), buffer)
    buffer.seek(0)
    restored = make_predictor(seed=77)
    restored.load_state_dict(torch.load(buffer, weights_only=True))

    assert len(restored) == len(original) == 20
    states, goals = random_obs(rng, 8), random_obs(rng, 8)
    np.testing.assert_array_equal(original.score(states, goals), restored.score(states, goals))
    np.testing.assert_array_equal(original.confidence(states, goals), restored.confidence(states, goals))
    assert original.train() == restored.train()  # same optimizer moments, minibatch order and masks
    np.testing.assert_array_equal(original.score(states, goals), restored.score(states, goals))


def test_load_state_dict_refuses_another_buffer_size():
    with pytest.raises(ValueError, match="buffer_size"):
        make_predictor(buffer_size=5).load_state_dict(make_predictor(buffer_size=6).state_dict())


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(dropout=1.0), "dropout"),
        (dict(dropout=-0.1), "dropout"),
        (dict(hidden_dim=0), "hidden_dim"),
        (dict(head="tanh"), "head"),
        (dict(architecture="transformer"), "architecture"),
        (dict(architecture="cnn"), "image"),
        (dict(n_masks=0), "n_masks"),
        (dict(batch_size=0), "batch_size"),
        (dict(n_epochs=0), "n_epochs"),
        (dict(buffer_size=0), "buffer_size"),
        (dict(mask_batch_size=0), "mask_batch_size"),
        (dict(learning_rate=0.0), "learning_rate"),
        (dict(spread="mad"), "spread"),
        (dict(observation_space=gym.spaces.Discrete(3)), "Box"),
        (dict(observation_space=gym.spaces.Box(0, 255, (8, 8, 3), np.uint8), architecture="cnn"), "too small"),
    ],
)
def test_bad_arguments_raise(kwargs, message):
    with pytest.raises(ValueError, match=message):
        make_predictor(**kwargs)


def test_bad_inputs_raise():
    rng = np.random.default_rng(0)
    predictor = make_predictor()
    with pytest.raises(ValueError, match="states"):
        predictor.score(rng.normal(size=(3, 5)), random_obs(rng, 3))
    with pytest.raises(ValueError, match="same length"):
        predictor.confidence(random_obs(rng, 3), random_obs(rng, 2))
    with pytest.raises(ValueError, match="n_epochs"):
        predictor.train(n_epochs=0)


def test_predictor_imports_before_the_oracles():
    # sb3_hhp.oracles imports this module (the synthetic oracle), so it must not need sb3_hhp.oracles at import
    code = "import sb3_hhp.preferences.predictor, sb3_hhp.oracles"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
