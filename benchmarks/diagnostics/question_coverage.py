"""Which sub-goals did a run's questions name, and how did the predictor score them? For every sub-goal of the run's
preference file (its gallery table): when it was found, how many questions named it, how many of their answers
preferred it, preferred the other sub-goal or called the two equal, and the predictor's mean score and recent
choices as the run last wrote them.

The meta-controller's preference bonus (eq. 3) is the predictor's score, centred on the best choosable sub-goal: a
sub-goal that no label names is scored by the predictor's extrapolation alone, and one scored low is seldom the
meta-controller's first or second choice, the pair a question shows with the paper's rule (``query_kwargs`` second
"meta").

    python benchmarks/diagnostics/question_coverage.py RUN/preferences.sqlite --out question_coverage.json
"""

import argparse
import json
import pathlib
import sys
from collections import Counter

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2]))
from sb3_hhp.preferences.store import PreferenceStore  # noqa: E402
from sb3_hhp.preferences.types import Label  # noqa: E402
from sb3_hhp.subgoal_table import SubgoalTable  # noqa: E402


def coverage(store: PreferenceStore) -> list[dict]:
    """One row per sub-goal of the gallery table: its record (without the image) and its questions' outcomes."""
    named, won, lost, equal = Counter(), Counter(), Counter(), Counter()
    for goal1, goal2, label in store.question_goals():
        named.update((goal1, goal2))
        if label == Label.EQUAL:
            equal.update((goal1, goal2))
        elif label in (Label.FIRST, Label.SECOND):
            winner, loser = (goal1, goal2) if label == Label.FIRST else (goal2, goal1)
            won[winner] += 1
            lost[loser] += 1
    rows = []
    for record in SubgoalTable(store).records(with_images=False):
        goal = record["id"]
        rows.append(dict(record, named=named[goal], won=won[goal], lost=lost[goal], equal=equal[goal]))
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("preferences", help="a run's preferences.sqlite")
    parser.add_argument("--out", help="write the rows as JSON here")
    args = parser.parse_args(argv)
    path = pathlib.Path(args.preferences)
    if not path.is_file():
        parser.error(f"no preference file at {path}")
    rows = coverage(PreferenceStore(path, create=False))
    if not rows:
        parser.error(f"{path} has no sub-goal table yet (the run writes it every 10 episodes)")
    print(f"{'id':>3} {'found at':>9} {'named':>5} {'won':>4} {'lost':>4} {'eq':>3} {'score':>7} {'chosen':>6}  name")
    for row in rows:
        score = "-" if row["mean_score"] is None else f"{row['mean_score']:.2f}"
        print(f"{row['id']:>3} {row['found_at']:>9} {row['named']:>5} {row['won']:>4} {row['lost']:>4} {row['equal']:>3} "
              f"{score:>7} {row['chosen_recently']:>6}  {row['name']}")
    never = [row["name"] for row in rows if row["named"] == 0]
    print(f"{len(never)} of {len(rows)} sub-goals named by no question")
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(dict(preferences=str(path), subgoals=rows), indent=1))


if __name__ == "__main__":
    main()
