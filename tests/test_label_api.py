import sqlite3
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from sb3_hhp.label.app import create_app
from sb3_hhp.label.server import LabelServer, check_bind, is_loopback
from sb3_hhp.oracles.base import Label, Query
from sb3_hhp.oracles.web import WebOracle
from sb3_hhp.preferences.codecs import decode_png
from sb3_hhp.preferences.store import PreferenceStore
from sb3_hhp.subgoal_table import SubgoalTable


def make_query(seed: int, asked_at: float = 0.0) -> Query:
    rng = np.random.default_rng(seed)
    return Query(
        state=np.zeros(4, np.float32),
        goal1=seed,
        goal2=seed + 10,
        goal1_obs=np.zeros(4),
        goal2_obs=np.ones(4),
        state_image=rng.integers(0, 255, (12, 12, 3), dtype=np.uint8),
        goal1_image=rng.integers(0, 255, (12, 12, 3), dtype=np.uint8),
        goal2_image=rng.integers(0, 255, (12, 12, 3), dtype=np.uint8),
        query_id=f"q{seed}",
        asked_at=asked_at or float(seed),
    )


@pytest.fixture
def db(tmp_path):
    path = tmp_path / "prefs.db"
    store = PreferenceStore(path)
    for seed in range(3):
        store.add_query(make_query(seed))
    yield store, path
    store.close()


def dump(path) -> list[str]:
    conn = sqlite3.connect(path)
    try:
        return list(conn.iterdump())
    finally:
        conn.close()


def test_next_answer_and_stats(db):
    store, _ = db
    client = TestClient(create_app(store, reply_window_s=3.0))
    page = client.get("/")
    assert page.status_code == 200 and 'id="btn-first"' in page.text
    assert client.get("/static/label.js").status_code == 200

    body = client.get("/api/next", params={"annotator": "alice"}).json()
    assert body["reply_window_s"] == 3.0 and body["queued"] == 3 and body["answered_by_you"] == 0
    question = body["query"]
    assert question["query_id"] == "q0" and (question["goal1"], question["goal2"]) == (0, 10)
    png = client.get(question["images"]["goal2"])
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    np.testing.assert_array_equal(decode_png(png.content), make_query(0).goal2_image)

    reply = client.post("/api/answer", json={"query_id": "q0", "label": "FIRST", "annotator": "alice"})
    assert reply.status_code == 200
    assert reply.json()["label"] == "FIRST" and reply.json()["answered_by_you"] == 1 and reply.json()["queued"] == 2
    assert store.get_answer("q0").label == Label.FIRST and store.get_answer("q0").annotator == "alice"
    assert client.get("/api/next", params={"annotator": "alice"}).json()["query"]["query_id"] == "q1"

    stats = client.get("/api/stats").json()
    assert stats["queued"] == 2 and stats["answered"] == 1 and stats["per_annotator"] == {"alice": 1}


def test_two_annotators_get_different_questions_and_are_recorded(db):
    store, _ = db
    client = TestClient(create_app(store))
    alice = client.get("/api/next", params={"annotator": "alice"}).json()["query"]["query_id"]
    bob = client.get("/api/next", params={"annotator": "bob"}).json()["query"]["query_id"]
    assert (alice, bob) == ("q0", "q1")  # the lease keeps q0 from bob while alice looks at it
    # asking again (a page reload) gives alice the question she holds
    assert client.get("/api/next", params={"annotator": "alice"}).json()["query"]["query_id"] == "q0"
    assert client.post("/api/answer", json={"query_id": bob, "label": "x", "annotator": "bob"}).status_code == 422
    assert client.post("/api/answer", json={"query_id": bob, "label": "SECOND", "annotator": "bob"}).status_code == 200
    assert client.post("/api/answer", json={"query_id": alice, "label": 2, "annotator": "alice"}).status_code == 200
    assert [(a.query_id, a.label, a.annotator) for _, _, a in store.answers_since(0)] == [
        ("q1", Label.SECOND, "bob"),
        ("q0", Label.EQUAL, "alice"),
    ]
    assert store.stats()["per_annotator"] == {"alice": 1, "bob": 1}


def test_a_lease_expires_after_the_reply_window(db, monkeypatch):
    store, _ = db
    import sb3_hhp.label.app as app_module

    monkeypatch.setattr(app_module, "LEASE_GRACE_S", 0.0)
    client = TestClient(create_app(store, reply_window_s=0.2))
    assert client.get("/api/next", params={"annotator": "alice"}).json()["query"]["query_id"] == "q0"
    assert client.get("/api/next", params={"annotator": "bob"}).json()["query"]["query_id"] == "q1"
    time.sleep(0.3)  # alice's lease ran out without an answer: q0 is free again
    assert client.get("/api/next", params={"annotator": "carol"}).json()["query"]["query_id"] == "q0"


