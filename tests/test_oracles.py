import io
import math
import os
import threading
import time

import cv2
import numpy as np
import pytest

from sb3_hhp.oracles.base import Answer, Label, Oracle, Query
from sb3_hhp.oracles.experts import MultiExpertOracle
from sb3_hhp.oracles.fetch import FetchScriptedOracle
from sb3_hhp.oracles.noisy import NoisyOracle
from sb3_hhp.oracles.synthetic import SyntheticOracle
from sb3_hhp.oracles.terminal import TerminalOracle, ansi_preview, parse_reply


class ConstantOracle(Oracle):
    """Always gives the same label."""

    def __init__(self, label: Label, name: str = "constant") -> None:
        super().__init__(name)
        self.label = label

    def answer(self, query: Query) -> Label:
        return self.label


class LaterOracle(Oracle):
    """Asynchronous: answers only when told to, like a person."""

    def __init__(self, label: Label, name: str = "later") -> None:
        super().__init__(name)
        self.label = label
        self.waiting: list[Query] = []

    def answer(self, query: Query) -> Label:
        return self.label

    def submit(self, queries):
        self.waiting.extend(queries)

    def release(self) -> None:
        self._ready.extend(Answer(q.query_id, self.label, self.name) for q in self.waiting)
        self.waiting = []

    def pending(self) -> int:
        return len(self.waiting)


def make_query(i: int = 0, **kwargs) -> Query:
    return Query(state=np.zeros(2), goal1=1, goal2=2, goal1_obs=np.ones(2), goal2_obs=-np.ones(2), query_id=f"q{i}", **kwargs)


def wait_for(predicate, timeout: float = 5.0) -> bool:
    end = time.time() + timeout
    while time.time() < end:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


# --- NoisyOracle ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("rho", [0.0, 0.1, 0.2, 1.0])
def test_noisy_flip_rate_matches_rho(rho):
    n = 5000
    oracle = NoisyOracle(ConstantOracle(Label.FIRST), rho, seed=0)
    oracle.submit([make_query(i) for i in range(n)])
    answers = oracle.collect()
    assert len(answers) == n
    flipped = np.array([answer.label == Label.SECOND for answer in answers])
    assert all(answer.label in (Label.FIRST, Label.SECOND) for answer in answers)
    # binomial: 4 standard deviations (0 for rho in {0, 1}, where the rate must be exact)
    assert abs(flipped.mean() - rho) <= 4 * np.sqrt(rho * (1 - rho) / n) + 1e-12
    assert oracle.n_corrupted == flipped.sum() and oracle.n_answers == n
    assert answers[0].annotator == "noisy(constant)"


def test_noisy_second_equal_and_incomparable():
    n = 4000
    second = NoisyOracle(ConstantOracle(Label.SECOND), 1.0, seed=1)
    assert all(second.answer(make_query(i)) == Label.FIRST for i in range(100))
    # EQUAL: a wrong answer (rate rho) prefers either side with probability 1/2
    equal = NoisyOracle(ConstantOracle(Label.EQUAL), 0.2, seed=2)
    labels = np.array([equal.answer(make_query(i)) for i in range(n)])
    assert set(labels.tolist()) <= {Label.EQUAL, Label.FIRST, Label.SECOND}
    assert abs((labels != Label.EQUAL).mean() - 0.2) <= 4 * np.sqrt(0.2 * 0.8 / n)
    assert abs((labels == Label.FIRST).mean() - 0.1) <= 4 * np.sqrt(0.1 * 0.9 / n)
    # INCOMPARABLE is never corrupted
    incomparable = NoisyOracle(ConstantOracle(Label.INCOMPARABLE), 1.0, seed=3)
    assert all(incomparable.answer(make_query(i)) == Label.INCOMPARABLE for i in range(100))


def test_noisy_wraps_asynchronous_oracle():
    inner = LaterOracle(Label.FIRST, name="person")
    oracle = NoisyOracle(inner, 1.0, seed=0, name="noisy-person")
    oracle.submit([make_query(i) for i in range(3)])
    assert oracle.pending() == 3 and oracle.collect() == []
    inner.release()
    answers = oracle.collect()
    assert [a.query_id for a in answers] == ["q0", "q1", "q2"]
    assert all(a.label == Label.SECOND and a.annotator == "noisy-person" for a in answers)
    assert oracle.pending() == 0


