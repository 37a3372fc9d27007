"""How much of a plan's choices an order of sub-goals explains: Bradley-Terry scores fitted by table, not by network.

``predictor_placement.py`` found that on ObstructedMaze-1Q a fresh predictor taught 100 labels on the plan's own states
matches the plan's choice in 0.77-0.79 of unseen states, while the inputs it reads would allow 0.92-0.96 in-sample
(``oracle_choices.py``'s feature ceiling). This fits the simplest scorers that could explain the plan's choices and
asks which of them the labels reach: a score per sub-goal plus, by ``--conditions``,

- ``goal``: nothing else (one order of the sub-goals, whatever the state),
- ``key``: a score per sub-goal for each distinct state key (the first ``--key-dims`` features of what the predictor
  reads of a state: on MiniGrid what is carried and faced and the goal space's flags),
- ``full``: a score per sub-goal for each distinct input of a state (a lookup of the states met);

fitted by maximum likelihood of the Bradley-Terry model (eq. 1, 2 of the paper) with an L2 penalty, first on every
pair the plan's ranks order in every training choice (what these scorers could learn from unlimited questions on those
states; also fitted to the test choices' own pairs, the most such scores can match there, beside the feature
ceilings), then on ``--labels`` questions naming two choosable sub-goals at random in random training states (as
``predictor_placement.py --pairs random``). Each is scored as ``predictor_placement.py`` scores a predictor: the
fraction of the test choices whose best-scored choosable sub-goal is among the plan's best. Reads the plan's choices
that ``predictor_placement.py --records`` keeps (no episode is played)::

    python benchmarks/diagnostics/choice_orders.py RECORDS.pkl --labels 50 100 200 800 \\
        --out benchmarks/results/diagnostics/choice_orders.json
"""

import argparse
import json
import pathlib
import pickle
import sys
from typing import Callable, Optional

import numpy as np
from scipy.optimize import minimize

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2]))
from benchmarks.diagnostics.oracle_choices import feature_ceiling  # noqa: E402
from benchmarks.diagnostics.predictor_placement import ask, matched  # noqa: E402
from sb3_hhp.preferences.types import Label  # noqa: E402

CONDITIONS = ("goal", "key", "full")


def state_key(condition: str, key_dims: int) -> Callable[[dict], bytes]:
    """The part of a record's state a ``condition``'s scores depend on, as bytes."""
    if condition == "goal":
        return lambda record: b""
    if condition == "key":
        return lambda record: record["inputs"][:key_dims].tobytes()
    if condition == "full":
        return lambda record: record["inputs"].tobytes()
    raise ValueError(f"unknown condition {condition!r}: one of {CONDITIONS}")


class TableOrder:
    """Bradley-Terry scores ``w[g] + c[k(s), g]`` over ``n_goals`` sub-goals, ``k`` a state's key (``key``); fitted
    to ``(record, preferred, other)`` triples by L-BFGS on the cross-entropy of eq. 1, 2 plus ``penalty`` times the
    squared scores. A key no triple held scores by ``w`` alone."""

    def __init__(self, n_goals: int, key: Callable[[dict], bytes], penalty: float = 0.1) -> None:
        self.n_goals, self.key, self.penalty = n_goals, key, penalty
        self.keys: dict = {}
        self.w = np.zeros(n_goals)
        self.c = np.zeros((0, n_goals))

    def fit(self, triples: list[tuple[dict, int, int]]) -> "TableOrder":
        self.keys = {}
        rows = np.array([self.keys.setdefault(self.key(record), len(self.keys)) for record, _, _ in triples], dtype=int)
        if not triples:
            self.c = np.zeros((0, self.n_goals))
            return self
        won = np.array([g for _, g, _ in triples])
        lost = np.array([g for _, _, g in triples])
        n, k = self.n_goals, len(self.keys)

        def loss(theta: np.ndarray) -> tuple[float, np.ndarray]:
            w, c = theta[:n], theta[n:].reshape(k, n)
            margin = w[won] + c[rows, won] - w[lost] - c[rows, lost]
            nll = np.logaddexp(0.0, -margin).sum()  # -log sigmoid(margin)
            slope = -1.0 / (1.0 + np.exp(margin))  # d nll / d margin
            grad_w, grad_c = np.zeros(n), np.zeros((k, n))
            np.add.at(grad_w, won, slope)
            np.add.at(grad_w, lost, -slope)
            np.add.at(grad_c, (rows, won), slope)
            np.add.at(grad_c, (rows, lost), -slope)
            value = nll + self.penalty * float(theta @ theta)
            return value, np.concatenate([grad_w, grad_c.ravel()]) + 2.0 * self.penalty * theta

        result = minimize(loss, np.zeros(n * (k + 1)), jac=True, method="L-BFGS-B")
        self.w, self.c = result.x[:n], result.x[n:].reshape(k, n)
        return self

    def scores(self, record: dict) -> np.ndarray:
        row = self.keys.get(self.key(record))
        return self.w if row is None else self.w + self.c[row]


