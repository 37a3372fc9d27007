"""Train HhP from a YAML file with RL Zoo: ``python -m sb3_hhp.train --env ENV --oracle NAME -n STEPS``.

This entry point registers HhP with RL Zoo and hands the rest to :func:`rl_zoo3.train.train`, so RL
Zoo's evaluation callback, checkpoints, saved configs (``config.yml``, ``args.yml``, ``command.txt``),
TensorBoard logs and optuna tuning (``-optimize``) work for HhP unchanged:

- ``rl_zoo3.utils.ALGOS["hhp"] = HhP``, a sampler in ``rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER["hhp"]``
  (and its converter), done here because ``--algo``'s choices are fixed when RL Zoo parses its arguments;
- :class:`HhPExperimentManager`, RL Zoo's :class:`~rl_zoo3.exp_manager.ExperimentManager` with four
  changes: an env id with no entry of its own in the YAML takes its domain's entry (``minigrid`` for any
  ``MiniGrid-*`` id, ``atari``, ``fetch``); unknown keys are refused before training; ``--oracle`` and a durable preference
  database in the run folder (``<log folder>/hhp/<ENV>_<run>/preferences.sqlite``) join the
  hyperparameters.

**Frequencies count primitive steps.** HhP's loop steps all its envs at once and calls the callbacks once per
step of the envs, as SB3's algorithms do, so RL Zoo's ``--eval-freq``, ``--save-freq``, the trials' evaluations
of ``-optimize`` and the ``--progress`` bar count primitive steps like ``-n``, divided over ``n_envs`` as RL Zoo
does for every algorithm.

After training, the deterministic policy (with ``--stochastic-eval``, the stochastic one) is evaluated
on fresh environments (built like the training env, by RL Zoo) whose seeds start at ``seed + 10_000``
(:func:`eval_seeds`), never a training seed. The summary (success rate, mean return, queries used,
sub-goals found, fps) is printed and, with ``--summary-json``, written as JSON. The trained model is
the one RL Zoo just saved to ``<log folder>/hhp/<ENV>_<run>/<ENV>.zip``, taken from the experiment
manager in memory.

``--checkpoint-freq N`` saves the model and its replays (:meth:`HhP.save_replay_buffer`) every N primitive steps in
the run folder (``checkpoints/<steps>/``, ``checkpoint.json``), in place of the last; ``--resume RUN_FOLDER`` goes
on from that checkpoint up to ``-n`` steps, on that run's preference database (RL Zoo's ``-i`` starts the step
count again and a new database). The part resumed draws its episodes and random numbers from :func:`resume_seed`
(the run's seed and the checkpoint's step count), so it does not replay the layouts the run began with.

``--label-server`` serves the labeling page (:class:`~sb3_hhp.label.server.LabelServer`) on 127.0.0.1
beside training, on the run's preference database, and implies ``--oracle web``.
"""

import argparse
import contextlib
import difflib
import functools
import importlib
import inspect
import io
import json
import os
import re
import shutil
import sys
import time
import warnings
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from pathlib import Path
from pprint import pprint
from typing import Any, Optional

import numpy as np
import yaml

#: the algorithm's name in RL Zoo (``--algo hhp``, ``<log folder>/hhp/``)
ALGO_NAME = "hhp"
#: eval seeds start this far above the training seed (training uses seed .. seed + n_envs - 1)
EVAL_SEED_OFFSET = 10_000
#: the file name of the preference database inside the run folder
PREFERENCE_DB_NAME = "preferences.sqlite"
CHECKPOINT_FILE = "checkpoint.json"  # the run folder's latest checkpoint (--checkpoint-freq, --resume)
RESUMED_FILE = "resumed.json"  # a resumed part's folder: the run folder and checkpoint it went on from
#: keys RL Zoo reads itself (they never reach HhP's constructor)
ZOO_KEYS = frozenset(
    {"n_timesteps", "policy", "env_wrapper", "n_envs", "normalize", "frame_stack", "callback", "vec_env_wrapper",
     "env_kwargs", "monitor_kwargs"}
)
#: constructor arguments RL Zoo sets from the command line; a YAML file must not set them
COMMAND_LINE_KEYS = {"seed": "--seed", "verbose": "--verbose", "device": "--device", "tensorboard_log": "--tensorboard-log"}
#: the YAML entry a domain's env ids fall back to when they have no entry of their own
DOMAIN_KEYS = ("minigrid", "atari", "fetch")
#: vectorized evaluation: at most this many fresh envs at once (one episode each)
EVAL_CHUNK = 50


