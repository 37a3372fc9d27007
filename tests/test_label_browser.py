"""The labeling page driven by headless Chromium (the system's /usr/bin/chromium, never a download)."""

import os
import time

import numpy as np
import pytest

from sb3_hhp.label.server import LabelServer
from sb3_hhp.oracles.base import Label, Query
from sb3_hhp.preferences.store import PreferenceStore
from sb3_hhp.subgoal_table import SubgoalTable

pytestmark = pytest.mark.browser

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update"]


def make_query(seed: int) -> Query:
    rng = np.random.default_rng(seed)
    images = [rng.integers(0, 255, (8, 8, 3), dtype=np.uint8) for _ in range(3)]
    return Query(
        state=np.zeros(4, np.float32),
        goal1=seed,
        goal2=seed + 1,
        goal1_obs=np.zeros(4),
        goal2_obs=np.ones(4),
        state_image=images[0],
        goal1_image=images[1],
        goal2_image=images[2],
        query_id=f"q{seed}",
        asked_at=float(seed),
    )


@pytest.fixture(scope="module")
def browser():
    if not os.path.exists(CHROMIUM):
        if os.environ.get("CI"):
            pytest.fail(f"{CHROMIUM} is missing; install Debian's chromium package")
        pytest.skip(f"{CHROMIUM} is missing")
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        yield browser
        browser.close()


def wait_for(condition, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.05)


def open_page(browser, server: LabelServer, annotator: str):
    page = browser.new_page()
    page.errors = []
    page.on("pageerror", lambda error: page.errors.append(error))
    page.goto(server.url)
    page.fill("#annotator", annotator)
    page.press("#annotator", "Enter")
    return page


def test_answer_by_keyboard_and_by_click(browser):
    store = PreferenceStore()
    for seed in range(4):
        store.add_query(make_query(seed))
    with LabelServer(store, token="tok", reply_window_s=30.0) as server:
        page = open_page(browser, server, "alice")
        try:
            page.wait_for_selector('#question[data-query-id="q0"]', timeout=10_000)
            page.wait_for_selector("#btn-first:enabled", timeout=10_000)  # images shown, countdown running
            assert page.eval_on_selector("#img-goal1", "img => img.getBoundingClientRect().width") >= 256
            assert page.text_content("#queued") == "4"
            page.keyboard.press("ArrowLeft")
            page.wait_for_selector('#question[data-query-id="q1"]', timeout=10_000)
            page.click("#btn-second")
            page.wait_for_selector('#question[data-query-id="q2"]', timeout=10_000)
            page.keyboard.press("=")
            page.wait_for_selector('#question[data-query-id="q3"]', timeout=10_000)
            page.keyboard.press("x")
            wait_for(lambda: len(store.answered_ids()) == 4)
            page.wait_for_function("document.getElementById('answers-mine').textContent === '4'", timeout=10_000)
            assert page.errors == []
        finally:
            page.close()
    answers = {a.query_id: (a.label, a.annotator) for _, _, a in store.answers_since(0)}
    assert answers == {
        "q0": (Label.FIRST, "alice"),
        "q1": (Label.SECOND, "alice"),
        "q2": (Label.EQUAL, "alice"),
        "q3": (Label.INCOMPARABLE, "alice"),
    }


def test_the_countdown_answers_cant_tell(browser):
    store = PreferenceStore()
    store.add_query(make_query(0))
    with LabelServer(store, reply_window_s=1.5) as server:
        page = open_page(browser, server, "bob")
        try:
            page.wait_for_selector('#question[data-query-id="q0"]', timeout=10_000)
            started = time.monotonic()
            wait_for(lambda: "q0" in store.answered_ids(), timeout=10.0)  # nobody touches the page
            assert time.monotonic() - started >= 1.0  # not before the reply window ran out
            page.wait_for_selector("#history li", timeout=5_000)
            assert "time ran out" in page.text_content("#history li")
            assert page.errors == []
        finally:
            page.close()
    [(_, _, answer)] = store.answers_since(0)
    assert (answer.query_id, answer.label, answer.annotator) == ("q0", Label.INCOMPARABLE, "bob")