def agreement(order: TableOrder, records: list[dict]) -> float:
    """The fraction of ``records`` whose best-scored choosable sub-goal is among the plan's best."""
    return matched(np.array([order.scores(record) for record in records]), records)


def every_pair(records: list[dict]) -> list[tuple[dict, int, int]]:
    """Every ``(record, preferred, other)`` the plan's ranks order among a record's choosable sub-goals."""
    triples = []
    for record in records:
        ranks = np.asarray(record["ranks"])
        for a in record["choosable"]:
            triples += [(record, int(a), int(b)) for b in record["choosable"] if ranks[a] < ranks[b]]
    return triples


def random_labels(records: list[dict], count: int, seed: int) -> list[tuple[dict, int, int]]:
    """``count`` questions naming two choosable sub-goals at random in random states of ``records`` (two or more
    choosable), answered by the plan's ranks; ties teach nothing (spent, not kept)."""
    rng = np.random.default_rng(seed)
    usable = [record for record in records if len(record["choosable"]) >= 2]
    triples: list = []
    for _ in range(count if usable else 0):
        record, a, b, label = ask(usable, "random", None, rng)
        if label is not Label.INCOMPARABLE:
            triples.append((record, a, b) if label is Label.FIRST else (record, b, a))
    return triples


def study(train: list[dict], test: list[dict], conditions: list[str], labels: list[int], repeats: int,
          key_dims: int, penalty: float, report: Optional[Callable[[str], None]] = print) -> dict:
    """Each condition's test (and training) agreement fitted on every training pair, then on each count of
    ``labels`` random questions (``repeats`` draws)."""
    n_goals = len(train[0]["ranks"])
    train_pairs, test_pairs = every_pair(train), every_pair(test)
    results: dict = {}
    for condition in conditions:
        key = state_key(condition, key_dims)
        everything = TableOrder(n_goals, key, penalty).fit(train_pairs)
        on_test = TableOrder(n_goals, key, penalty).fit(test_pairs)  # in sample: the most such scores can match
        entry = dict(keys=len(everything.keys), every_pair=dict(test=agreement(everything, test),
                                                                 train=agreement(everything, train)),
                     in_sample_test=agreement(on_test, test), labels={})
        if report:
            report(f"{condition:>5}: {entry['keys']} state keys; every training pair: test {entry['every_pair']['test']:.2f}"
                   f" (train {entry['every_pair']['train']:.2f}); fitted to every test pair: test "
                   f"{entry['in_sample_test']:.2f}")
        for count in labels:
            tests = [agreement(TableOrder(n_goals, key, penalty).fit(random_labels(train, count, seed)), test)
                     for seed in range(repeats)]
            entry["labels"][count] = tests
            if report:
                report(f"       {count:4d} random labels: test {np.mean(tests):.2f} (" +
                       ", ".join(f"{t:.2f}" for t in tests) + ")")
        results[condition] = entry
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("records", help="the plan's choices kept by predictor_placement.py --records")
    parser.add_argument("--conditions", nargs="+", default=list(CONDITIONS), choices=CONDITIONS)
    parser.add_argument("--labels", type=int, nargs="+", default=[50, 100, 200, 800])
    parser.add_argument("--repeats", type=int, default=3, help="draws of the labels per count (seeds 0, 1, ...)")
    parser.add_argument("--key-dims", type=int, default=30,
                        help="the features of a state that make its key (MiniGrid: carried, faced and flags come first)")
    parser.add_argument("--penalty", type=float, default=0.1, help="L2 penalty on the scores")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    if args.repeats < 1 or min(args.labels) < 1 or args.key_dims < 0 or args.penalty < 0:
        parser.error("--repeats and --labels must be >= 1, --key-dims and --penalty >= 0")
    path = pathlib.Path(args.records)
    if not path.exists():
        parser.error(f"{path} does not exist: write it with predictor_placement.py MODEL --records {path}")
    train, test = pickle.loads(path.read_bytes())
    if not train or not test:
        parser.error(f"{path} holds {len(train)} training and {len(test)} test choices: both must hold some")
    ceilings = {name: feature_ceiling(records) for name, records in (("train", train), ("test", test))}
    ceilings = {name: c["ceiling"] / max(c["choices"], 1) for name, c in ceilings.items()}
    print(f"{path}: {len(train)} training choices, {len(test)} test choices, {len(train[0]['ranks'])} sub-goals; "
          f"feature ceilings: train {ceilings['train']:.2f}, test {ceilings['test']:.2f}")
    results = study(train, test, args.conditions, sorted(args.labels), args.repeats, args.key_dims, args.penalty)
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(dict(
            records=str(path), train_choices=len(train), test_choices=len(test), feature_ceilings=ceilings,
            key_dims=args.key_dims,
            penalty=args.penalty, repeats=args.repeats, conditions=results), indent=1))


if __name__ == "__main__":
    main()