class ConfigError(ValueError):
    """A wrong command line or hyperparameter file: reported in one line, before training starts."""


# ---------------------------------------------------------------------- hyperparameter file


def default_config_path() -> Path:
    """``sb3_hhp/hyperparams/hhp.yml``: package data, found from the package so that any working directory and an
    installed wheel work."""
    path = Path(__file__).resolve().parent / "hyperparams" / f"{ALGO_NAME}.yml"
    if not path.is_file():
        raise ConfigError(f"No default hyperparameter file: looked for {path}; pass one with --conf-file FILE")
    return path


def domain_of(env_id: str) -> Optional[str]:
    """The domain of a registered env id, whose YAML entry serves ids with no entry of their own.

    :param env_id: a gymnasium env id (registered)
    :return: "minigrid", "atari", "fetch" or None
    """
    import gymnasium as gym

    entry_point = str(gym.spec(env_id).entry_point)
    if "minigrid" in entry_point:
        return "minigrid"
    if "AtariEnv" in entry_point or "ale_py" in entry_point:
        return "atari"
    if "gymnasium_robotics" in entry_point and env_id.startswith("Fetch"):
        return "fetch"
    return None


def select_entry(table: dict[str, Any], env_id: str, config: str = "the hyperparameter file") -> str:
    """The key of ``table`` that holds ``env_id``'s hyperparameters: the id itself, else its domain's
    entry (:data:`DOMAIN_KEYS`), else ``default`` (RL Zoo's convention).

    :param table: the parsed YAML file (env id or domain -> hyperparameters)
    :param env_id: a registered gymnasium env id
    :param config: the file's name, for the error message
    """
    if not isinstance(table, dict):
        raise ConfigError(f"{config} must map env ids to hyperparameters, got {type(table).__name__}")
    if env_id in table:
        return env_id
    domain = domain_of(env_id)
    if domain is not None and domain in table:
        return domain
    if "default" in table:
        return "default"
    raise ConfigError(
        f"No hyperparameters for {env_id} in {config}: add an entry {env_id!r}"
        + (f" or {domain!r}" if domain else "")
        + f" (entries: {', '.join(map(str, table))})"
    )


def hhp_arguments() -> list[str]:
    """The keyword arguments of :class:`~sb3_hhp.HhP` a hyperparameter file may set."""
    from sb3_hhp.hhp import HhP

    excluded = {"self", "policy", "env", "_init_setup_model", *COMMAND_LINE_KEYS}
    return [name for name, parameter in inspect.signature(HhP.__init__).parameters.items()
            if name not in excluded and parameter.kind is not inspect.Parameter.VAR_KEYWORD]


