import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest

from sb3_hhp.oracles.base import Answer, Label, Query
from sb3_hhp.preferences.codecs import decode_png, encode_png
from sb3_hhp.preferences.store import SCHEMA_VERSION, AlreadyAnswered, PreferenceStore
from sb3_hhp.subgoal_table import SubgoalTable

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def make_query(seed: int = 0, asked_at: float = 1000.0, images: bool = True, **kwargs) -> Query:
    rng = np.random.default_rng(seed)
    return Query(
        state=rng.random((3, 7, 7)).astype(np.float32),
        goal1=seed,
        goal2=seed + 1,
        goal1_obs=rng.integers(0, 255, (3, 7, 7), dtype=np.uint8),
        goal2_obs=rng.integers(0, 255, (3, 7, 7), dtype=np.uint8),
        state_image=rng.integers(0, 255, (24, 32, 3), dtype=np.uint8) if images else None,
        goal1_image=rng.integers(0, 255, (24, 32, 3), dtype=np.uint8) if images else None,
        goal2_image=rng.integers(0, 255, (16, 16), dtype=np.uint8) if images else None,
        info={"keys": np.array([1, 2]), "value": np.float32(0.5), "name": "door"},
        query_id=f"q{seed}",
        asked_at=asked_at,
        **kwargs,
    )


def dump(path) -> list[str]:
    """Every row of the database file, read through an independent connection."""
    conn = sqlite3.connect(path)
    try:
        return list(conn.iterdump())
    finally:
        conn.close()


def test_png_round_trip_keeps_rgb_order():
    image = np.zeros((4, 5, 3), dtype=np.uint8)
    image[..., 0] = 255  # pure red in RGB
    decoded = decode_png(encode_png(image))
    np.testing.assert_array_equal(decoded, image)
    gray = np.arange(20, dtype=np.uint8).reshape(4, 5)
    np.testing.assert_array_equal(decode_png(encode_png(gray)), gray)
    with pytest.raises(ValueError, match="uint8"):
        encode_png(image.astype(np.float32))


def test_query_and_answer_round_trip(tmp_path):
    path = tmp_path / "prefs.db"
    query = make_query(3)
    with PreferenceStore(path) as store:
        store.add_query(query, run_id="run-a")
        assert store.open_query_ids() == ["q3"]
        answer = store.add_answer("q3", "second", "alice", answered_at=1234.5)
        assert answer == Answer("q3", Label.SECOND, "alice", 1234.5)

    with PreferenceStore(path) as store:  # reopened: everything came from the file
        [(seq, loaded, answer)] = store.answers_since(0)
        assert seq == 1
        assert answer == Answer("q3", Label.SECOND, "alice", 1234.5)
        for name in ("state", "goal1_obs", "goal2_obs", "state_image", "goal1_image", "goal2_image"):
            expected, actual = getattr(query, name), getattr(loaded, name)
            assert actual.dtype == expected.dtype and actual.shape == expected.shape, name
            np.testing.assert_array_equal(actual, expected, err_msg=name)
        assert (loaded.goal1, loaded.goal2, loaded.asked_at) == (3, 4, 1000.0)
        assert loaded.info == {"keys": [1, 2], "value": 0.5, "name": "door"}
        np.testing.assert_array_equal(decode_png(store.image_png("q3", "goal1")), query.goal1_image)
        assert store.count_asked() == 1 and store.count_asked("run-a") == 1 and store.count_asked("run-b") == 0
        assert store.asked_ids() == {"q3"} and store.answered_ids() == {"q3"}
        assert store.open_queries() == []


def test_dict_observation_and_missing_images():
    store = PreferenceStore()
    query = make_query(1, images=False)
    query.state = {"image": np.ones((2, 2), np.uint8), "direction": np.array(3)}
    store.add_query(query)
    loaded = store.get_query("q1")
    assert set(loaded.state) == {"image", "direction"}
    np.testing.assert_array_equal(loaded.state["image"], np.ones((2, 2), np.uint8))
    assert loaded.state_image is None and store.image_kinds("q1") == []
    with pytest.raises(KeyError, match="no state image"):
        store.image_png("q1", "state")
    with pytest.raises(ValueError, match="which must be one of"):
        store.image_png("q1", "goal3")


