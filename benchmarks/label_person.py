"""A person at the labeling page, played by headless Chromium: how fast the page is, and whether it fits.

The script fills a preference store with questions about real MiniGrid DoorKey-8x8 states (privileged
facts, sub-goal keys and names as training writes them), serves it with :class:`LabelServer`, and
answers every question from the page the way a person would: it reads the two sub-goal names shown
and presses the left or right arrow key for the one closer to solving the task ("=" when both are
as good, "x" when it cannot tell). It measures the page's side only:

- latency: from the key press to the next question rendered (its images decoded, its buttons live),
  as the page's own clock (``performance.now``) records it; target <= 0.3 s;
- fit: every control (the names, the three images, the answer buttons) lies inside the window, with
  no scrolling, at 1280x720 (each question) and at 1366x768 and 1920x1080 (one question each).

It writes a small JSON result and, with ``--screenshots``, the page at 1280x720 and 1920x1080::

    python benchmarks/label_person.py --questions 40 --out benchmarks/results/label_person.json \\
        --screenshots docs/screenshots

With ``--env`` a Fetch task (``FetchReach-v4``, ``FetchPush-v4``, ``FetchPickAndPlace-v4``), the questions are
about states of random-action episodes of that task (the object, where there is one, lies where each reset put
it), between places those episodes found at least ``distance_threshold`` apart (the discovery gate's
``b_similarity = 0.5``). Each shows the state's rendered scene (MuJoCo headless, ``MUJOCO_GL=egl`` unless set; the
table top seen by :data:`~sb3_hhp.goals.fetch.TABLE_CAMERA`) and each sub-goal's scene where it was found, or the
goal space's drawings where the env cannot render. The person's answer is then
:class:`~sb3_hhp.oracles.fetch.FetchScriptedOracle`'s on the question's facts
(:meth:`~sb3_hhp.goals.fetch.FetchGoalSpace.query_info`), and the screenshots are named ``*_fetch_*.png``::

    python benchmarks/label_person.py --env FetchPush-v4 --questions 40 --screenshots docs/screenshots
"""

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Optional

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import numpy as np

from sb3_hhp.goals.base import SUCCESS_KEY, GoalSpace
from sb3_hhp.goals.fetch import TABLE_CAMERA, FetchFlatObs, FetchGoalSpace
from sb3_hhp.goals.minigrid import GOAL, MiniGridEgocentricObs, MiniGridGoalSpace
from sb3_hhp.label.server import LabelServer
from sb3_hhp.oracles.base import Label, Query
from sb3_hhp.oracles.fetch import FetchScriptedOracle
from sb3_hhp.preferences.store import PreferenceStore
from sb3_hhp.subgoal_table import SubgoalTable

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update"]
ENV_ID = "MiniGrid-DoorKey-8x8-v0"
FETCH_ENV_IDS = ("FetchReach-v4", "FetchPush-v4", "FetchPickAndPlace-v4")
#: random-action episodes of a Fetch task that the questions are drawn from (50 steps each)
FETCH_EPISODES = 20
TARGET_LATENCY_S = 0.3
#: what the person knows of DoorKey, in the words the page uses: a sub-goal whose name holds an earlier
#: phrase is closer to solving the task
PREFERENCE = ("task solved", "carrying key, facing open door", "carrying key, facing locked door", "facing key")
#: every control a person needs, which must be inside the window without scrolling
CONTROLS = (
    "#goal1-name", "#goal2-name", "#img-goal1", "#img-state", "#img-goal2",
    "#btn-first", "#btn-equal", "#btn-incomparable", "#btn-second",
)
KEY_OF_LABEL = {Label.FIRST: "ArrowLeft", Label.SECOND: "ArrowRight", Label.EQUAL: "=", Label.INCOMPARABLE: "x"}


def rank(name: str) -> int:
    """How close the sub-goal named ``name`` is to solving DoorKey (0: no idea)."""
    for position, phrase in enumerate(PREFERENCE):
        if phrase in name:
            return len(PREFERENCE) - position
    return 0


def decide(name1: str, name2: str) -> Label:
    """The person's answer, from the two names on the page."""
    first, second = rank(name1), rank(name2)
    if first == second:
        return Label.EQUAL if first > 0 else Label.INCOMPARABLE
    return Label.FIRST if first > second else Label.SECOND


def key_json(key: Any) -> list:
    return list(key) if isinstance(key, tuple) else [key]


