"""Train HhP from a YAML file with RL Zoo: ``python -m sb3_hhp.train --env ENV --oracle NAME -n STEPS``.

This entry point registers HhP with RL Zoo and hands the rest to :func:`rl_zoo3.train.train`, so RL
Zoo's evaluation callback, checkpoints, saved configs (``config.yml``, ``args.yml``, ``command.txt``),
TensorBoard logs and optuna tuning (``-optimize``) work for HhP unchanged:

- ``rl_zoo3.utils.ALGOS["hhp"] = HhP``, a sampler in ``rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER["hhp"]``
  (and its converter), done here because ``--algo``'s choices are fixed when RL Zoo parses its arguments;
- ``HhPExperimentManager`` (:mod:`sb3_hhp.zoo.experiment`), RL Zoo's
  :class:`~rl_zoo3.exp_manager.ExperimentManager` with four changes: an env id with no entry of its own in the YAML
  takes its domain's entry (``minigrid`` for any ``MiniGrid-*`` id, ``atari``, ``fetch``); unknown keys are refused
  before training (:mod:`sb3_hhp.zoo.config`); ``--oracle`` and a durable preference database in the run folder
  (``<log folder>/hhp/<ENV>_<run>/preferences.sqlite``) join the hyperparameters.

**Frequencies count primitive steps.** HhP's loop steps all its envs at once and calls the callbacks once per
step of the envs, as SB3's algorithms do, so RL Zoo's ``--eval-freq``, ``--save-freq``, the trials' evaluations
of ``-optimize`` and the ``--progress`` bar count primitive steps like ``-n``, divided over ``n_envs`` as RL Zoo
does for every algorithm.

**One torch thread by default.** ``--num-threads`` is 1 unless given (RL Zoo leaves torch's default, one thread per
core): on HhP's small networks torch's OpenMP threads spin, and a run beside any other busy process stalls (two
DoorKey-6x6 runs side by side on 2 cores: 120-137 steps/s each with torch's default, 877-970 with one thread).
``--num-threads N`` (N > 0) sets N, ``--num-threads -1`` leaves torch's setting alone.

After training, the deterministic policy (with ``--stochastic-eval``, the stochastic one) is evaluated
on fresh environments (built like the training env, by RL Zoo) whose seeds start at ``seed + 10_000``
(:func:`~sb3_hhp.zoo.evaluation.eval_seeds`), never a training seed. The summary (success rate, mean return, queries
used, sub-goals found, fps) is printed and, with ``--summary-json``, written as JSON
(:mod:`sb3_hhp.zoo.evaluation`). The trained model is the one RL Zoo just saved to
``<log folder>/hhp/<ENV>_<run>/<ENV>.zip``, taken from the experiment manager in memory.

``--checkpoint-freq N`` saves the model and its replays (:meth:`~sb3_hhp.hhp.hhp.HhP.save_replay_buffer`) every N
primitive steps in the run folder (``checkpoints/<steps>/``, ``checkpoint.json``), in place of the last;
``--resume RUN_FOLDER`` goes on from that checkpoint up to ``-n`` steps, on that run's preference database (RL Zoo's ``-i``
starts the step count again and a new database). The part resumed draws its episodes and random numbers from
:func:`~sb3_hhp.zoo.checkpoints.resume_seed` (the run's seed and the checkpoint's step count), so it does not replay
the layouts the run began with (:mod:`sb3_hhp.zoo.checkpoints`).

``--label-server`` serves the labeling page (:class:`~sb3_hhp.label.server.LabelServer`) on 127.0.0.1
beside training, on the run's preference database, and implies ``--oracle web``.
"""

import argparse
import contextlib
import io
import json
import os
import re
import sys
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Optional

import numpy as np

from sb3_hhp.zoo.checkpoints import read_checkpoint, resume_seed
# CHECKPOINT_FILE, ..., select_entry: not used here, imported from here by the benchmark scripts
from sb3_hhp.zoo.checkpoints import CHECKPOINT_FILE, RESUMED_FILE, checkpoint_callback_class  # noqa: F401
from sb3_hhp.zoo.config import ALGO_NAME, ConfigError, check_env_id, default_config_path
from sb3_hhp.zoo.config import ZOO_KEYS, domain_of, select_entry  # noqa: F401
from sb3_hhp.zoo.evaluation import eval_seeds, evaluate, summarize
from sb3_hhp.zoo.experiment import experiment_manager_class

#: torch's threads unless ``--num-threads`` says otherwise (see ``--help``)
DEFAULT_NUM_THREADS = 1
#: the sampler's trial parameters that HhP takes inside a ``*_kwargs`` argument: trial name -> (argument, key)
TRIAL_GROUPED = {"query_mode": ("query_kwargs", "mode"), "t_qry": ("query_kwargs", "threshold"),
                 "center_bonus": ("meta_kwargs", "center_bonus"), "meta_input": ("meta_kwargs", "input")}