def validate_hyperparams(hyperparams: dict[str, Any], where: str) -> None:
    """Refuse keys that neither HhP's constructor nor RL Zoo accepts, and settings HhP cannot run with.

    :param hyperparams: one env's hyperparameters, after RL Zoo's overrides (``--hyperparams``)
    :param where: where they came from, for the messages
    """
    from sb3_hhp.hhp.hhp import MOVED_ARGUMENTS, moved_argument_message
    from sb3_hhp.oracles.registry import ORACLE_NAMES

    valid = hhp_arguments()
    for key in hyperparams:
        if key in COMMAND_LINE_KEYS:
            raise ConfigError(f"{where}: {key!r} is set on the command line ({COMMAND_LINE_KEYS[key]}), not in the file")
        if key in MOVED_ARGUMENTS:
            raise ConfigError(f"{where}: {moved_argument_message(key)}")
        if key not in ZOO_KEYS and key not in valid:
            close = difflib.get_close_matches(str(key), [*valid, *ZOO_KEYS], n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ConfigError(
                f"{where}: unknown hyperparameter {key!r}{hint}. Valid keys: HhP's arguments {', '.join(valid)}; "
                f"RL Zoo's {', '.join(sorted(ZOO_KEYS))}"
            )
    n_envs = hyperparams.get("n_envs", 1)
    if isinstance(n_envs, bool) or not isinstance(n_envs, int) or n_envs < 1:
        raise ConfigError(f"{where}: n_envs must be an integer >= 1, got {n_envs!r}")
    for key in ("normalize", "frame_stack", "vec_env_wrapper"):
        if hyperparams.get(key):
            raise ConfigError(
                f"{where}: {key!r} wraps the VecEnv, and HhP needs the plain env: use env_wrapper (a gym.Wrapper) instead"
            )
    oracle = hyperparams.get("oracle", "scripted")
    if isinstance(oracle, str) and oracle not in ORACLE_NAMES:
        raise ConfigError(f"{where}: unknown oracle {oracle!r}: use one of {', '.join(ORACLE_NAMES)}")


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
    """RL Zoo converter (``--storage ... --trial-id``): a trial's sampled values (named as the paper names them:
    ``query_mode``, ``t_qry``) as HhP's arguments (``query_kwargs``)."""
    from sb3_hhp.hhp.hhp import group_moved_arguments

    return group_moved_arguments(sampled_params)


def register() -> None:
    """Make HhP known to RL Zoo: ``ALGOS["hhp"]``, its optuna sampler and converter."""
    from rl_zoo3 import hyperparams_opt, utils

    from sb3_hhp.hhp import HhP

    utils.ALGOS[ALGO_NAME] = HhP
    hyperparams_opt.HYPERPARAMS_SAMPLER[ALGO_NAME] = sample_hhp_params
    hyperparams_opt.HYPERPARAMS_CONVERTER[ALGO_NAME] = convert_hhp_params


# ---------------------------------------------------------------------- callbacks and experiment manager


@contextlib.contextmanager
def _replaced(module: Any, name: str, value: Any) -> Iterator[None]:
    original = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, original)


