"""Does a run's preference predictor order its own labels? For every answered question of the run's preference file,
the trained predictor's scores of the two sub-goals in the question's state, and whether the label agrees.

A predictor that contradicts labels it was trained on passes the wrong ranking to the meta-controller's bonus (eq. 3):
with ``center_bonus="max"`` the choice it scores best earns 0 and the one a person preferred a penalty.

    python benchmarks/diagnostics/predictor_labels.py RUN/MiniGrid-DoorKey-16x16-v0.zip RUN/preferences.sqlite \\
        --out predictor_labels.json
"""

import argparse
import json
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2]))
from sb3_hhp import HhP  # noqa: E402
from sb3_hhp.preferences.store import PreferenceStore  # noqa: E402
from sb3_hhp.preferences.types import Label  # noqa: E402


def label_agreement(model: HhP, store: PreferenceStore) -> list[dict]:
    """One row per answered question with a preference (FIRST or SECOND), in the order they were answered."""
    rows = []
    for _, query, answer in store.answers_since(0):
        if answer.label not in (Label.FIRST, Label.SECOND):
            continue
        state, goal1, goal2 = model.query_inputs(query)  # as the run fed the label to the predictor
        scores = model.predictor.score(np.stack([state, state]), np.stack([goal1, goal2]))
        info = query.info or {}
        rows.append(dict(goal1=info.get("goal1_name", query.goal1), goal2=info.get("goal2_name", query.goal2),
                         label=answer.label.name, scores=[round(float(x), 4) for x in scores],
                         agrees=bool((scores[0] > scores[1]) == (answer.label == Label.FIRST))))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", help="the run's model .zip")
    parser.add_argument("store", help="the run's preferences.sqlite")
    parser.add_argument("--out", default=None, help="write the rows as JSON here")
    args = parser.parse_args()
    model = HhP.load(args.model, device="cpu")
    with PreferenceStore(args.store, create=False) as store:
        rows = label_agreement(model, store)
    for row in rows:
        print(f"{'agrees    ' if row['agrees'] else 'CONTRADICTS'} {row['label']:6s} {row['scores']}  "
              f"{row['goal1']}  vs  {row['goal2']}")
    print(f"{sum(row['agrees'] for row in rows)} of {len(rows)} labels ordered as answered")
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(dict(model=args.model, store=args.store, rows=rows), indent=1))


if __name__ == "__main__":
    main()