# ---------------------------------------------------------------------- RL Zoo registration


def sample_hhp_params(trial: Any, n_actions: int, n_envs: int, additional_args: dict) -> dict[str, Any]:
    """RL Zoo sampler for ``-optimize``: query budget, query threshold, eq. 3's beta, eq. 6's alpha, the
    meta-controller's learning rate, how the preference bonus is centred and what the meta-controller reads.

    :param trial: the optuna trial
    :param n_actions: unused (RL Zoo's sampler signature)
    :param n_envs: unused (RL Zoo's sampler signature)
    :param additional_args: unused (RL Zoo's sampler signature)
    :return: HhP keyword arguments
    """
    hyperparams: dict[str, Any] = {
        "query_budget": trial.suggest_int("query_budget", 25, 400, log=True),
        "query_mode": trial.suggest_categorical("query_mode", ["adaptive", "fixed"]),
        "beta": trial.suggest_float("beta", 0.0, 1.0),
        "alpha": trial.suggest_float("alpha", 0.01, 2.0, log=True),
        "learning_rate": trial.suggest_float("learning_rate", 1e-5, 3e-3, log=True),
        "center_bonus": trial.suggest_categorical("center_bonus", ["mean", "max"]),
        "meta_input": trial.suggest_categorical("meta_input", ["observation", "auto"]),
    }
    if hyperparams["query_mode"] == "fixed":  # the adaptive mode sets its own threshold
        hyperparams["t_qry"] = trial.suggest_float("t_qry", 0.02, 0.5)
    return convert_hhp_params(hyperparams)


def convert_hhp_params(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """RL Zoo converter (``--storage ... --trial-id``): a trial's sampled values, flat as optuna names them (the
    paper's ``t_qry``, ``query_mode``, ...), as HhP's arguments (``query_kwargs``, ``meta_kwargs``: :data:`TRIAL_GROUPED`)."""
    converted = {name: value for name, value in sampled_params.items() if name not in TRIAL_GROUPED}
    for name, (argument, key) in TRIAL_GROUPED.items():
        if name in sampled_params:
            converted[argument] = {**(converted.get(argument) or {}), key: sampled_params[name]}
    return converted


def register() -> None:
    """Make HhP known to RL Zoo: ``ALGOS["hhp"]``, its optuna sampler and converter."""
    from rl_zoo3 import hyperparams_opt, utils

    from sb3_hhp.hhp import HhP

    utils.ALGOS[ALGO_NAME] = HhP
    hyperparams_opt.HYPERPARAMS_SAMPLER[ALGO_NAME] = sample_hhp_params
    hyperparams_opt.HYPERPARAMS_CONVERTER[ALGO_NAME] = convert_hhp_params


# ---------------------------------------------------------------------- command line


@contextlib.contextmanager
def _replaced(module: Any, name: str, value: Any) -> Iterator[None]:
    original = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, original)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m sb3_hhp.train",
        description="Train HhP from a YAML file with RL Zoo, evaluate it on fresh seeds and summarize the run.",
        add_help=False,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=(
            "Every other option is RL Zoo's (listed below) and passed through; --algo is hhp and --conf-file\n"
            "defaults to sb3_hhp/hyperparams/hhp.yml. Frequencies (--eval-freq, --save-freq, -n, -optimize's evaluations)\n"
            "count primitive env steps, as for every RL Zoo algorithm. RL Zoo's --eval-episodes is\n"
            "--periodic-eval-episodes here. The preference database is\n"
            "<log folder>/hhp/<ENV>_<run>/preferences.sqlite unless the file sets preference_db."
        ),
    )
    parser.add_argument("-h", "--help", action="store_true", help="show this help (and RL Zoo's options) and exit")
    parser.add_argument(
        "--oracle", default=None,
        help="who answers preference queries (default: the file's, else scripted; web with --label-server)",
    )
    parser.add_argument(
        "--summary-json", default=None, help="write the run's summary (evaluation, queries, sub-goals, fps) to this file"
    )
    parser.add_argument(
        "--eval-episodes", type=int, default=100,
        help="episodes of the final evaluation, one fresh env each, seeds from seed + 10000 (default 100)",
    )
    parser.add_argument(
        "--stochastic-eval", action="store_true",
        help="evaluate the stochastic policy at the end (as RL Zoo does for MiniGrid, where greedy policies can loop)",
    )
    parser.add_argument(
        "--eval-both", action="store_true",
        help="evaluate the deterministic and the stochastic policy, on the same seeds (success_rate_deterministic, "
             "success_rate_stochastic in the summary; success_rate is the one --stochastic-eval picks)",
    )
    parser.add_argument(
        "--periodic-eval-episodes", type=int, default=5,
        help="episodes of each periodic evaluation (RL Zoo's --eval-episodes, default 5)",
    )
    parser.add_argument(
        "--checkpoint-freq", type=int, default=0,
        help="every N primitive steps and at the end, save the model and its replays in the run folder (checkpoints/, "
             "checkpoint.json), replacing the last checkpoint: what --resume goes on from (default 0: none)",
    )
    parser.add_argument(
        "--resume", default=None, metavar="RUN_FOLDER",
        help="go on training a run from its latest checkpoint (e.g. logs/hhp/MiniGrid-DoorKey-8x8-v0_1): the step "
             "count goes on up to -n, the answers go to that run's preference database; the logs of this part "
             "go to a new run folder",
    )
    parser.add_argument(
        "--num-threads", type=int, default=DEFAULT_NUM_THREADS, metavar="N",
        help=f"torch threads (default {DEFAULT_NUM_THREADS}; -1: torch's own default, one per core). Torch's default "
             "stalls HhP's small networks beside any other busy process, its OpenMP threads spinning: two DoorKey-6x6 "
             "runs side by side on 2 cores trained at 120-137 steps/s each with it, 877-970 with one thread",
    )
    parser.add_argument(
        "--label-server", action="store_true", help="serve the labeling page beside training (implies --oracle web)"
    )
    parser.add_argument(
        "--label-port", type=int, default=8000,
        help="port of the labeling page on 127.0.0.1 (default 8000, 0 picks a free one)",
    )
    return parser