def test_the_gallery_page_shows_every_subgoal(browser):
    store = PreferenceStore()
    image = np.random.default_rng(0).integers(0, 255, (8, 8, 3), dtype=np.uint8)
    SubgoalTable(store).put(
        [
            {"id": 0, "image": image, "found_at": 0, "success_rate": None, "chosen_recently": 0, "mean_score": None},
            {"id": 7, "image": image, "found_at": 900, "success_rate": 0.75, "chosen_recently": 4, "mean_score": 0.25},
        ]
    )
    with LabelServer(store, token="tok") as server:
        page = browser.new_page()
        errors = []
        page.on("pageerror", lambda error: errors.append(error))
        try:
            page.goto(server.url.replace("/?", "/gallery?"))
            page.wait_for_function(
                "[...document.querySelectorAll('#gallery img')].filter(i => i.complete && i.naturalWidth === 8).length === 2",
                timeout=10_000,
            )
            caption = page.text_content('figure[data-subgoal-id="7"] figcaption')
            assert "#7" in caption and "900" in caption and "75 %" in caption and "chosen 4" in caption
            assert "0.250" in caption
            assert page.text_content("#count") == "2"
            assert errors == []
        finally:
            page.close()


def minigrid_query(query_id: str, signature: str) -> Query:
    """A question about a real DoorKey state, with the facts and names training writes into ``info``."""
    import gymnasium as gym
    import minigrid  # noqa: F401

    from sb3_hhp.goals.minigrid import MiniGridEgocentricObs, MiniGridGoalSpace

    env = MiniGridEgocentricObs(gym.make("MiniGrid-DoorKey-8x8-v0", render_mode="rgb_array"))
    env.reset(seed=3)
    goal_space = MiniGridGoalSpace()
    keys = [(5, 4, 2), ("success",)]  # carrying the key facing the locked door; the task solved
    query = make_query(0)
    query.query_id = query_id
    query.info = {
        "state": goal_space.privileged(env),
        "goal1_key": list(keys[0]),
        "goal2_key": list(keys[1]),
        "goal1_name": goal_space.describe(keys[0]),
        "goal2_name": goal_space.describe(keys[1]),
        "signature": signature,
    }
    env.close()
    return query


def test_a_person_sees_names_no_broken_images_and_every_control_without_scrolling(browser):
    store = PreferenceStore()
    store.add_query(minigrid_query("m0", signature="s0"))
    store.add_query(minigrid_query("m1", signature="s1"))
    store.set_query_budget(20)
    with LabelServer(store, reply_window_s=30.0) as server:
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        errors = []
        page.on("pageerror", lambda error: errors.append(error))
        try:
            page.goto(server.url)  # no name yet: empty boxes, never a broken-image sign
            hidden = page.eval_on_selector_all(".panels img", "imgs => imgs.map(i => getComputedStyle(i).visibility)")
            assert hidden == ["hidden", "hidden", "hidden"]
            page.fill("#annotator", "carol")
            page.press("#annotator", "Enter")
            page.wait_for_selector('#question[data-state="ready"]', timeout=10_000)
            assert page.text_content("#goal1-name") == "carrying key, facing locked door"
            assert page.text_content("#goal2-name") == "task solved"
            assert page.text_content("#budget") == "20" and page.text_content("#distinct") == "2 / 2"
            outside = page.evaluate(
                """() => ['#goal1-name', '#goal2-name', '#img-goal1', '#img-state', '#img-goal2', '#btn-first',
                          '#btn-second', '#btn-equal', '#btn-incomparable'].filter(s => {
                  const r = document.querySelector(s).getBoundingClientRect();
                  return r.bottom > innerHeight || r.right > innerWidth || r.width === 0; })"""
            )
            assert outside == []
            left = page.eval_on_selector("#img-goal1", "i => i.getBoundingClientRect().left")
            right = page.eval_on_selector("#img-goal2", "i => i.getBoundingClientRect().left")
            assert left < right  # the left arrow answers for the image on the left
            drawn = page.get_attribute("#img-goal1", "src")
            page.keyboard.press("e")  # the image from where the sub-goal was found
            page.wait_for_function("document.getElementById('img-goal1').src.includes('goal1_found')", timeout=5_000)
            page.keyboard.press("e")
            page.wait_for_function(f"document.getElementById('img-goal1').getAttribute('src') === {drawn!r}", timeout=5_000)
            page.keyboard.press("ArrowRight")
            page.wait_for_selector('#question[data-query-id="m1"][data-state="ready"]', timeout=10_000)
            page.wait_for_function("document.getElementById('median-mine').textContent.endsWith(' s')", timeout=5_000)
            assert errors == []
        finally:
            page.close()
    assert store.get_answer("m0").label == Label.SECOND
    [seconds] = store.response_times("carol")
    assert 0 < seconds < 30