def checkpoint_callback_class() -> type:
    from stable_baselines3.common.callbacks import BaseCallback

    class LatestCheckpoint(BaseCallback):
        """Every ``save_freq`` primitive steps (and at the end of training), the model (:meth:`HhP.save`), its
        replays (:meth:`HhP.save_replay_buffer`; any off-policy model's) and the state of a
        :class:`~sb3_hhp.curiosity.VecRNDReward` around its env (an on-policy baseline's curiosity) in
        ``<run folder>/checkpoints/<steps>/``, then ``checkpoint.json`` pointing at them, then the older checkpoints
        removed: a run stopped at any moment keeps a complete checkpoint, which ``--resume`` (HhP) or the benchmark
        runner (every variant) goes on from. A checkpoint the disk cannot hold is not written (less free space than
        the last one took, or the disk full while writing it: its files are removed), with a warning: training goes
        on and the last complete checkpoint stays the one to resume from.

        :param save_freq: primitive steps between checkpoints (counted on the model's step count, so a resumed run
            keeps the same checkpoint steps)
        :param save_path: the run folder
        :param train_seconds: seconds of training before this part (a resumed run's, up to its checkpoint): each
            checkpoint records the training time up to it, every part together
        :param at_rollout_end: write a checkpoint that falls due at the end of the rollout it fell due in (SB3's own
            off-policy algorithms call the callbacks before they store the step's transition; HhP stores first)
        """

        def __init__(self, save_freq: int, save_path: str, train_seconds: float = 0.0, verbose: int = 0,
                     at_rollout_end: bool = False) -> None:
            super().__init__(verbose)
            self.save_freq, self.save_path = int(save_freq), Path(save_path)
            self.saved_at = self.complete_at = -1
            self.earlier_seconds, self.start = float(train_seconds), time.perf_counter()
            self.at_rollout_end, self.due = bool(at_rollout_end), False

        def _init_callback(self) -> None:
            self.saved_at = self.model.num_timesteps  # a resumed run's checkpoint is its start
            self.complete_at = self.saved_at  # the last checkpoint written whole
            self.start = time.perf_counter()

        def _on_step(self) -> bool:
            if self.num_timesteps // self.save_freq > max(self.saved_at, 0) // self.save_freq:
                if self.at_rollout_end:
                    self.due = True
                else:
                    self.save()
            return True

        def _on_rollout_end(self) -> None:
            if self.due:
                self.save()

        def _on_training_end(self) -> None:
            if self.num_timesteps != self.saved_at:
                self.save()

        def save(self) -> None:
            steps = int(self.model.num_timesteps)
            folder = self.save_path / "checkpoints" / str(steps)
            last_size = checkpoint_bytes(self.save_path / "checkpoints")  # the last one's files (one at a time)
            free = shutil.disk_usage(self.save_path).free
            if free < last_size:
                self._skip(steps, f"{free / 1e9:.2f} GB free on its disk, the last checkpoint took {last_size / 1e9:.2f} GB")
                return
            try:
                files = self._write(folder, steps)
            except OSError as error:  # the disk full while writing: the files written so far go
                shutil.rmtree(folder, ignore_errors=True)
                self._skip(steps, str(error))
                return
            pointer = self.save_path / CHECKPOINT_FILE
            temporary = pointer.with_suffix(".json.tmp")
            seconds = round(self.earlier_seconds + time.perf_counter() - self.start, 1)
            temporary.write_text(json.dumps({"timesteps": steps, **files, "train_seconds": seconds}) + "\n")
            os.replace(temporary, pointer)
            for older in (self.save_path / "checkpoints").iterdir():
                if older.name != str(steps):
                    shutil.rmtree(older, ignore_errors=True)
            self.saved_at = self.complete_at = steps
            self.due = False
            if self.verbose:
                print(f"Checkpoint at {steps} steps: {folder}")

        def _write(self, folder: Path, steps: int) -> dict[str, str]:
            """The checkpoint's files (model, replays, curiosity state) in ``folder``; their paths for the pointer."""
            folder.mkdir(parents=True, exist_ok=True)
            files = {"model": f"checkpoints/{steps}/model.zip"}
            self.model.save(folder / "model.zip")
            if hasattr(self.model, "save_replay_buffer"):  # off-policy: HhP, DQN
                self.model.save_replay_buffer(folder / "replay.pkl")
                files["replay"] = f"checkpoints/{steps}/replay.pkl"
            curiosity = vec_rnd_of(self.model.get_env())
            if curiosity is not None:
                import torch as th

                th.save(curiosity.state_dict(), folder / "vec_rnd.pt")
                files["vec_rnd"] = f"checkpoints/{steps}/vec_rnd.pt"
            return files

        def _skip(self, steps: int, why: str) -> None:
            """No checkpoint at ``steps`` (the disk cannot hold it): say so, and train on to the next one."""
            last = (f"the last complete checkpoint ({self.complete_at} steps) stays the one to resume from"
                    if self.complete_at > 0 else "there is no complete checkpoint to resume from yet")
            warnings.warn(f"No checkpoint at {steps} steps in {self.save_path} ({why}): training goes on; {last}. "
                          "Free disk space to have checkpoints again.", stacklevel=2)
            self.saved_at, self.due = steps, False

    return LatestCheckpoint


def checkpoint_bytes(folder: Path) -> int:
    """The bytes the files under ``folder`` take (0 where there is none): a run's checkpoints."""
    folder = Path(folder)
    return sum(path.stat().st_size for path in folder.rglob("*") if path.is_file()) if folder.is_dir() else 0


def vec_rnd_of(env: Any) -> Any:
    """The :class:`~sb3_hhp.curiosity.VecRNDReward` among the VecEnv wrappers of ``env``, None when there is none."""
    from stable_baselines3.common.vec_env import unwrap_vec_wrapper

    from sb3_hhp.curiosity import VecRNDReward

    return unwrap_vec_wrapper(env, VecRNDReward) if env is not None else None


def read_checkpoint(run_folder: str) -> dict[str, Any]:
    """The latest checkpoint of a run folder (``checkpoint.json``): its step count and the paths of the model, the
    replays (off-policy models) and a curiosity wrapper's state (``vec_rnd``, where the run had one; None
    otherwise). A clear error when there is none or its files are gone."""
    folder = Path(run_folder)
    if not folder.is_dir():
        raise ConfigError(f"--resume {run_folder}: no such run folder (e.g. logs/hhp/MiniGrid-DoorKey-8x8-v0_1)")
    pointer = folder / CHECKPOINT_FILE
    if not pointer.is_file():
        raise ConfigError(f"--resume {run_folder}: the folder has no {CHECKPOINT_FILE}; a run writes checkpoints "
                          "when trained with --checkpoint-freq N")
    try:
        checkpoint = json.loads(pointer.read_text())
        checkpoint = {"timesteps": int(checkpoint["timesteps"]), "model": str(folder / checkpoint["model"]),
                      **{what: str(folder / checkpoint[what]) if checkpoint.get(what) else None
                         for what in ("replay", "vec_rnd")},
                      "run_folder": str(folder), "train_seconds": float(checkpoint.get("train_seconds", 0.0))}
    except (ValueError, KeyError, TypeError) as error:
        raise ConfigError(f"--resume {run_folder}: {pointer} is damaged ({error})") from error
    for what in ("model", "replay", "vec_rnd"):
        if checkpoint[what] is not None and not os.path.isfile(checkpoint[what]):
            raise ConfigError(f"--resume {run_folder}: the checkpoint's {what} {checkpoint[what]} is missing")
    return checkpoint