def test_bad_requests_get_clean_4xx_and_leave_the_db_unchanged(db):
    store, path = db
    client = TestClient(create_app(store))
    assert client.post("/api/answer", json={"query_id": "q0", "label": "FIRST", "annotator": "alice"}).status_code == 200
    before = dump(path)
    cases = [
        ({"query_id": "nope", "label": "FIRST", "annotator": "alice"}, 404),
        ({"query_id": "q0", "label": "SECOND", "annotator": "bob"}, 409),  # replayed / second answer
        ({"query_id": "q1", "label": "BEST", "annotator": "alice"}, 422),
        ({"query_id": "q1", "label": 9, "annotator": "alice"}, 422),
        ({"query_id": "q1", "label": True, "annotator": "alice"}, 422),
        ({"query_id": "q1", "label": "FIRST"}, 422),  # no annotator
        ({"query_id": "q1", "label": "FIRST", "annotator": ""}, 422),
        ({"query_id": "q1", "label": "FIRST", "annotator": "   "}, 422),
        ({"label": "FIRST", "annotator": "alice"}, 422),
    ]
    for payload, status in cases:
        response = client.post("/api/answer", json=payload)
        assert response.status_code == status, (payload, response.text)
    assert client.post("/api/answer", content=b"{not json", headers={"content-type": "application/json"}).status_code == 422
    assert client.get("/api/next").status_code == 422  # no annotator
    assert dump(path) == before


def test_images_are_served_only_for_open_queries(db):
    store, _ = db
    client = TestClient(create_app(store))
    assert client.get("/api/image/q1/state.png").status_code == 200
    assert client.get("/api/image/q1/goal3.png").status_code == 404
    assert client.get("/api/image/missing/state.png").status_code == 404
    store.add_answer("q1", "FIRST", "alice")
    for which in ("state", "goal1", "goal2"):
        assert client.get(f"/api/image/q1/{which}.png").status_code == 404
    image_less = make_query(9)
    image_less.goal2_image = None
    store.add_query(image_less)
    assert client.get("/api/image/q9/goal2.png").status_code == 404


def test_token_is_required_on_every_api_call(db):
    store, _ = db
    client = TestClient(create_app(store, token="s3cret"))
    calls = [
        ("get", "/api/next?annotator=alice"),
        ("get", "/api/stats"),
        ("get", "/api/image/q0/state.png"),
        ("get", "/api/subgoals"),
        ("get", "/api/subgoal/0.png"),
        ("post", "/api/answer"),
    ]
    for method, url in calls:
        assert getattr(client, method)(url).status_code == 401, url
        assert getattr(client, method)(url, headers={"X-Token": "wrong"}).status_code == 401, url
    assert client.get("/api/stats", headers={"X-Token": "s3cret"}).status_code == 200
    assert client.get("/api/stats", headers={"Authorization": "Bearer s3cret"}).status_code == 200
    assert client.get("/api/stats?token=s3cret").status_code == 200
    assert client.get("/api/image/q0/state.png?token=s3cret").status_code == 200
    payload = {"query_id": "q0", "label": "FIRST", "annotator": "alice"}
    assert client.post("/api/answer", json=payload).status_code == 401
    assert store.answered_ids() == set()
    assert client.post("/api/answer?token=s3cret", json=payload).status_code == 200
    assert client.get("/").status_code == 200  # the page itself holds no data


def test_subgoal_gallery_api(db):
    store, _ = db
    client = TestClient(create_app(store))
    assert client.get("/api/subgoals").json()["subgoals"] == []
    image = np.random.default_rng(1).integers(0, 255, (8, 8, 3), dtype=np.uint8)
    SubgoalTable(store).put(
        [{"id": 4, "image": image, "found_at": 120, "success_rate": 0.5, "chosen_recently": 2, "mean_score": -0.3}]
    )
    [record] = client.get("/api/subgoals").json()["subgoals"]
    assert record == {
        "id": 4,
        "found_at": 120,
        "success_rate": 0.5,
        "chosen_recently": 2,
        "mean_score": -0.3,
        "name": None,
        "image": "/api/subgoal/4.png",
    }
    np.testing.assert_array_equal(decode_png(client.get(record["image"]).content), image)
    assert client.get("/api/subgoal/5.png").status_code == 404
    assert client.get("/gallery").status_code == 200


def test_invalid_arguments_and_binding_rules():
    store = PreferenceStore()
    with pytest.raises(ValueError, match="reply_window_s must be > 0"):
        create_app(store, reply_window_s=0)
    with pytest.raises(ValueError, match="PreferenceStore"):
        create_app("prefs.db")
    assert is_loopback("127.0.0.1") and is_loopback("localhost") and is_loopback("::1")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.4")
    check_bind("127.0.0.1", None)
    check_bind("0.0.0.0", "t")
    with pytest.raises(ValueError, match="pass a token"):
        check_bind("0.0.0.0", None)
    with pytest.raises(ValueError, match="pass a token"):
        LabelServer(store, host="0.0.0.0")
    with pytest.raises(ValueError, match="port must be"):
        LabelServer(store, port=70000)