def test_noisy_is_reproducible():
    first = NoisyOracle(ConstantOracle(Label.FIRST), 0.5, seed=7)
    second = NoisyOracle(ConstantOracle(Label.FIRST), 0.5, seed=7)
    assert [first.answer(make_query(i)) for i in range(50)] == [second.answer(make_query(i)) for i in range(50)]


@pytest.mark.parametrize("rho", [-0.1, 1.5])
def test_noisy_bad_rho(rho):
    with pytest.raises(ValueError, match="rho"):
        NoisyOracle(ConstantOracle(Label.FIRST), rho)


def test_noisy_needs_an_oracle():
    with pytest.raises(ValueError, match="Oracle"):
        NoisyOracle("scripted", 0.1)  # type: ignore[arg-type]


# --- MultiExpertOracle ----------------------------------------------------------------------------------


def three_experts() -> list[Oracle]:
    return [ConstantOracle(Label.FIRST, "ann"), ConstantOracle(Label.SECOND, "bob"), ConstantOracle(Label.EQUAL, "cid")]


def test_experts_per_query_uses_all_and_records_names():
    oracle = MultiExpertOracle(three_experts(), assignment="query", seed=0)
    n = 300
    oracle.submit([make_query(i) for i in range(n)])
    answers = oracle.collect()
    assert len(answers) == n
    expected_label = {"ann": Label.FIRST, "bob": Label.SECOND, "cid": Label.EQUAL}
    names = [answer.annotator for answer in answers]
    assert set(names) == {"ann", "bob", "cid"}
    for name in ("ann", "bob", "cid"):
        assert 60 <= names.count(name) <= 140  # about n / 3 each
    for answer in answers:
        assert answer.label == expected_label[answer.annotator]
        assert oracle.oracles[oracle.assigned[answer.query_id]].name == answer.annotator


def test_experts_per_run_uses_one():
    chosen = set()
    for seed in range(12):
        oracle = MultiExpertOracle(three_experts(), assignment="run", seed=seed)
        oracle.submit([make_query(i) for i in range(50)])
        names = {answer.annotator for answer in oracle.collect()}
        assert len(names) == 1
        assert names == {oracle.oracles[oracle.run_expert].name}
        chosen |= names
        oracle.answer(make_query(99))
        assert oracle.last_annotator in names
    assert len(chosen) >= 2  # the run's expert is drawn at random


def test_experts_asynchronous():
    experts = [LaterOracle(Label.FIRST, "ann"), LaterOracle(Label.SECOND, "bob")]
    oracle = MultiExpertOracle(experts, seed=0)
    oracle.submit([make_query(i) for i in range(20)])
    assert oracle.pending() == 20 and oracle.collect() == []
    experts[0].release()
    experts[1].release()
    answers = oracle.collect()
    assert len(answers) == 20 and oracle.pending() == 0


def test_experts_bad_arguments():
    with pytest.raises(ValueError, match="at least one"):
        MultiExpertOracle([])
    with pytest.raises(ValueError, match="assignment"):
        MultiExpertOracle(three_experts(), assignment="episode")
    with pytest.raises(ValueError, match="distinct"):
        MultiExpertOracle([ConstantOracle(Label.FIRST, "ann"), ConstantOracle(Label.SECOND, "ann")])
    with pytest.raises(ValueError, match="not an Oracle"):
        MultiExpertOracle([ConstantOracle(Label.FIRST), "bob"])  # type: ignore[list-item]


# --- FetchScriptedOracle --------------------------------------------------------------------------------


def fetch_query(desired, achieved1, achieved2) -> Query:
    info = {"desired_goal": np.array(desired), "goal1_achieved": np.array(achieved1), "goal2_achieved": np.array(achieved2)}
    return Query(state=np.zeros(3), goal1=0, goal2=1, goal1_obs=np.zeros(3), goal2_obs=np.zeros(3), info=info)


def test_fetch_prefers_closer_sub_goal():
    oracle = FetchScriptedOracle()
    desired = [1.3, 0.7, 0.42]
    # distances 0.1 vs sqrt(3 * 0.05^2) = 0.0866: the second is closer in Euclidean distance, while the
    # L1 distance (0.1 vs 0.15) would prefer the first
    assert oracle.answer(fetch_query(desired, [1.4, 0.7, 0.42], [1.35, 0.75, 0.47])) == Label.SECOND
    assert oracle.answer(fetch_query(desired, [1.35, 0.75, 0.47], [1.4, 0.7, 0.42])) == Label.FIRST
    # distances 0.1 vs 0.0995 differ by less than 1 mm: equal; 0.1 vs 0.098 do not
    assert oracle.answer(fetch_query(desired, [1.4, 0.7, 0.42], [1.3, 0.7995, 0.42])) == Label.EQUAL
    assert oracle.answer(fetch_query(desired, [1.4, 0.7, 0.42], [1.3, 0.7, 0.518])) == Label.SECOND
    oracle.submit([fetch_query(desired, [1.3, 0.7, 0.43], [1.0, 0.7, 0.42])])
    (answer,) = oracle.collect()
    assert answer.label == Label.FIRST and answer.annotator == "scripted"