def test_add_query_is_idempotent_and_open_queries_are_oldest_first():
    store = PreferenceStore()
    store.add_query(make_query(2, asked_at=30.0))
    store.add_query(make_query(1, asked_at=10.0))
    store.add_query(make_query(3, asked_at=20.0))
    store.add_query(make_query(1, asked_at=99.0))  # same id again: ignored
    assert store.count_asked() == 3
    assert [q.query_id for q in store.open_queries()] == ["q1", "q3", "q2"]
    assert [q.query_id for q in store.open_queries(limit=2)] == ["q1", "q3"]
    assert store.get_query("q1").asked_at == 10.0
    store.add_answer("q3", Label.EQUAL, "bob")
    assert store.open_query_ids() == ["q1", "q2"]
    assert store.is_open("q1") and not store.is_open("q3") and not store.is_open("nope")


def test_answers_since_reads_incrementally_in_commit_order():
    store = PreferenceStore()
    for seed in range(4):
        store.add_query(make_query(seed, asked_at=float(seed)))
    store.add_answer("q2", 0, "alice")
    store.add_answer("q0", "can't tell", "bob")
    first = store.answers_since(0)
    assert [(a.query_id, a.label, a.annotator) for _, _, a in first] == [
        ("q2", Label.FIRST, "alice"),
        ("q0", Label.INCOMPARABLE, "bob"),
    ]
    last = first[-1][0]
    assert store.answers_since(last) == []
    store.add_answer("q3", "EQUAL", "alice")
    [(seq, query, answer)] = store.answers_since(last)
    assert seq > last and query.query_id == "q3" and answer.label == Label.EQUAL
    assert store.last_seq() == seq
    stats = store.stats()
    assert stats["asked"] == 4 and stats["queued"] == 1 and stats["answered"] == 3
    assert stats["per_annotator"] == {"alice": 2, "bob": 1}
    assert stats["per_label"] == {"FIRST": 1, "SECOND": 0, "EQUAL": 1, "INCOMPARABLE": 1}


def test_bad_answers_raise_and_leave_the_file_unchanged(tmp_path):
    path = tmp_path / "prefs.db"
    store = PreferenceStore(path)
    store.add_query(make_query(0))
    store.add_query(make_query(1))
    store.add_answer("q0", "FIRST", "alice")
    before = dump(path)
    with pytest.raises(KeyError, match="Unknown query id"):
        store.add_answer("missing", "FIRST", "alice")
    with pytest.raises(ValueError, match="Unknown preference label"):
        store.add_answer("q1", "BEST", "alice")
    with pytest.raises(ValueError, match="Unknown preference label"):
        store.add_answer("q1", 7, "alice")
    with pytest.raises(ValueError, match="annotator"):
        store.add_answer("q1", "FIRST", "  ")
    with pytest.raises(AlreadyAnswered, match="already answered by 'alice'"):
        store.add_answer("q0", "SECOND", "bob")
    assert issubclass(AlreadyAnswered, ValueError)
    assert dump(path) == before
    assert store.get_answer("q0").label == Label.FIRST and store.get_answer("q1") is None
    store.close()