def fill_store(store: PreferenceStore, n_questions: int, seed: int) -> None:
    """Questions about DoorKey-8x8 states visited by a random walk, between sub-goals the walk found."""
    rng = np.random.default_rng(seed)
    env = MiniGridEgocentricObs(gym.make(ENV_ID, render_mode="rgb_array"))
    goal_space = MiniGridGoalSpace()
    found: dict = {}  # sub-goal key -> the image of the state where it was first seen
    states: list[tuple[dict, np.ndarray, np.ndarray]] = []
    for episode in range(40):
        obs, _ = env.reset(seed=seed + episode)
        for step in range(120):
            key = goal_space.key(obs)
            if goal_space.is_milestone(key) and key not in found:
                found[key] = goal_space.render(env)
            if step % 15 == 0:
                states.append((goal_space.privileged(env), obs, goal_space.render(env)))
            obs, reward, terminated, truncated, _ = env.step(int(rng.integers(env.action_space.n)))
            if terminated and reward > 0:
                found.setdefault(SUCCESS_KEY, goal_space.render(env))
            if terminated or truncated:
                break
    env.close()
    if SUCCESS_KEY not in found:  # a random walk seldom solves DoorKey: draw a state with the agent on the goal square
        facts = dict(states[-1][0])
        goal_at = np.argwhere(np.asarray(facts["grid"])[..., 0] == GOAL)[0]
        facts["agent_pos"] = [int(v) for v in goal_at]
        found[SUCCESS_KEY] = goal_space.image_in_state(facts)
    keys = put_subgoals(store, goal_space, found)
    store.set_query_budget(n_questions + 10)
    for index in range(n_questions):
        facts, obs, frame = states[int(rng.integers(len(states)))]
        first, second = (int(i) for i in rng.choice(len(keys), size=2, replace=False))
        store.add_query(
            question(
                index, goal_space, keys, (first, second), obs, frame, (obs, obs),
                (found[keys[first]], found[keys[second]]), {"state": facts},
            )
        )


def put_subgoals(store: PreferenceStore, goal_space: GoalSpace, images: dict) -> list:
    """Write the sub-goals found (key -> image where it was found) into the store's table; their keys, in id order."""
    keys = sorted(images, key=repr)
    SubgoalTable(store).put(
        [
            {"id": i, "image": images[key], "found_at": 100 * i, "name": goal_space.describe(key), "chosen_recently": 0}
            for i, key in enumerate(keys)
        ]
    )
    return keys


def question(index: int, goal_space: GoalSpace, keys: list, goals: tuple[int, int], state: np.ndarray,
             state_image: np.ndarray, goal_obs: tuple[np.ndarray, np.ndarray], goal_images: tuple[np.ndarray, np.ndarray],
             info: dict) -> Query:
    """The ``index``-th question, between sub-goals ``goals`` (ids into ``keys``) in ``state``, with their keys and
    names in ``info`` as training writes them."""
    first, second = goals
    return Query(
        state=state, goal1=first, goal2=second, goal1_obs=goal_obs[0], goal2_obs=goal_obs[1],
        state_image=state_image, goal1_image=goal_images[0], goal2_image=goal_images[1],
        info={
            **info,
            "goal1_key": key_json(keys[first]),
            "goal2_key": key_json(keys[second]),
            "goal1_name": goal_space.describe(keys[first]),
            "goal2_name": goal_space.describe(keys[second]),
            "signature": f"benchmark-{index}",
        },
        query_id=f"q{index:04d}",
        asked_at=float(index),
    )


def fill_store_fetch(store: PreferenceStore, n_questions: int, seed: int, env_id: str) -> tuple[dict[str, Label], bool]:
    """Questions about states of random-action episodes of a Fetch task, between the places they found; returns
    the scripted oracle's answer to each question (by query id) and whether the scenes were rendered (else drawn)."""
    os.environ.setdefault("MUJOCO_GL", "egl")  # before MuJoCo is imported: render without a display
    import gymnasium_robotics  # noqa: F401  (registers the Fetch envs)

    rng = np.random.default_rng(seed)
    env = FetchFlatObs(gym.make(env_id, render_mode="rgb_array", default_camera_config=TABLE_CAMERA))
    goal_space = FetchGoalSpace()
    goal_space.bind(env)
    env.action_space.seed(seed)
    rendered = True

    def image(obs: np.ndarray) -> np.ndarray:
        nonlocal rendered
        frame = goal_space.render(env)
        rendered = rendered and frame is not None
        return goal_space.image_of(obs) if frame is None else frame

    found: dict = {}  # sub-goal key -> (the observation where it was first seen, its image)
    states: list[tuple[np.ndarray, np.ndarray]] = []
    for episode in range(FETCH_EPISODES):
        obs, _ = env.reset(seed=seed + episode)
        for step in range(env.spec.max_episode_steps or 50):
            key = goal_space.terminal_key(obs, 0.0, False)  # the task's goal where the target is reached
            new = key not in found and (
                key == SUCCESS_KEY
                or not found
                or goal_space.similarity(key, obs, list(found), None).max() < 0.5  # the discovery gate, b_similarity
            )
            picture = image(obs) if new or step % 10 == 0 else None  # one render a state
            if new:
                found[key] = (obs, picture)
            if step % 10 == 0:
                states.append((obs, picture))
            obs, *_ = env.step(env.action_space.sample())
    env.close()
    keys = put_subgoals(store, goal_space, {key: frame for key, (_, frame) in found.items()})
    oracle = FetchScriptedOracle(name="person")
    decided: dict[str, Label] = {}
    store.set_query_budget(n_questions + 10)
    for index in range(n_questions):
        obs, frame = states[int(rng.integers(len(states)))]
        first, second = (int(i) for i in rng.choice(len(keys), size=2, replace=False))
        (obs1, image1), (obs2, image2) = found[keys[first]], found[keys[second]]
        query = question(
            index, goal_space, keys, (first, second), obs, frame, (obs1, obs2), (image1, image2),
            goal_space.query_info(obs, obs1, obs2),
        )
        decided[query.query_id] = oracle.answer(query)
        store.add_query(query)
    return decided, rendered