def test_fetch_counts_the_gripper_at_the_object_two_centimetres_nearer():
    oracle = FetchScriptedOracle()
    desired = [1.3, 0.7, 0.42]

    def with_gripper(achieved1, achieved2, at1, at2):
        query = fetch_query(desired, achieved1, achieved2)
        query.info.update(goal1_gripper_at_object=at1, goal2_gripper_at_object=at2)
        return query

    # the same place: the gripper at the object is the better sub-goal, either way round
    assert oracle.answer(with_gripper([1.4, 0.7, 0.42], [1.4, 0.7, 0.42], False, True)) == Label.SECOND
    assert oracle.answer(with_gripper([1.4, 0.7, 0.42], [1.4, 0.7, 0.42], True, False)) == Label.FIRST
    assert oracle.answer(with_gripper([1.4, 0.7, 0.42], [1.4, 0.7, 0.42], True, True)) == Label.EQUAL
    # 0.10 - 0.02 against 0.085 (the object 1.5 cm nearer, the gripper away): the gripper at the object; against 0.07
    # (3 cm nearer): the object nearer; without the flags the nearer place as before
    assert oracle.answer(with_gripper([1.4, 0.7, 0.42], [1.385, 0.7, 0.42], True, False)) == Label.FIRST
    assert oracle.answer(with_gripper([1.4, 0.7, 0.42], [1.37, 0.7, 0.42], True, False)) == Label.SECOND
    assert oracle.answer(fetch_query(desired, [1.4, 0.7, 0.42], [1.385, 0.7, 0.42])) == Label.SECOND
    assert FetchScriptedOracle(gripper_bonus=0.0).answer(
        with_gripper([1.4, 0.7, 0.42], [1.4, 0.7, 0.42], False, True)) == Label.EQUAL
    with pytest.raises(ValueError, match="gripper_bonus"):
        FetchScriptedOracle(gripper_bonus=-0.01)


def test_fetch_missing_keys():
    oracle = FetchScriptedOracle()
    query = fetch_query([0, 0, 0], [1, 0, 0], [0, 1, 0])
    del query.info["goal2_achieved"]
    with pytest.raises(ValueError, match="goal2_achieved"):
        oracle.answer(query)
    with pytest.raises(ValueError, match="shape"):
        oracle.answer(fetch_query([0, 0, 0], [1, 0], [0, 1, 0]))
    with pytest.raises(ValueError, match="equal_tolerance"):
        FetchScriptedOracle(equal_tolerance=-1.0)


# --- TerminalOracle -------------------------------------------------------------------------------------


def image_query(i: int) -> Query:
    rng = np.random.default_rng(i)
    images = [rng.integers(0, 256, size=(40, 60, 3), dtype=np.uint8) for _ in range(3)]
    return make_query(i, state_image=images[0], goal1_image=images[1], goal2_image=images[2])


def test_parse_reply():
    assert parse_reply("1\n") == Label.FIRST and parse_reply(" Left ") == Label.FIRST
    assert parse_reply("2") == Label.SECOND and parse_reply("RIGHT\n") == Label.SECOND
    assert parse_reply("=") == Label.EQUAL and parse_reply("x") == Label.INCOMPARABLE
    assert parse_reply("can't tell") == Label.INCOMPARABLE
    for garbage in ("", "\n", "3", "0", "maybe", "12"):
        assert parse_reply(garbage) is None


def test_terminal_answers_from_fake_stdin(tmp_path):
    output = io.StringIO()
    oracle = TerminalOracle("alice", io.StringIO("hello\n1\nright\n=\nx\n"), output, image_dir=str(tmp_path))
    queries = [image_query(i) for i in range(4)]
    oracle.submit(queries)
    assert wait_for(lambda: oracle.pending() == 0)
    answers = oracle.collect()
    assert [a.label for a in answers] == [Label.FIRST, Label.SECOND, Label.EQUAL, Label.INCOMPARABLE]
    assert [a.query_id for a in answers] == ["q0", "q1", "q2", "q3"]
    assert all(a.annotator == "alice" for a in answers)
    text = output.getvalue()
    assert text.count("Which sub-goal is better") == 5  # "hello" was re-prompted
    assert "Could not read 'hello'" in text
    # the PNGs are written, their paths printed, and they hold the query's images (RGB order kept)
    path = os.path.join(str(tmp_path), "q0_goal1.png")
    assert path in text
    np.testing.assert_array_equal(cv2.cvtColor(cv2.imread(path), cv2.COLOR_BGR2RGB), queries[0].goal1_image)
    assert "\u2580" in text and "\x1b[38;2;" in text
    oracle.close()