def test_label_server_serves_on_a_free_port(db):
    store, _ = db
    with LabelServer(store, token="t0k") as server:
        assert server.url.startswith("http://127.0.0.1:") and server.url.endswith("/?token=t0k")
        base = server.url.split("?")[0]
        assert httpx.get(base + "api/stats", timeout=5).status_code == 401
        response = httpx.post(
            base + "api/answer",
            json={"query_id": "q2", "label": "SECOND", "annotator": "dora"},
            headers={"X-Token": "t0k"},
            timeout=5,
        )
        assert response.status_code == 200
    assert store.get_answer("q2").annotator == "dora"
    with pytest.raises(httpx.TransportError):
        httpx.get(base + "api/stats", timeout=1)


def test_cli_refuses_a_public_host_without_token(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "sb3_hhp.label", "--db", str(tmp_path / "p.db"), "--host", "0.0.0.0"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode != 0 and "token" in result.stderr


def test_web_oracle_collects_answers_from_any_process(tmp_path):
    path = tmp_path / "prefs.db"
    trainer_store = PreferenceStore(path)
    oracle = WebOracle(trainer_store, run_id="run-1")
    with pytest.raises(NotImplementedError):
        oracle.answer(make_query(0))
    oracle.submit([make_query(0), make_query(1)])
    assert oracle.pending() == 2 and trainer_store.count_asked("run-1") == 2
    assert oracle.collect() == []

    annotator_store = PreferenceStore(path)  # what a `python -m sb3_hhp.label --db` process opens
    client = TestClient(create_app(annotator_store))
    assert client.post("/api/answer", json={"query_id": "q1", "label": "SECOND", "annotator": "eve"}).status_code == 200
    [answer] = oracle.collect()
    assert (answer.query_id, answer.label, answer.annotator) == ("q1", Label.SECOND, "eve")
    assert oracle.collect() == [] and oracle.pending() == 1
    annotator_store.add_answer("q0", "EQUAL", "frank")
    [(query, answer)] = oracle.collect_pairs()
    assert query.query_id == "q0" and answer.annotator == "frank"

    # a resumed run starts after the answers it had already; start_seq=0 replays them all
    assert WebOracle(trainer_store).collect() == []
    assert [a.query_id for a in WebOracle(trainer_store, start_seq=0).collect()] == ["q1", "q0"]
    annotator_store.close()
    trainer_store.close()


def minigrid_query(query_id: str = "m0", signature: str = "s0"):
    """A question about a real DoorKey state, with the facts and names training writes into ``info``."""
    import gymnasium as gym
    import minigrid  # noqa: F401

    from sb3_hhp.goals.minigrid import MiniGridEgocentricObs, MiniGridGoalSpace

    env = MiniGridEgocentricObs(gym.make("MiniGrid-DoorKey-8x8-v0", render_mode="rgb_array"))
    env.reset(seed=3)
    goal_space = MiniGridGoalSpace()
    facts = goal_space.privileged(env)
    keys = [(5, 4, 2), ("success",)]  # carrying the key facing the locked door; the task solved
    query = make_query(0)
    query.query_id = query_id
    query.info = {
        "state": facts,
        "goal1_key": list(keys[0]),
        "goal2_key": list(keys[1]),
        "goal1_name": goal_space.describe(keys[0]),
        "goal2_name": goal_space.describe(keys[1]),
        "signature": signature,
    }
    env.close()
    return query, facts, keys


def test_sub_goals_are_named_and_drawn_in_the_current_room(db):
    from sb3_hhp.goals.minigrid import HIGHLIGHT_RGB, MiniGridGoalSpace
    from sb3_hhp.label.app import LAYOUT_TILE

    store, _ = db
    query, facts, keys = minigrid_query()
    store.add_query(query)
    store.add_query(minigrid_query("m1", signature="s0")[0])  # the same question asked twice
    store.set_query_budget(50)
    for query_id in ("q0", "q1", "q2"):
        store.add_answer(query_id, "EQUAL", "someone")
    client = TestClient(create_app(store))
    body = client.get("/api/next", params={"annotator": "alice"}).json()
    assert (body["asked"], body["budget"], body["queued"]) == (5, 50, 2)
    assert (body["distinct"], body["signed"]) == (1, 2)  # two asked, one distinct
    question = body["query"]
    assert question["query_id"] == "m0" and question["drawn_in_state"]
    assert question["goal1_name"] == "carrying key, facing locked door" and question["goal2_name"] == "task solved"

    goal_space = MiniGridGoalSpace(tile_size=LAYOUT_TILE)
    for which, key in (("goal1", keys[0]), ("goal2", keys[1]), ("state", None)):
        drawn = decode_png(client.get(question["images"][which]).content)
        np.testing.assert_array_equal(drawn, goal_space.image_in_state(facts, key))
    goal1 = decode_png(client.get(question["images"]["goal1"]).content)
    assert (goal1 == HIGHLIGHT_RGB).all(axis=-1).sum() > 0  # the key and the door are framed
    assert goal_space.concerned_cells(facts, keys[0]).sum() == 2 and goal_space.concerned_cells(facts, keys[1]).sum() == 1
    # the image from where the sub-goal was found stays one request away
    found = client.get(question["images"]["goal1_found"])
    np.testing.assert_array_equal(decode_png(found.content), query.goal1_image)
    assert "state_found" not in question["images"]


def test_an_answer_records_its_time_and_hands_over_the_next_question(db):
    store, _ = db
    client = TestClient(create_app(store))
    reply = client.post(
        "/api/answer", json={"query_id": "q0", "label": "FIRST", "annotator": "alice", "response_s": 1.5, "next": True}
    ).json()
    assert reply["next"]["query_id"] == "q1" and reply["next"]["goal1_name"] == "sub-goal #1"
    # without the state's facts (other goal spaces) people see the stored images, nothing to swap
    assert not reply["next"]["drawn_in_state"] and reply["next"]["images"]["goal1_found"] is None
    assert reply["your_median_s"] == 1.5 and reply["answered_by_you"] == 1
    # the next question is leased to alice: bob gets the one after
    assert client.get("/api/next", params={"annotator": "bob"}).json()["query"]["query_id"] == "q2"
    client.post("/api/answer", json={"query_id": "q1", "label": "SECOND", "annotator": "alice", "response_s": 2.5})
    assert client.get("/api/next", params={"annotator": "alice"}).json()["your_median_s"] == 2.0
    assert store.response_times("alice") == [1.5, 2.5] and store.response_times("bob") == []


def test_malformed_inputs_get_4xx_and_leave_the_db_unchanged(db):
    from sb3_hhp.label.app import MAX_BODY_BYTES, MAX_ID_LENGTH

    store, path = db
    SubgoalTable(store).put([{"id": 0, "image": np.zeros((4, 4, 3), np.uint8)}])
    client = TestClient(create_app(store))
    before = dump(path)
    answer = {"query_id": "q0", "label": "FIRST", "annotator": "alice"}
    huge = {**answer, "annotator": "a" * (5 * 1024 * 1024)}
    assert client.post("/api/answer", json=huge).status_code == 413  # read no further, stored nothing
    padded = client.post(
        "/api/answer", content=b" " * (MAX_BODY_BYTES + 1) + b"{}", headers={"content-type": "application/json"}
    )
    assert padded.status_code == 413
    long_id = client.post("/api/answer", json={**answer, "query_id": "q" * 3000})
    assert long_id.status_code == 422 and "q" * 100 not in long_id.text  # bounded, and never echoed back
    assert "query_id" in long_id.text  # says which field to fix
    for bad in (-1.0, 1e9, "soon"):
        assert client.post("/api/answer", json={**answer, "response_s": bad}).status_code == 422, bad
    paths = [
        "/api/subgoal/" + "9" * 23 + ".png",  # beyond SQLite's integers (a 500 once)
        "/api/subgoal/-1.png",
        "/api/subgoal/abc.png",
        "/api/subgoal/1e3.png",
        "/api/image/" + "q" * (MAX_ID_LENGTH + 1) + "/state.png",
        "/api/image/q0/goal9.png",
        "/api/image/q0/" + "x" * 100 + ".png",
        "/api/image/%FF%FE/state.png",
        "/api/image/q0%00/state.png",
        "/api/next?annotator=" + "a" * 101,
    ]
    for url in paths:
        response = client.get(url)
        assert 400 <= response.status_code < 500, (url, response.status_code)
        assert len(response.content) < 2000, url
    assert client.get("/api/subgoal/0.png").status_code == 200
    assert dump(path) == before


def test_cli_refuses_a_missing_db_unless_asked_to_create(tmp_path, capsys):
    from sb3_hhp.label.__main__ import main

    missing = tmp_path / "typo.sqlite"
    assert main(["--db", str(missing)]) == 2
    message = capsys.readouterr().err
    assert "--create" in message and str(missing) in message
    assert not missing.exists() and list(tmp_path.iterdir()) == []
    assert main(["--db", str(tmp_path / "no" / "such" / "folder.sqlite"), "--create"]) == 2
    assert "folder does not exist" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
