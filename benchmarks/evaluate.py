"""Evaluate saved HhP models again on the episodes their run was evaluated on, with options given to ``HhP.load``.

A run of the benchmark runner (or ``sb3_hhp.train``) is evaluated once, at its end, on ``--episodes`` fresh envs seeded
``seed + 10000``, ``seed + 10001``, ... (:func:`sb3_hhp.train.eval_seeds`). This evaluates the same models on the same
episodes, deterministic and stochastic, each with ``HhP.load``'s options as saved and with every setting of
``--compare`` (a JSON object of load options, e.g. a prediction-time setting switched off), so that a change of how a
trained model acts is measured on the very episodes the runs reported:

    python benchmarks/evaluate.py MiniGrid-MultiRoom-N12-S10-v0 \\
        0=benchmarks/results/minigrid_tasks/logs/MiniGrid-MultiRoom-N12-S10-v0__hhp__s0 \\
        --compare '{"break_cycles": false}' --out benchmarks/results/minigrid_tasks/break_cycles.json

Each model is ``SEED=PATH``: a model ``.zip``, or a run's log folder (the newest final model in it, else its newest
checkpoint). Needs nothing beyond the package. Written into a sweep's folder (next to its ``results.csv``), the file's
deterministic figures with cycles broken replace, in ``report.py``'s table, those of runs the runner evaluated plain
greedy.
"""

import argparse
import json
import pathlib
import sys
import time
from typing import Any

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from benchmarks.run import latest_checkpoint  # noqa: E402
from sb3_hhp.goals import register_minigrid_tasks, wrap_env  # noqa: E402
from sb3_hhp.train import eval_seeds, evaluate, read_checkpoint  # noqa: E402


def model_file(path: str, env_id: str) -> pathlib.Path:
    """A model ``.zip`` as given, or the newest ``<env id>.zip`` a run saved under a log folder (its final model), or,
    where the run has not ended, the model of its newest complete checkpoint (the one its ``checkpoint.json`` points at,
    as the runner resumes)."""
    given = pathlib.Path(path)
    if given.suffix == ".zip":
        if not given.is_file():
            raise SystemExit(f"No such model: {given}")
        return given
    finals = sorted(given.rglob(f"{env_id}.zip"), key=lambda found: found.stat().st_mtime)
    if finals:
        return finals[-1]
    run_folder = latest_checkpoint(given)  # complete checkpoints only
    if run_folder is None:
        raise SystemExit(f"{given} holds no model: give a model .zip or a run's log folder")
    return pathlib.Path(read_checkpoint(str(run_folder))["model"])


def run_episodes(model: Any, env_id: str, seeds: list[int], deterministic: bool) -> dict[str, Any]:
    """One episode per seed on fresh envs of ``env_id`` wrapped as for training (:func:`sb3_hhp.train.evaluate`)."""
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv

    def make_envs(n: int) -> Any:
        return DummyVecEnv([lambda: wrap_env(gym.make(env_id)) for _ in range(n)])

    return evaluate(model, make_envs, seeds, deterministic=deterministic)


def success_rates(model: Any, env_id: str, seed: int, episodes: int, modes: tuple[str, ...]) -> dict[str, float]:
    seeds = eval_seeds(seed, episodes)
    rates = {}
    for name in modes:
        results = run_episodes(model, env_id, seeds, deterministic=name == "deterministic")
        rates[name] = sum(results["successes"]) / len(seeds)
        rates[f"mean_return_{name}"] = sum(results["returns"]) / len(seeds)
    return rates


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("env", help="the env id the models were trained on")
    parser.add_argument("models", nargs="+", help="SEED=PATH: the run's training seed and its model (.zip or log folder)")
    parser.add_argument("--episodes", type=int, default=100, help="fresh episodes per model (default 100, as the runner)")
    parser.add_argument("--compare", action="append", default=[], type=json.loads,
                        help="a JSON object of HhP.load options to evaluate too (repeatable)")
    parser.add_argument("--deterministic-only", action="store_true",
                        help="only the deterministic policy (long episodes of a task the policy fails cost minutes each)")
    parser.add_argument("--stochastic-only", action="store_true", help="only the stochastic policy")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1, as the runner's runs)")
    parser.add_argument("--out", default=None, help="write the figures as JSON here")
    args = parser.parse_args(argv)
    import torch as th

    from sb3_hhp import HhP

    th.set_num_threads(args.threads)
    register_minigrid_tasks()
    settings = [{}] + list(args.compare)
    if args.deterministic_only and args.stochastic_only:
        raise SystemExit("--deterministic-only and --stochastic-only leave nothing to evaluate: give one at most")
    modes = ("deterministic",) if args.deterministic_only else ("stochastic",) if args.stochastic_only else (
        "deterministic", "stochastic")
    rows = []
    for spec in args.models:
        seed_text, sep, path = spec.partition("=")
        if not sep or not seed_text.isdigit():
            raise SystemExit(f"{spec!r}: give each model as SEED=PATH, e.g. 0=logs/hhp/MiniGrid-DoorKey-8x8-v0_1")
        file = model_file(path, args.env)
        for options in settings:
            start = time.perf_counter()
            model = HhP.load(file, device="cpu", **options)
            rates = success_rates(model, args.env, int(seed_text), args.episodes, modes)
            rows.append({"seed": int(seed_text), "model": str(file), "load_options": options,
                         "break_cycles": bool(model.break_cycles), **rates,
                         "seconds": round(time.perf_counter() - start, 1)})
            print(f"seed {seed_text} {json.dumps(options) if options else '(as saved)'}: success "
                  + ", ".join(f"{rates[mode]:.2f} {mode}" for mode in modes), flush=True)
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps({"env": args.env, "episodes": args.episodes, "runs": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
