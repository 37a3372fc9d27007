"""Calibrate the CI learning test (``tests/test_learning.py``) over training seeds: its training and evaluation,
seed by seed, each in a fresh process with one torch thread, and the table its docstring shows::

    python benchmarks/calibrate_learning_test.py --seeds 0 1 2 3 4 5 6 7 8 9 --jobs 2

Every seed must clear the test's bars (success rate and the margin of the mean return over the random policy's)
for the test not to hinge on the seed it trains.
"""

import argparse
import concurrent.futures
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def learning_test():
    """The CI learning test's module (its training, evaluation and bars), under the test session's settings (the
    pinned CPU kernels of ``tests/conftest.py``, set before torch is imported; the workers inherit them)."""
    if str(ROOT / "tests") not in sys.path:
        sys.path.insert(0, str(ROOT / "tests"))
    import conftest  # noqa: F401  (sets the environment as a test session has it)
    import test_learning

    return test_learning


def calibrate(seed: int) -> dict:
    import numpy as np
    import torch as th

    learning = learning_test()
    th.set_num_threads(1)
    begin = time.perf_counter()
    model = learning.train(seed)
    seconds = time.perf_counter() - begin
    returns = learning.hhp_returns(model, learning.EVAL_SEEDS)
    return dict(seed=seed, success_rate=float(np.mean(returns > 0)), mean_return=round(float(returns.mean()), 3),
                train_seconds=round(seconds, 1), questions=model.query_selector.used)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    parser.add_argument("--jobs", type=int, default=1, help="seeds at once, one process each")
    parser.add_argument("--out", default=None, help="a JSON file for the rows")
    args = parser.parse_args()
    learning = learning_test()  # before the workers start: they inherit the pinned kernels
    from conftest import PINNED_KERNELS  # the variables tests/conftest.py sets (on the path now)
    chance = learning.random_returns(learning.EVAL_SEEDS).mean()
    load = os.getloadavg()[0]
    with concurrent.futures.ProcessPoolExecutor(max_workers=args.jobs) as pool:
        rows = list(pool.map(calibrate, args.seeds))
    bar = chance + learning.MIN_RETURN_MARGIN
    print(f"random policy: mean return {chance:.3f}; bars: success {learning.MIN_SUCCESS_RATE}, mean return {bar:.3f}")
    print("train seed  success  mean return  train s  clears")
    for row in rows:
        clears = row["success_rate"] >= learning.MIN_SUCCESS_RATE and row["mean_return"] >= bar
        print(f"{row['seed']:>10}  {row['success_rate']:7.2f}  {row['mean_return']:11.3f}  {row['train_seconds']:7.1f}  {clears}")
    if args.out:
        Path(args.out).write_text(json.dumps(dict(rows=rows, random_mean_return=round(float(chance), 3), jobs=args.jobs,
                                                  load_average_start=round(load, 2), command=" ".join(sys.argv),
                                                  kernels={name: os.environ.get(name) for name in PINNED_KERNELS}), indent=2) + "\n")


if __name__ == "__main__":
    main()