def test_concurrent_writers_from_threads_and_a_second_connection(tmp_path):
    path = tmp_path / "prefs.db"
    store = PreferenceStore(path)
    other = PreferenceStore(path)  # another "process" on the same file
    for seed in range(40):
        store.add_query(make_query(seed, images=False))
    errors = []

    def answer(start: int, target: PreferenceStore, name: str) -> None:
        try:
            for seed in range(start, 40, 4):
                target.add_answer(f"q{seed}", seed % 4, name)
        except Exception as error:  # collected and asserted below
            errors.append(error)

    threads = [threading.Thread(target=answer, args=(i, store if i % 2 else other, f"a{i}")) for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    triples = store.answers_since(0)
    seqs = [seq for seq, _, _ in triples]
    assert len(triples) == 40 and seqs == sorted(set(seqs))
    assert store.stats()["per_annotator"] == {f"a{i}": 10 for i in range(4)}
    other.close()
    store.close()


CHILD = textwrap.dedent(
    """
    import sys
    import numpy as np
    from sb3_hhp.oracles.base import Query
    from sb3_hhp.preferences.store import PreferenceStore

    store = PreferenceStore(sys.argv[1])
    for i in range(100000):
        qid = f"k{i}"
        store.add_query(Query(np.full(4, i, np.float32), 0, 1, np.zeros(4), np.ones(4), query_id=qid, asked_at=i))
        store.add_answer(qid, i % 4, "child")
        print(qid, flush=True)
    """
)


def test_sigkill_loses_no_reported_answer(tmp_path):
    path = tmp_path / "prefs.db"
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, text=True, env=env, cwd=str(tmp_path)
    )
    reported = []
    try:
        deadline = time.monotonic() + 30
        while len(reported) < 25 and time.monotonic() < deadline:
            line = child.stdout.readline()
            if not line:
                break
            reported.append(line.strip())
        child.send_signal(signal.SIGKILL)
        child.wait(10)
        reported += [line.strip() for line in child.stdout.read().splitlines() if line.strip()]
    finally:
        if child.poll() is None:
            child.kill()
        child.stdout.close()
    assert child.returncode == -signal.SIGKILL
    assert len(reported) >= 25
    with PreferenceStore(path) as store:
        answered = store.answered_ids()
        assert set(reported) <= answered
        for qid in reported:
            i = int(qid[1:])
            assert store.get_answer(qid).label == Label(i % 4)
            np.testing.assert_array_equal(store.get_query(qid).state, np.full(4, i, np.float32))
        assert store._conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"


def test_export_and_import_round_trip_without_duplicates(tmp_path):
    source = PreferenceStore(tmp_path / "a.db")
    for seed in range(4):
        source.add_query(make_query(seed, asked_at=float(seed)))
    source.add_answer("q0", "FIRST", "alice", answered_at=1.0)
    source.add_answer("q2", "SECOND", "bob", answered_at=2.0)
    source.add_answer("q1", "EQUAL", "alice", answered_at=3.0)
    SubgoalTable(source).put([{"id": 0, "image": np.zeros((4, 4, 3), np.uint8)}])
    dataset = tmp_path / "prefs_dataset.db"
    source.export(dataset)
    with pytest.raises(FileExistsError):
        source.export(dataset)
    # one self-contained file: no leftover partial file, no -wal/-shm beside the dataset
    assert sorted(name for name in os.listdir(tmp_path) if name.startswith("prefs_dataset")) == ["prefs_dataset.db"]

    pairs = PreferenceStore.load_dataset(dataset)
    assert [(q.query_id, a.label, a.annotator, a.answered_at) for q, a in pairs] == [
        ("q0", Label.FIRST, "alice", 1.0),
        ("q2", Label.SECOND, "bob", 2.0),
        ("q1", Label.EQUAL, "alice", 3.0),
    ]
    np.testing.assert_array_equal(pairs[1][0].goal1_image, make_query(2).goal1_image)
    with PreferenceStore(dataset) as loaded:  # only answered queries travel, no open query, no sub-goal
        assert loaded.open_query_ids() == [] and SubgoalTable(loaded).records() == []

    target = PreferenceStore(tmp_path / "b.db")
    target.add_query(make_query(2))  # asked here and still open: receives the dataset's answer
    target.add_query(make_query(1))
    target.add_answer("q1", "FIRST", "carol")  # answered here: the dataset's answer is skipped
    target.add_query(make_query(7))
    assert target.import_dataset(dataset) == 2
    assert target.import_dataset(dataset) == 0
    assert target.count_asked() == 4
    assert target.get_answer("q1").annotator == "carol"
    assert target.get_answer("q2") == Answer("q2", Label.SECOND, "bob", 2.0)
    assert target.get_answer("q0").label == Label.FIRST
    assert target.open_query_ids() == ["q7"]
    with pytest.raises(FileNotFoundError):
        target.import_dataset(tmp_path / "missing.db")
    with pytest.raises(FileNotFoundError):
        PreferenceStore.load_dataset(tmp_path / "missing.db")
    source.close()
    target.close()