def _without_option(help_text: str, option: str) -> str:
    """argparse ``help_text`` without ``option`` (its usage token and its entry): RL Zoo's option of that name is
    set through another one here."""
    help_text = re.sub(r"\s*\[" + re.escape(option) + r" [A-Z_]+\]", "", help_text)
    lines, kept, skipping = help_text.splitlines(keepends=True), [], False
    for line in lines:
        if line.startswith(f"  {option} "):
            skipping = True
            continue
        if skipping and line.startswith("  ") and not line.startswith("   "):
            skipping = False
        if skipping and not line.strip():
            skipping = False
        if not skipping:
            kept.append(line)
    return "".join(kept)


def _zoo_peek(argv: Sequence[str]) -> argparse.Namespace:
    """The few RL Zoo options this entry point reads (they stay in the command line)."""
    peek = argparse.ArgumentParser(add_help=False)
    peek.add_argument("--algo", default=ALGO_NAME)
    peek.add_argument("--env", default=None)
    peek.add_argument("-conf", "--conf-file", default=None)
    peek.add_argument("--gym-packages", nargs="+", default=[])
    peek.add_argument("-optimize", "--optimize-hyperparameters", action="store_true")
    return peek.parse_known_args(list(argv))[0]


def run(argv: Optional[Sequence[str]] = None) -> Optional[dict[str, Any]]:
    """Parse the command line, train with RL Zoo, evaluate and summarize.

    :param argv: the arguments (default ``sys.argv[1:]``)
    :return: the summary, or None when nothing was trained (``-optimize``)
    """
    from sb3_hhp.extras import register_fetch_envs

    register_fetch_envs()  # imported first, quietly: gymnasium-robotics prints a notice on Adroit envs at import
    import rl_zoo3.train
    import torch

    from sb3_hhp.oracles.registry import ORACLE_NAMES

    argv = list(sys.argv[1:] if argv is None else argv)
    # HhP trains on its sub-goal view of the envs (SubgoalVecEnv) and RL Zoo evaluates on the plain VecEnv, by design
    warnings.filterwarnings("ignore", message="Training and eval env are not of the same type")
    options, zoo_argv = _parser().parse_known_args(argv)
    if options.help:
        _parser().print_help()
        print("\nRL Zoo options (passed through to rl_zoo3.train):")
        zoo_help = io.StringIO()
        with _replaced(sys, "argv", ["python -m sb3_hhp.train", "--help"]), contextlib.redirect_stdout(zoo_help):
            register()
            try:
                rl_zoo3.train.train()  # prints RL Zoo's help and exits
            except SystemExit:
                pass
        zoo_text = zoo_help.getvalue()
        for option in ("--eval-episodes", "--num-threads"):  # set through this entry point's options
            zoo_text = _without_option(zoo_text, option)
        print(zoo_text, end="")
        return None
    if options.label_server and options.oracle is None:
        options.oracle = "web"
    if options.oracle is not None and options.oracle not in ORACLE_NAMES:
        raise ConfigError(f"Unknown oracle {options.oracle!r}: use one of {', '.join(ORACLE_NAMES)}")
    if options.eval_episodes < 0:
        raise ConfigError(f"--eval-episodes must be >= 0, got {options.eval_episodes}")
    if options.checkpoint_freq < 0:
        raise ConfigError(f"--checkpoint-freq must be >= 0 (0: no checkpoints), got {options.checkpoint_freq}")
    if options.resume is not None:
        if read_checkpoint(options.resume)["replay"] is None:  # refused before anything is built
            raise ConfigError(f"--resume {options.resume}: the checkpoint has no replays (not an HhP run's checkpoint)")
    if options.num_threads < 1 and options.num_threads != -1:
        raise ConfigError(f"--num-threads must be >= 1, or -1 for torch's own default, got {options.num_threads}")
    if not 0 <= options.label_port <= 65535:
        raise ConfigError(f"--label-port must be in [0, 65535], got {options.label_port}")
    zoo = _zoo_peek(zoo_argv)
    if zoo.algo != ALGO_NAME:
        raise ConfigError(f"sb3_hhp.train trains HhP (--algo hhp); use python -m rl_zoo3.train for {zoo.algo!r}")
    env_id = check_env_id(zoo.env, zoo.gym_packages)
    if zoo.conf_file is None:
        zoo_argv += ["--conf-file", str(default_config_path())]
    elif zoo.conf_file.endswith((".yml", ".yaml", ".py")) and not os.path.isfile(zoo.conf_file):
        raise ConfigError(f"--conf-file {zoo.conf_file}: no such file")
    zoo_argv = ["--algo", ALGO_NAME, *zoo_argv, "--eval-episodes", str(options.periodic_eval_episodes),
                "--num-threads", str(options.num_threads)]  # RL Zoo sets torch's threads when > 0

    register()
    managers: list[Any] = []
    manager_class = experiment_manager_class()

    def make_manager(*args: Any, **kwargs: Any) -> Any:
        managers.append(manager_class(*args, hhp_options=options, **kwargs))
        return managers[-1]

    try:
        with _replaced(sys, "argv", ["python -m sb3_hhp.train", *zoo_argv]), _replaced(
            rl_zoo3.train, "ExperimentManager", make_manager
        ):
            rl_zoo3.train.train()
    finally:
        for manager in managers:
            if manager.label_server is not None:
                manager.label_server.stop()
    manager = managers[-1] if managers else None
    if manager is None or manager.trained_model is None:
        return None
    model = manager.trained_model
    seeds = eval_seeds(manager.seed, options.eval_episodes)
    deterministic = not options.stochastic_eval
    results = evaluate(model, lambda n: manager.create_envs(n, eval_env=True, no_log=True), seeds, deterministic)
    summary = summarize(model, env_id, manager.seed, seeds, results, manager.train_seconds)
    summary["deterministic_eval"] = deterministic
    summary["num_threads"] = torch.get_num_threads()  # what trained, as --num-threads set it
    summary["break_cycles"] = bool(getattr(model, "break_cycles", False))  # how the deterministic policy acted
    # and the stochastic one, epsilon-greedy around it (a summary without this key: plain epsilon-greedy)
    summary["stochastic_breaks_cycles"] = summary["break_cycles"]
    if options.eval_both:
        other = evaluate(model, lambda n: manager.create_envs(n, eval_env=True, no_log=True), seeds, not deterministic)
        for mode, result in ((deterministic, results), (not deterministic, other)):
            name = "deterministic" if mode else "stochastic"
            summary[f"success_rate_{name}"] = float(np.mean(result["successes"])) if len(result["successes"]) else None
            summary[f"mean_return_{name}"] = float(np.mean(result["returns"])) if len(result["returns"]) else None
    if manager.checkpoint is not None:
        trained = model.num_timesteps - manager.start_timesteps
        summary["fps"] = round(trained / manager.train_seconds, 1) if manager.train_seconds > 0 else None
        summary["resumed_from"] = {"run_folder": manager.checkpoint["run_folder"], "timesteps": manager.start_timesteps,
                                   "seed": resume_seed(manager.seed, int(manager.checkpoint["timesteps"]))}
        # every part's training up to the checkpoint this part resumed, and this part's (a part's steps after its
        # last checkpoint were trained again, and are not counted)
        summary["train_seconds_all_parts"] = round(manager.checkpoint["train_seconds"] + manager.train_seconds, 3)
    summary["log_path"] = manager.save_path
    summary["model_path"] = os.path.join(manager.save_path, f"{manager.env_name}.zip")
    summary["config"] = manager.config
    summary["config_entry"] = manager.config_entry
    shown = {key: value for key, value in summary.items() if key != "eval_seeds"}
    print("HhP summary: " + json.dumps(shown, indent=2))
    if options.summary_json:
        path = Path(options.summary_json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(summary, indent=2) + "\n")
        print(f"Summary written to {path}")
    if model.store is not None:
        model.store.close()
    return summary


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Command-line entry point: exit status 0 on success, 2 (one line on stderr) on a configuration error."""
    try:
        run(argv)
    except ConfigError as error:
        print(f"python -m sb3_hhp.train: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