def test_terminal_submit_does_not_block():
    read_fd, write_fd = os.pipe()
    with os.fdopen(read_fd, "r") as reader, os.fdopen(write_fd, "w") as writer:
        oracle = TerminalOracle(input_stream=reader, output_stream=io.StringIO())
        # nobody has typed anything yet: a submit that read its replies on the caller's thread would wait for them
        # forever, so it runs on a thread of its own that must end (the bound is generous: it fails a blocking submit,
        # not a slow machine)
        submitter = threading.Thread(target=oracle.submit, args=([image_query(0), image_query(1)],), daemon=True)
        submitter.start()
        submitter.join(timeout=30.0)
        assert not submitter.is_alive()
        assert oracle.pending() == 2 and oracle.collect() == []
        time.sleep(0.1)
        assert oracle.collect() == []
        writer.write("2\n")
        writer.flush()
        assert wait_for(lambda: oracle.pending() == 1)
        (answer,) = oracle.collect()
        assert answer.query_id == "q0" and answer.label == Label.SECOND and answer.annotator == "terminal"
        writer.write("left\n")
        writer.flush()
        assert wait_for(lambda: oracle.pending() == 0)
        assert [a.label for a in oracle.collect()] == [Label.FIRST]
        image_dir = oracle.image_dir
        assert os.path.isfile(os.path.join(image_dir, "q1_state.png"))
        oracle.close()
        assert not os.path.exists(image_dir)  # the temporary folder is removed


def test_terminal_reply_window_gives_incomparable():
    read_fd, write_fd = os.pipe()
    with os.fdopen(read_fd, "r") as reader, os.fdopen(write_fd, "w") as writer:
        output = io.StringIO()
        oracle = TerminalOracle(input_stream=reader, output_stream=output, reply_window_s=0.3)
        oracle.submit([make_query(0), make_query(1)])  # no images: text only
        assert wait_for(lambda: oracle.pending() == 1)
        (late,) = oracle.collect()
        assert late.label == Label.INCOMPARABLE and late.query_id == "q0"
        assert "No reply within 0.3 s" in output.getvalue()
        # reply once the second query is on screen (a line typed before it appeared would not count)
        assert wait_for(lambda: output.getvalue().count("Which sub-goal is better") == 2)
        writer.write("1\n")
        writer.flush()
        assert wait_for(lambda: oracle.pending() == 0)
        (answer,) = oracle.collect()
        assert answer.label == Label.FIRST and answer.query_id == "q1"
        oracle.close()


def test_terminal_input_closed_leaves_queries_pending():
    oracle = TerminalOracle(input_stream=io.StringIO("1\n"), output_stream=io.StringIO())
    oracle.submit([make_query(0), make_query(1)])
    assert wait_for(lambda: oracle.input_closed)
    assert [a.label for a in oracle.collect()] == [Label.FIRST]
    assert oracle.pending() == 1
    oracle.close()


def test_terminal_bad_arguments():
    with pytest.raises(ValueError, match="reply_window_s"):
        TerminalOracle(reply_window_s=0)
    with pytest.raises(ValueError, match="name"):
        TerminalOracle(name="")


def test_ansi_preview_colours_and_layout():
    red = np.zeros((4, 4, 3), dtype=np.uint8)
    red[..., 0] = 255
    gray = np.full((8, 4), 0.5)  # float grayscale in [0, 1], twice as tall
    preview = ansi_preview([red, None, gray], width=4, titles=["a", "b", "c"])
    lines = preview.split("\n")
    assert lines[0] == " a  " + "  " + " b  " + "  " + " c  "
    # red: 4 pixel rows -> 2 text rows; gray: 8 pixel rows -> 4 text rows
    assert len(lines) == 1 + 4
    assert lines[1].count("\x1b[38;2;255;0;0m\x1b[48;2;255;0;0m\u2580") == 4
    assert lines[1].count("\x1b[38;2;128;128;128m") == 4
    assert lines[4].startswith(" " * 4 + "  " + " " * 4 + "  ")  # red and the missing image are blank there


