"""Train HhP while a person answers its questions in a web browser.

HhP queues each question (the current state and two sub-goal images) in a SQLite preference store;
a labeling server, running in a background thread of this process, serves the store as a web page.
Open the printed URL and click which sub-goal is better; training never waits for you, and every
answer is kept in the store, so a later run (same ``--db``) learns from it and never asks again.

    python examples/label_in_browser.py                          # a short run; open the URL it prints
    python examples/label_in_browser.py --steps 50000 --no-wait    # stop serving when training ends

After training, the page stays open until every question asked has been answered (or Ctrl-C), and a second
``learn`` call then feeds those answers to the predictor.

The same page can also be served by another process: ``python -m sb3_hhp.label --db labels.sqlite``.
"""

import argparse
import os
import tempfile
import time
from collections import Counter

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid envs)
import torch as th

from sb3_hhp import HhP
from sb3_hhp.label.server import LabelServer
from small_settings import SMALL_ENV, SMALL_SETTINGS


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default=SMALL_ENV, help="a MiniGrid env id")
    parser.add_argument("--steps", type=int, default=8_000, help="training length in primitive env steps")
    parser.add_argument("--budget", type=int, default=20, help="questions a person may be asked over training")
    parser.add_argument("--db", default=None, help="the preference store (SQLite file); default: a new temporary file")
    parser.add_argument("--host", default="127.0.0.1", help="address of the page (anything but loopback needs --token)")
    parser.add_argument("--port", type=int, default=0, help="TCP port of the page (0: a free one)")
    parser.add_argument("--token", default=None, help="access token of the page (required beyond this machine)")
    parser.add_argument("--reply-window", type=float, default=30.0,
                        help="seconds per question before the page answers CAN'T TELL")
    parser.add_argument("--wait", type=float, default=0.0, help="seconds to wait before training, to open the page")
    parser.add_argument("--no-wait", action="store_true",
                        help="stop serving when training ends, even if questions are still open")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    th.set_num_threads(args.threads)
    db = args.db or os.path.join(tempfile.mkdtemp(prefix="hhp_labels_"), "labels.sqlite")
    model = HhP(
        "MlpPolicy",
        gym.make(args.env),
        oracle="web",  # questions go to the store; answers come back from the page
        preference_db=db,
        query_budget=args.budget,
        **SMALL_SETTINGS,
        seed=args.seed,
    )
    server = LabelServer(model.store, host=args.host, port=args.port, token=args.token, reply_window_s=args.reply_window)
    with server:
        print(f"label the questions at {server.url}")
        print(f"preference store: {db}")
        if args.wait > 0:
            time.sleep(args.wait)
        model.learn(args.steps)
        asked = model.store.count_asked()
        answers = Counter(answer.label.name for _, _, answer in model.store.answers_since(0))
        print(f"{model.num_timesteps} primitive steps, {len(model.subgoals)} sub-goals")
        print(f"questions asked: {asked} of {args.budget}; answered: {sum(answers.values())} {dict(answers)}")
        print(f"labels the predictor learnt from: {len(model.predictor)}")
        if not args.no_wait:
            wait_for_answers(model, server.url)
    model.store.close()


def wait_for_answers(model: HhP, url: str) -> None:
    """Serve the page until every question asked has an answer (or Ctrl-C), then learn from the answers."""
    store = model.store
    waiting = len(store.open_query_ids())
    if waiting == 0:
        return
    print(f"training is done; {waiting} questions wait for you at {url} (Ctrl-C to stop)")
    try:
        while store.open_query_ids():
            time.sleep(1.0)
    except KeyboardInterrupt:
        print("stopped: the open questions stay in the store for a later run")
        return
    added = model.resume_preferences()  # the answers given after training, into the predictor
    print(f"all questions answered; the predictor learnt {added} more labels ({len(model.predictor)} in all)")


if __name__ == "__main__":
    main()