FIT_JS = """(selectors) => {
  const width = window.innerWidth, height = window.innerHeight;
  const out = {width, height, scroll_width: document.documentElement.scrollWidth, outside: [], lowest: 0};
  for (const selector of selectors) {
    const rect = document.querySelector(selector).getBoundingClientRect();
    out.lowest = Math.max(out.lowest, rect.bottom);
    if (rect.top < 0 || rect.left < 0 || rect.bottom > height || rect.right > width || rect.width === 0)
      out.outside.push(selector);
  }
  return out;
}"""


def check_fit(page: Any) -> dict:
    """Which controls lie outside the window (scrolled to the top, as a question is shown)."""
    page.evaluate("window.scrollTo(0, 0)")
    fit = page.evaluate(FIT_JS, list(CONTROLS))
    if fit["scroll_width"] > fit["width"]:
        fit["outside"].append("(page wider than the window)")
    return fit


def wait_ready(page: Any, previous: Optional[str], timeout_ms: int = 20_000) -> Optional[str]:
    """Wait for the next question after ``previous`` to be ready (None when none is left)."""
    page.wait_for_function(
        """(previous) => {
          const main = document.getElementById('question');
          if (main.dataset.state === 'ready' && main.dataset.queryId !== previous) return true;
          return main.dataset.state === 'idle' && document.getElementById('status').textContent.startsWith('No question');
        }""",
        arg=previous or "",
        timeout=timeout_ms,
    )
    query_id = page.eval_on_selector("#question", "main => main.dataset.state === 'ready' ? main.dataset.queryId : ''")
    return query_id or None


def answer_one(
    page: Any, think_s: float, decided: Optional[dict[str, Label]] = None
) -> tuple[str, Label, Optional[str], float]:
    """Read the names, think, press the key (the answer in ``decided`` for the question shown, by its query id,
    when given, else the one the names tell); return (query id, label, next query id, latency in s)."""
    query_id = page.eval_on_selector("#question", "main => main.dataset.queryId")
    names = page.text_content("#goal1-name"), page.text_content("#goal2-name")
    label = decide(*names) if decided is None else decided[query_id]
    time.sleep(think_s)
    pressed_at = page.evaluate("performance.now()")
    page.keyboard.press(KEY_OF_LABEL[label])
    next_id = wait_ready(page, query_id)
    if next_id is None:
        return query_id, label, None, float("nan")
    shown_at = float(page.eval_on_selector("#question", "main => main.dataset.shownAt"))
    return query_id, label, next_id, (shown_at - pressed_at) / 1000.0


def open_page(browser: Any, url: str, width: int, height: int, annotator: str) -> Any:
    page = browser.new_page(viewport={"width": width, "height": height})
    page.errors = []
    page.on("pageerror", lambda error: page.errors.append(str(error)))
    page.goto(url)
    page.fill("#annotator", annotator)
    page.press("#annotator", "Enter")
    return page