# --- SyntheticOracle ------------------------------------------------------------------------------------


def synthetic_data(n: int, seed: int = 0):
    """Goals of two kinds: goal[0] = +1 gives returns 0 or 2 (average 1), goal[0] = -1 always 1.5.

    A regression of the *average* return prefers the second kind, although the first sometimes gets more.
    """
    rng = np.random.default_rng(seed)
    states = rng.uniform(-1, 1, size=(n, 3)).astype(np.float32)
    kind = rng.integers(0, 2, size=n)
    goals = rng.uniform(-1, 1, size=(n, 3)).astype(np.float32)
    goals[:, 0] = np.where(kind == 0, 1.0, -1.0)
    returns = np.where(kind == 0, 2.0 * rng.integers(0, 2, size=n), 1.5)
    return states, goals, returns


def test_synthetic_oracle_prefers_higher_average_return():
    import gymnasium
    import torch

    torch.set_num_threads(1)
    space = gymnasium.spaces.Box(-1, 1, shape=(3,), dtype=np.float32)
    oracle = SyntheticOracle(space, hidden_dim=32, dropout=0.1, batch_size=64, n_epochs=2, seed=0)
    states, goals, returns = synthetic_data(2000)
    oracle.observe(states, goals, returns)
    assert len(oracle) == 2000
    first_mse = oracle.train()
    for _ in range(10):
        mse = oracle.train()
    # the best possible MSE is the variance of the returns around their means: 1 for kind 0, 0 for kind 1
    assert mse < first_mse and 0.35 < mse < 0.7
    test_states, test_goals, _ = synthetic_data(200, seed=1)
    values = oracle.predict(test_states, test_goals)
    np.testing.assert_allclose(values[test_goals[:, 0] > 0].mean(), 1.0, atol=0.2)
    np.testing.assert_allclose(values[test_goals[:, 0] < 0].mean(), 1.5, atol=0.2)
    good, bad = test_goals[test_goals[:, 0] < 0], test_goals[test_goals[:, 0] > 0]
    n_queries = min(len(good), len(bad))
    queries = [
        Query(state=test_states[i], goal1=0, goal2=1, goal1_obs=bad[i], goal2_obs=good[i], query_id=f"q{i}")
        for i in range(n_queries)
    ]
    oracle.submit(queries)
    answers = oracle.collect()
    assert all(answer.annotator == "synthetic" for answer in answers)
    assert np.mean([answer.label == Label.SECOND for answer in answers]) > 0.95
    swapped = Query(state=test_states[0], goal1=1, goal2=0, goal1_obs=good[0], goal2_obs=bad[0])
    assert oracle.answer(swapped) == Label.FIRST
    same = Query(state=test_states[0], goal1=1, goal2=1, goal1_obs=good[0], goal2_obs=good[0].copy())
    assert oracle.answer(same) == Label.EQUAL
    # dropout is off when answering: the same query always gets the same estimate
    np.testing.assert_array_equal(oracle.predict(test_states, test_goals), values)


def test_synthetic_oracle_fifo_buffer_and_state_dict():
    import gymnasium

    space = gymnasium.spaces.Box(-1, 1, shape=(3,), dtype=np.float32)
    oracle = SyntheticOracle(space, hidden_dim=8, buffer_size=1500, seed=3)
    states, goals, returns = synthetic_data(2500)
    for start in range(0, 2500, 700):  # crosses the growth steps and the wrap-around
        oracle.observe(states[start : start + 700], goals[start : start + 700], returns[start : start + 700])
    assert len(oracle) == 1500
    saved = oracle.state_dict(include_buffer=True)
    # the newest 1500, stored in a ring: 2500 = 1500 + 1000, so the oldest kept one sits at position 1000
    order = (1000 + np.arange(1500)) % 1500
    assert saved["buffer"]["pos"] == 1000
    np.testing.assert_array_equal(saved["buffer"]["states"].numpy()[order], states[-1500:])
    np.testing.assert_array_equal(saved["buffer"]["returns"].numpy()[order], returns[-1500:].astype(np.float32))
    oracle.train(1)
    saved = oracle.state_dict(include_buffer=True)
    other = SyntheticOracle(space, hidden_dim=8, buffer_size=1500, seed=4)
    other.load_state_dict(saved)
    assert len(other) == 1500
    np.testing.assert_array_equal(other.predict(states[:10], goals[:10]), oracle.predict(states[:10], goals[:10]))
    # same generator states: the next training step is identical too
    assert other.train(1) == oracle.train(1)
    assert "buffer" not in oracle.state_dict()
    with pytest.raises(ValueError, match="buffer_size"):
        SyntheticOracle(space, hidden_dim=8, buffer_size=100).load_state_dict(saved)


