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
from sb3_hhp.preferences.store import PreferenceStore, decode_png


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
    store.put_subgoals(
        [{"id": 4, "image": image, "found_at": 120, "success_rate": 0.5, "chosen_recently": 2, "mean_score": -0.3}]
    )
    [record] = client.get("/api/subgoals").json()["subgoals"]
    assert record == {
        "id": 4,
        "found_at": 120,
        "success_rate": 0.5,
        "chosen_recently": 2,
        "mean_score": -0.3,
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