def answers_database(run_folder: str) -> str:
    """The preference database a run folder's answers went to: its own, or, for a resumed part (``resumed.json``),
    which goes on with the answers of the part it resumed, that part's, back to the run's first part; a run resumed
    twice then keeps every answer in one file and asks no question twice."""
    folder, seen = Path(run_folder), set()
    while not (folder / PREFERENCE_DB_NAME).is_file() and (folder / RESUMED_FILE).is_file() and folder not in seen:
        seen.add(folder)
        try:
            folder = Path(json.loads((folder / RESUMED_FILE).read_text())["run_folder"])
        except (ValueError, KeyError, TypeError):
            break
    found = folder / PREFERENCE_DB_NAME
    return str(found if found.is_file() else Path(run_folder) / PREFERENCE_DB_NAME)


def _experiment_manager_class() -> type:
    from rl_zoo3.exp_manager import ExperimentManager

    class HhPExperimentManager(ExperimentManager):
        """RL Zoo's experiment manager for HhP: domain entries, key checks, the oracle and preference
        database, callbacks in primitive steps, the labeling server; it keeps the trained model."""

        def __init__(self, *args: Any, hhp_options: argparse.Namespace, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.hhp_options = hhp_options
            self.trained_model: Any = None
            self.train_seconds = 0.0
            self.label_server: Any = None
            self.config_entry = ""
            self.checkpoint = read_checkpoint(hhp_options.resume) if hhp_options.resume else None
            self.start_timesteps = 0
            if self.checkpoint is not None:  # RL Zoo's own way of going on from a saved model, by its name
                self.trained_agent, self.continue_training = self.checkpoint["model"], True

        def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
            if not self.config.endswith((".yml", ".yaml")):  # a .py file or a module: RL Zoo reads it
                hyperparams, _ = super().read_hyperparameters()
                self.config_entry = self.env_name.gym_id
            else:
                print(f"Loading hyperparameters from: {self.config}")
                try:
                    with open(self.config) as file:
                        table = yaml.safe_load(file)
                except OSError as error:
                    raise ConfigError(f"Cannot read the hyperparameter file {self.config}: {error}") from error
                self.config_entry = select_entry(table, self.env_name.gym_id, self.config)
                if self.config_entry != self.env_name.gym_id:
                    print(f"Using the {self.config_entry!r} entry for {self.env_name.gym_id}")
                hyperparams = dict(table[self.config_entry] or {})
                # as RL Zoo's own read_hyperparameters from here on
                if self.storage and self.study_name and self.trial_id:
                    print("Loading from Optuna study...")
                    hyperparams.update(self.load_trial(self.storage, self.study_name, self.trial_id))
                if self.custom_hyperparams is not None:
                    validate_hyperparams(dict(self.custom_hyperparams), "--hyperparams")
                    hyperparams.update(self.custom_hyperparams)
                if "env_kwargs" in hyperparams and self.env_kwargs:
                    hyperparams.update({"env_kwargs": self.env_kwargs})
                    if self._eval_env_kwargs_args is None:
                        self.eval_env_kwargs = hyperparams["env_kwargs"]
            options = self.hhp_options
            if options.oracle is not None:
                hyperparams["oracle"] = options.oracle
            # every run keeps its answers in a durable store; optuna trials would share one, so they get none
            if "preference_db" not in hyperparams and not (self.optimize_hyperparameters and not options.label_server):
                # a resumed run goes on with the answers of the run it resumes
                hyperparams["preference_db"] = (answers_database(self.checkpoint["run_folder"]) if self.checkpoint
                                                is not None else os.path.join(self.save_path, PREFERENCE_DB_NAME))
            validate_hyperparams(hyperparams, f"{self.config} [{self.config_entry}]")
            self._check_values(hyperparams)
            if self.n_timesteps > 0:  # -n overrides the file: the dump (config.yml) says what was trained
                hyperparams["n_timesteps"] = self.n_timesteps
            saved_hyperparams = OrderedDict([(key, hyperparams[key]) for key in sorted(hyperparams.keys())])
            print("Default hyperparameters for environment (ones being tuned will be overridden):")
            pprint(saved_hyperparams)
            return hyperparams, saved_hyperparams

        def _check_values(self, hyperparams: dict[str, Any]) -> None:
            """HhP's checks of the values, before anything is created, blaming ``--hyperparams`` or the file."""
            from sb3_hhp import HhP

            def check(values: dict[str, Any]) -> None:
                kwargs = {key: value for key, value in values.items() if key not in ZOO_KEYS}
                HhP(values.get("policy", "MlpPolicy"), None, _init_setup_model=False, **kwargs)

            custom = dict(self.custom_hyperparams or {})
            try:
                check(hyperparams)
            except (ValueError, TypeError) as error:
                from_file = {key: value for key, value in hyperparams.items() if key not in custom}
                try:
                    check(from_file)
                except (ValueError, TypeError):
                    raise ConfigError(f"{self.config} [{self.config_entry}]: {error}") from error
                raise ConfigError(f"--hyperparams: {error}") from error

        def setup_experiment(self) -> Any:
            try:
                results = super().setup_experiment()
            except ConfigError:
                raise
            except (ValueError, TypeError) as error:  # HhP's constructor refusing a value from the file
                raise ConfigError(f"{self.config} [{self.config_entry}]: {error}") from error
            if results is not None and self.hhp_options.label_server:
                from sb3_hhp.label.server import LabelServer

                model = results[0]
                self.label_server = LabelServer(model.store, host="127.0.0.1", port=self.hhp_options.label_port).start()
                print(f"Labeling page: {self.label_server.url} (answers go to {model.store.path})", flush=True)
            return results

        def create_callbacks(self) -> None:
            super().create_callbacks()
            if self.hhp_options.checkpoint_freq > 0:
                earlier = self.checkpoint["train_seconds"] if self.checkpoint is not None else 0.0
                self.callbacks.append(checkpoint_callback_class()(self.hhp_options.checkpoint_freq, self.save_path, earlier))

        def _load_pretrained_agent(self, hyperparams: dict[str, Any], env: Any) -> Any:
            """The checkpoint of ``--resume``: the model as it was saved (its own hyperparameters), with this run's
            oracle and preference database, and its replays."""
            from sb3_hhp import HhP

            checkpoint = self.checkpoint
            print(f"Resuming {checkpoint['run_folder']} at {checkpoint['timesteps']} steps")
            os.makedirs(self.save_path, exist_ok=True)  # where this part's evaluations begin (benchmarks join the parts)
            part_seed = resume_seed(self.seed, int(checkpoint["timesteps"]))
            with open(os.path.join(self.save_path, RESUMED_FILE), "w") as file:
                json.dump({"run_folder": checkpoint["run_folder"], "timesteps": checkpoint["timesteps"],
                           "seed": part_seed}, file)
            chosen = {key: hyperparams[key] for key in ("oracle", "preference_db") if hyperparams.get(key) is not None}
            model = HhP.load(checkpoint["model"], env=env, seed=self.seed, device=self.device, verbose=self.verbose,
                             tensorboard_log=self.tensorboard_log, **chosen)  # else the ones it was saved with
            model.load_replay_buffer(checkpoint["replay"])
            model.set_random_seed(part_seed)  # the envs' next layouts, exploration and torch: not the run's first ones
            return model

        def learn(self, model: Any) -> None:
            start = time.perf_counter()
            self.start_timesteps = int(model.num_timesteps)
            if self.checkpoint is None:
                super().learn(model)
            else:  # -n is the run's whole budget: train what is left, the step count going on
                budget = self.n_timesteps
                self.n_timesteps = max(0, budget - model.num_timesteps)
                model.learn = functools.partial(type(model).learn, model, reset_num_timesteps=False)
                try:
                    if self.n_timesteps > 0:
                        super().learn(model)
                    else:
                        print(f"The checkpoint is at {model.num_timesteps} steps, the budget (-n) {budget}: nothing to train")
                finally:
                    del model.learn
                    self.n_timesteps = budget
            self.train_seconds = time.perf_counter() - start

        def save_trained_model(self, model: Any) -> None:
            super().save_trained_model(model)
            self.trained_model = model

    return HhPExperimentManager


# ---------------------------------------------------------------------- evaluation and summary


def resume_seed(seed: int, timesteps: int) -> int:
    """The seed of a run's part resumed at ``timesteps``: its envs' layouts, exploration and torch draws.

    A resumed part seeded with the run's own seed would replay the episodes the run began with. This seed is drawn
    from ``(seed, timesteps)`` (the same checkpoint resumes the same way) in ``[2**30, 2**31)``: above every
    training seed ``seed .. seed + n_envs - 1`` and evaluation seed (:func:`eval_seeds`) of a run seeded below
    ``2**30 - 10**6``, and below ``2**32`` with any env's rank added.

    :param seed: the run's training seed (>= 0)
    :param timesteps: the checkpoint's step count (>= 0)
    """
    if seed < 0 or timesteps < 0:
        raise ValueError(f"seed and timesteps must be >= 0, got {seed} and {timesteps}")
    state = int(np.random.SeedSequence([int(seed), int(timesteps)]).generate_state(1)[0])
    return (1 << 30) + state % (1 << 30)



def eval_seeds(seed: int, n_episodes: int, offset: int = EVAL_SEED_OFFSET) -> list[int]:
    """Seeds of the evaluation episodes: ``seed + offset``, ``seed + offset + 1``, ... (one per episode).

    The training env is seeded with ``seed`` (RL Zoo seeds env ``i`` with ``seed + i``, and HhP runs one), so
    with ``offset`` above the number of training envs no evaluation seed is a training seed.

    :param seed: the training seed (>= 0)
    :param n_episodes: number of evaluation episodes (>= 0)
    :param offset: distance from the training seed (>= 1)
    """
    if n_episodes < 0:
        raise ValueError(f"n_episodes must be >= 0, got {n_episodes}")
    if offset < 1:
        raise ValueError(f"offset must be >= 1 so that evaluation never reuses the training seed, got {offset}")
    return [int(seed) + offset + index for index in range(n_episodes)]


def evaluate(model: Any, make_envs: Any, seeds: Sequence[int], deterministic: bool = True) -> dict[str, Any]:
    """Run the policy for one episode per seed, each on a fresh env.

    :param model: a trained HhP
    :param make_envs: ``make_envs(n)`` builds a VecEnv of ``n`` fresh envs wrapped like the training env
        (RL Zoo's ``ExperimentManager.create_envs(n, eval_env=True)``)
    :param seeds: one seed per episode; a chunk of consecutive seeds goes to ``VecEnv.seed(first)``
    :param deterministic: greedy sub-goal choices and primitive actions (else sampled, as in training)
    :return: returns, lengths and successes (``is_success`` when the env reports it, else return > 0)
    """
    from stable_baselines3.common.evaluation import evaluate_policy

    returns: list[float] = []
    lengths: list[int] = []
    successes: list[bool] = []
    seeds = [int(seed) for seed in seeds]
    for start in range(0, len(seeds), EVAL_CHUNK):
        chunk = seeds[start : start + EVAL_CHUNK]
        if chunk != list(range(chunk[0], chunk[0] + len(chunk))):
            raise ValueError("evaluate needs consecutive seeds (VecEnv.seed(s) seeds env i with s + i)")
        env = make_envs(len(chunk))
        reported: dict[int, bool] = {}

        def record(locals_: dict[str, Any], _globals: dict[str, Any]) -> None:
            if locals_["done"] and "is_success" in locals_["info"]:
                reported[int(locals_["i"])] = bool(locals_["info"]["is_success"])

        env.seed(chunk[0])
        try:
            episode_returns, episode_lengths = evaluate_policy(
                model, env, n_eval_episodes=len(chunk), deterministic=deterministic, return_episode_rewards=True,
                callback=record, warn=False,
            )
        finally:
            env.close()
        returns += [float(value) for value in episode_returns]
        lengths += [int(value) for value in episode_lengths]
        successes += [reported.get(index, value > 0) for index, value in enumerate(episode_returns)]
    return {"returns": returns, "lengths": lengths, "successes": successes}


def summarize(
    model: Any, env_id: str, seed: int, seeds: Sequence[int], results: dict[str, Any], train_seconds: float
) -> dict[str, Any]:
    """The run's summary: evaluation, queries, sub-goals and training speed.

    :param model: the trained HhP
    :param env_id: the task
    :param seed: the training seed
    :param seeds: the evaluation seeds
    :param results: :func:`evaluate`'s output
    :param train_seconds: wall-clock seconds of ``learn`` (callbacks included)
    """
    returns = np.asarray(results["returns"], dtype=float)
    subgoals = [model.goal_space.describe(goal.key) for goal in model.subgoals]
    oracle = model.oracle_spec
    return {
        "env": env_id,
        "seed": int(seed),
        "oracle": oracle if isinstance(oracle, str) or oracle is None else type(oracle).__name__,
        "total_timesteps": int(model.num_timesteps),
        "train_seconds": round(float(train_seconds), 3),
        "fps": round(model.num_timesteps / train_seconds, 1) if train_seconds > 0 else None,
        "eval_episodes": len(returns),
        "eval_seeds": [int(value) for value in seeds],
        "success_rate": float(np.mean(results["successes"])) if len(returns) else None,
        "mean_return": float(returns.mean()) if len(returns) else None,
        "std_return": float(returns.std()) if len(returns) else None,
        "mean_episode_length": float(np.mean(results["lengths"])) if len(returns) else None,
        "queries_used": int(model.query_selector.used),
        "queries_asked": int(model.store.count_asked()),
        "queries_distinct": len(model.asked_signatures),
        "query_budget": int(model.query_selector.budget),
        "num_subgoals": len(subgoals),
        "subgoals": subgoals,
        "preference_db": model.preference_db,
    }


# ---------------------------------------------------------------------- command line


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


def check_env_id(env_id: Optional[str], gym_packages: Sequence[str] = ()) -> str:
    """Fail early, in one line, on a missing or unknown env id (suggesting the closest registered one).

    :param env_id: the ``--env`` value
    :param gym_packages: modules that register envs (``--gym-packages``)
    """
    import gymnasium as gym

    from sb3_hhp.extras import missing_extra_hint, register_fetch_envs
    from sb3_hhp.goals import register_minigrid_tasks

    register_fetch_envs()  # the Fetch tasks, with the [fetch] extra (rl_zoo3 does not register them)
    register_minigrid_tasks()  # the paper's MultiRoom-N12-S10
    with contextlib.redirect_stderr(io.StringIO()):  # gymnasium-robotics prints a notice on Adroit envs at import
        import rl_zoo3.import_envs  # noqa: F401  registers MiniGrid, ALE, ...

    if not env_id:
        raise ConfigError("--env ENV is required (e.g. --env MiniGrid-DoorKey-5x5-v0)")
    for module in gym_packages:
        try:
            importlib.import_module(module)
        except ImportError as error:
            raise ConfigError(f"--gym-packages: cannot import {module!r}: {error}") from error
    if env_id not in gym.envs.registry:
        close = difflib.get_close_matches(env_id, list(gym.envs.registry), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        extra = missing_extra_hint(env_id)
        install = f"; it comes with an extra: {extra}" if extra else ""
        raise ConfigError(f"Unknown env id {env_id!r}{hint}: not in the gymnasium registry{install}")
    return env_id


def run(argv: Optional[Sequence[str]] = None) -> Optional[dict[str, Any]]:
    """Parse the command line, train with RL Zoo, evaluate and summarize.

    :param argv: the arguments (default ``sys.argv[1:]``)
    :return: the summary, or None when nothing was trained (``-optimize``)
    """
    from sb3_hhp.extras import register_fetch_envs

    register_fetch_envs()  # imported first, quietly: gymnasium-robotics prints a notice on Adroit envs at import
    import rl_zoo3.train

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
        print(_without_option(zoo_help.getvalue(), "--eval-episodes"), end="")
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
    zoo_argv = ["--algo", ALGO_NAME, *zoo_argv, "--eval-episodes", str(options.periodic_eval_episodes)]

    register()
    managers: list[Any] = []
    manager_class = _experiment_manager_class()

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