def run(n_questions: int, seed: int, think_s: float, screenshots: Optional[Path], env_id: str = ENV_ID) -> dict:
    from playwright.sync_api import sync_playwright

    if not os.path.exists(CHROMIUM):
        raise SystemExit(f"{CHROMIUM} is missing: install Debian's chromium package (apt-get install chromium)")
    folder = tempfile.mkdtemp(prefix="label_person_")
    store = PreferenceStore(os.path.join(folder, "questions.sqlite"))
    oracle_answers: Optional[dict[str, Label]] = None  # None: the person decides by the names shown
    scenes = None
    if env_id in FETCH_ENV_IDS:
        oracle_answers, rendered = fill_store_fetch(store, n_questions, seed, env_id)
        scenes = "rendered" if rendered else "drawn"
    else:
        fill_store(store, n_questions, seed)
    shot = "fetch_" if env_id in FETCH_ENV_IDS else ""  # the screenshots' name: labeling_{shot}{size}.png
    decided: dict[str, Label] = {}
    latencies: list[float] = []
    fits: dict[str, list[dict]] = {"1280x720": [], "1366x768": [], "1920x1080": []}
    errors: list[str] = []
    with LabelServer(store, reply_window_s=30.0) as server, sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        try:
            for size, count in (("1366x768", 1), ("1920x1080", 1), ("1280x720", n_questions - 2)):
                width, height = (int(v) for v in size.split("x"))
                page = open_page(browser, server.url, width, height, "person")  # one person, three windows
                query_id = wait_ready(page, None)
                if screenshots is not None and size in ("1920x1080", "1280x720"):
                    screenshots.mkdir(parents=True, exist_ok=True)
                    page.screenshot(path=str(screenshots / f"labeling_{shot}{size}.png"))
                for _ in range(count):
                    if query_id is None:
                        break
                    fits[size].append(check_fit(page))
                    answered, label, query_id, latency = answer_one(page, think_s, oracle_answers)
                    decided[answered] = label
                    if query_id is not None:
                        latencies.append(latency)
                errors += page.errors
                page.close()
            if screenshots is not None:
                page = browser.new_page(viewport={"width": 1280, "height": 720})
                page.goto(server.url.replace("/?", "/gallery?") if "?" in server.url else server.url + "gallery")
                page.wait_for_function("document.querySelectorAll('#gallery img').length > 0", timeout=10_000)
                page.wait_for_timeout(500)
                page.screenshot(path=str(screenshots / f"gallery_{shot}1280x720.png"))
                page.close()
        finally:
            browser.close()
    stored = {answer.query_id: answer.label for _, _, answer in store.answers_since(0)}
    store.close()
    latencies_sorted = sorted(latencies)
    result = {
        "env": env_id,
        "questions": n_questions,
        "answered": len(stored),
        "answers_as_decided": sum(stored.get(qid) == label for qid, label in decided.items()),
        "labels": {label.name: sum(1 for v in stored.values() if v == label) for label in Label},
        "latency_s": {
            "measured": len(latencies),
            "median": round(statistics.median(latencies), 4) if latencies else None,
            "p95": round(latencies_sorted[int(0.95 * (len(latencies_sorted) - 1))], 4) if latencies else None,
            "max": round(max(latencies), 4) if latencies else None,
            "target": TARGET_LATENCY_S,
        },
        "fit": {
            size: {
                "questions_checked": len(checks),
                "needing_scroll": sum(1 for check in checks if check["outside"]),
                "outside": sorted({selector for check in checks for selector in check["outside"]}),
                "lowest_control_px": max((round(check["lowest"]) for check in checks), default=None),
            }
            for size, checks in fits.items()
        },
        "think_s": think_s,
        "page_errors": errors,
        "load_average": [round(v, 2) for v in os.getloadavg()],
        "cpu_count": os.cpu_count(),
    }
    if scenes is not None:
        result["scenes"] = scenes  # Fetch: the rendered scenes, or the goal space's drawings where MuJoCo cannot render
    return result


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--env", default=ENV_ID, choices=(ENV_ID, *FETCH_ENV_IDS), help="the task the questions are about"
    )
    parser.add_argument("--questions", type=int, default=40, help="questions to answer (>= 3)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random walk (episodes) and of the questions")
    parser.add_argument("--think", type=float, default=0.3, help="seconds the person looks before answering")
    parser.add_argument(
        "--out", default=None,
        help="the JSON result (default benchmarks/results/label_person.json, label_person_fetch.json for a Fetch task)",
    )
    parser.add_argument("--screenshots", default=None, help="folder for the page's screenshots (none when omitted)")
    args = parser.parse_args(argv)
    if args.questions < 3:
        parser.error(
            f"--questions must be >= 3 (one each at 1366x768 and 1920x1080, the rest at 1280x720), got {args.questions}"
        )
    result = run(args.questions, args.seed, args.think, Path(args.screenshots) if args.screenshots else None, args.env)
    result["command"] = "python benchmarks/label_person.py " + " ".join(argv if argv is not None else sys.argv[1:])
    out = Path(args.out or f"benchmarks/results/label_person{'_fetch' if args.env in FETCH_ENV_IDS else ''}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    latency_ok = result["latency_s"]["p95"] is not None and result["latency_s"]["p95"] <= TARGET_LATENCY_S
    fit_ok = all(entry["needing_scroll"] == 0 for entry in result["fit"].values())
    return 0 if latency_ok and fit_ok and not result["page_errors"] else 1


if __name__ == "__main__":
    sys.exit(main())