def test_foreign_or_corrupt_files_are_refused_untouched(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_bytes(b"these are my notes, not a database\n" * 10)
    with pytest.raises(ValueError, match="not a preference store"):
        PreferenceStore(text)
    assert text.read_bytes() == b"these are my notes, not a database\n" * 10

    foreign = tmp_path / "other.db"
    conn = sqlite3.connect(foreign)
    conn.execute("CREATE TABLE users (name TEXT)")
    conn.execute("INSERT INTO users VALUES ('x')")
    conn.commit()
    conn.close()
    before = foreign.read_bytes()
    with pytest.raises(ValueError, match="not a preference store"):
        PreferenceStore(foreign)
    assert foreign.read_bytes() == before

    truncated = tmp_path / "truncated.db"
    store = PreferenceStore(tmp_path / "good.db")
    store.add_query(make_query(0))
    store.close()
    truncated.write_bytes((tmp_path / "good.db").read_bytes()[:100] + b"\x00garbage" * 50)
    with pytest.raises(ValueError, match="preference store"):
        PreferenceStore(truncated)

    newer = tmp_path / "newer.db"
    PreferenceStore(newer).close()
    conn = sqlite3.connect(newer)
    conn.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(SCHEMA_VERSION + 1),))
    conn.commit()
    conn.close()
    with pytest.raises(ValueError, match="newer than this sb3_hhp"):
        PreferenceStore(newer)

    with pytest.raises(ValueError, match="is a directory"):
        PreferenceStore(tmp_path)
    with pytest.raises(ValueError, match="timeout must be > 0"):
        PreferenceStore(":memory:", timeout=0)


def test_a_store_of_schema_version_1_is_migrated_and_keeps_its_answers(tmp_path):
    path = tmp_path / "old.db"
    store = PreferenceStore(path)
    store.add_query(make_query(0))
    store.add_answer("q0", "FIRST", "alice")
    store.close()
    conn = sqlite3.connect(path)  # make it a file written by schema version 1
    conn.execute("ALTER TABLE answers DROP COLUMN response_s")
    conn.execute(  # version 1 kept the sub-goal gallery's table, without its info column
        "CREATE TABLE subgoals (id INTEGER PRIMARY KEY, png BLOB NOT NULL, found_at INTEGER, success_rate REAL, "
        "chosen_recently INTEGER NOT NULL DEFAULT 0, mean_score REAL)"
    )
    conn.execute("INSERT INTO subgoals (id, png, found_at) VALUES (3, ?, 70)", (encode_png(np.zeros((4, 4, 3), np.uint8)),))
    conn.execute("UPDATE meta SET value = '1' WHERE key = 'schema_version'")
    conn.commit()
    conn.close()
    store = PreferenceStore(path)
    assert store.get_answer("q0").annotator == "alice" and store.response_times() == []
    store.add_query(make_query(1))
    store.add_answer("q1", "SECOND", "bob", response_s=1.25)
    assert store.response_times("bob") == [1.25]
    [record] = SubgoalTable(store).records(with_images=False)
    assert (record["id"], record["found_at"], record["name"]) == (3, 70, None)
    store.close()
    conn = sqlite3.connect(path)
    assert conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0] == str(SCHEMA_VERSION)
    conn.close()


def test_create_false_refuses_a_missing_file_and_writes_nothing(tmp_path):
    with pytest.raises(FileNotFoundError, match="No preference store"):
        PreferenceStore(tmp_path / "typo.db", create=False)
    assert list(tmp_path.iterdir()) == []
    PreferenceStore(tmp_path / "new.db").close()
    PreferenceStore(tmp_path / "new.db", create=False).close()


def test_budget_distinct_questions_and_response_times():
    store = PreferenceStore()
    stats = store.stats()
    assert stats["budget"] is None and stats["distinct"] is None and stats["signed"] == 0
    for index, signature in enumerate(["a", "b", "a", None]):
        query = make_query(index)
        if signature is not None:
            query.info["signature"] = signature
        store.add_query(query)
    store.set_query_budget(200)
    stats = store.stats()
    assert (stats["asked"], stats["budget"], stats["distinct"], stats["signed"]) == (4, 200, 2, 3)
    with pytest.raises(ValueError, match="budget must be an integer >= 0"):
        store.set_query_budget(-1)
    store.add_answer("q0", "FIRST", "alice", response_s=2.0)
    store.add_answer("q1", "FIRST", "alice")
    with pytest.raises(ValueError, match="response_s must be"):
        store.add_answer("q2", "FIRST", "alice", response_s=float("nan"))
    assert store.response_times("alice") == [2.0] and store.get_answer("q2") is None
    assert store.query_info("q0")["signature"] == "a" and store.query_goals("q0")[:2] == (0, 1)