def test_synthetic_oracle_is_seeded_and_leaves_global_rng():
    import gymnasium
    import torch

    space = gymnasium.spaces.Box(-1, 1, shape=(3,), dtype=np.float32)
    states, goals, returns = synthetic_data(300)
    torch.manual_seed(123)
    expected_draw = torch.rand(1).item()
    losses = []
    for global_seed in (123, 456):
        torch.manual_seed(global_seed)
        oracle = SyntheticOracle(space, hidden_dim=8, seed=5)
        oracle.observe(states, goals, returns)
        losses.append(oracle.train(1))
        if global_seed == 123:  # building and training drew nothing from the global generator
            assert torch.rand(1).item() == expected_draw
    assert losses[0] == losses[1]  # the oracle's own seed decides, whatever the global one


def test_synthetic_oracle_bad_arguments():
    import gymnasium

    space = gymnasium.spaces.Box(-1, 1, shape=(3,), dtype=np.float32)
    for kwargs, match in [
        ({"batch_size": 0}, "batch_size"),
        ({"n_epochs": 0}, "n_epochs"),
        ({"buffer_size": 0}, "buffer_size"),
        ({"learning_rate": 0.0}, "learning_rate"),
        ({"equal_tolerance": -1.0}, "equal_tolerance"),
        ({"dropout": 1.0}, "dropout"),
        ({"hidden_dim": 0}, "hidden_dim"),
        ({"head": "tanh"}, "head"),
    ]:
        with pytest.raises(ValueError, match=match):
            SyntheticOracle(space, **kwargs)
    with pytest.raises(ValueError, match="Box"):
        SyntheticOracle(gymnasium.spaces.Discrete(3))
    oracle = SyntheticOracle(space, hidden_dim=8)
    with pytest.raises(ValueError, match="goals must have shape"):
        oracle.observe(np.zeros((4, 3)), np.zeros((4, 2)), np.zeros(4))
    with pytest.raises(ValueError, match="finite"):
        oracle.observe(np.zeros((1, 3)), np.zeros((1, 3)), np.array([np.nan]))
    with pytest.warns(UserWarning, match="negative returns"):  # the paper's ReLU head reads them as 0
        SyntheticOracle(space, hidden_dim=8, head="relu").observe(np.zeros((1, 3)), np.zeros((1, 3)), np.array([-1.0]))
    assert math.isnan(SyntheticOracle(space, hidden_dim=8).train())


def test_synthetic_oracle_trains_on_new_triples_at_a_cost_that_follows_what_arrived(monkeypatch):
    """train_on_new: ceil(n_epochs * new / batch_size) minibatches from the whole buffer, however large it is; nothing
    when nothing arrived; and the estimates it learns in episodes' chunks are the average returns."""
    import gymnasium
    import torch

    torch.set_num_threads(1)
    space = gymnasium.spaces.Box(-1, 1, shape=(3,), dtype=np.float32)
    oracle = SyntheticOracle(space, hidden_dim=32, dropout=0.1, batch_size=64, n_epochs=4, seed=0)
    steps = []
    step = oracle.optimizer.step
    monkeypatch.setattr(oracle.optimizer, "step", lambda *a, **k: (steps.append(1), step(*a, **k))[1])
    states, goals, returns = synthetic_data(4000)
    counts = []
    for start in range(0, 4000, 40):  # episodes of 40 triples, the buffer growing to 4000
        oracle.observe(states[start : start + 40], goals[start : start + 40], returns[start : start + 40])
        before = len(steps)
        oracle.train_on_new()
        counts.append(len(steps) - before)
    assert set(counts) == {math.ceil(4 * 40 / 64)}  # 3 a call, from the first episode to the hundredth
    assert math.isnan(oracle.train_on_new()) and len(steps) == sum(counts)  # nothing new, nothing trained
    test_states, test_goals, _ = synthetic_data(200, seed=1)
    values = oracle.predict(test_states, test_goals)
    np.testing.assert_allclose(values[test_goals[:, 0] > 0].mean(), 1.0, atol=0.25)
    np.testing.assert_allclose(values[test_goals[:, 0] < 0].mean(), 1.5, atol=0.25)
