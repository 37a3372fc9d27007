"""Run a sweep of experiments (env x variant x seed) in parallel and gather one CSV of results.

    python -m benchmarks.run benchmarks/experiments/doorkey8x8.yml --jobs 2
    python benchmarks/report.py benchmarks/results/doorkey8x8/results.csv

``--envs``, ``--variants`` and ``--seeds`` run a part of the sweep (same output folder, same rows), e.g. one long
run at a time: ``--envs MiniGrid-DoorKey-16x16-v0 --variants hhp --seeds 0``.

Variants:

- ``hhp``: ``python -m sb3_hhp.train --env ENV --oracle scripted -n STEPS --seed S --eval-both ...``, the
  command users train with (hyperparameters from ``hhp_conf``, default ``sb3_hhp/hyperparams/hhp.yml``; a variant that
  names its own ``--oracle`` has that one instead of ``scripted``);
- ``dqn``, ``ppo``: SB3's DQN and PPO, flat, on the observation HhP sees (:func:`sb3_hhp.goals.wrap_env`);
- ``ppo_rnd``: PPO with RND's intrinsic reward added to the env's (:class:`sb3_hhp.curiosity.VecRNDReward`),
  the paper's baseline;
- ``ddpg_her``, ``tqc_her``: SB3's DDPG and sb3-contrib's TQC with SB3's ``HerReplayBuffer`` (the paper's HER, and
  RL Zoo's strongest Fetch entry), on the env's own dict observation (``MultiInputPolicy``: observation,
  achieved and desired goal), not HhP's flat one;
- ``ddpg``: DDPG on the same dict observation, without hindsight (the paper's DDPG row).

The baselines take their settings from ``baselines_conf`` (default ``sb3_hhp/hyperparams/baselines.yml``). Every
variant trains for the sweep's step budget (primitive env steps), then is evaluated the way
``sb3_hhp.train`` evaluates HhP (:func:`sb3_hhp.train.evaluate`): ``eval_episodes`` fresh envs seeded
``seed + 10000``, ``seed + 10001``, ..., with the deterministic and with the stochastic policy. Learning
curves come from periodic evaluations every ``eval_freq`` steps (``curve_episodes`` episodes each,
stochastic policy on MiniGrid, as RL Zoo evaluates there), written to ``curves/<run>.csv``. Success is the env's
``info["is_success"]`` at an episode's end where it reports one (Fetch), else a positive return (MiniGrid).

Each experiment runs in a fresh worker process with one torch thread (``--jobs`` at once). The sweep is
resumable: an experiment whose row is already in ``results.csv`` is skipped, so an interrupted sweep is
finished by running the same command again; a failed one leaves no row, its log in ``logs/<run>.log``. An HhP
run writes a checkpoint (model and replays) at every periodic evaluation, and an HhP run that stopped before its
end goes on from its last checkpoint (``sb3_hhp.train --resume``): a run longer than a session is trained in parts,
its curve joined from them. The baselines write the same checkpoints (model, an off-policy baseline's replay, PPO +
RND's curiosity state, a ``VecNormalize``'s statistics) and go on from them the same way. Killing the runner stops
its workers and their training processes.
Output folder (``--out``, default ``benchmarks/results/<name>``)::

    results.csv        one row per env x variant x seed
    runs/<run>.json    each run's summary (sb3_hhp.train's summary for HhP), with ``code``: the commit each part
                       of the run was trained with and the package files that differed from it
    curves/<run>.csv   success rate and mean return at each periodic evaluation
    logs/<run>/        each run's log folder, logs/<run>.log its output

Sweep file (YAML)::

    name: doorkey8x8                 # default output folder name (default: the file's stem)
    envs: [MiniGrid-DoorKey-8x8-v0]
    variants: [hhp, dqn, ppo, ppo_rnd]
    seeds: [0, 1, 2]
    variant_seeds: {ppo_rnd: [0]}    # optional, the seeds of some variants instead of seeds
    steps: 300000                    # one budget, or a mapping env id -> budget
    eval_episodes: 100               # final evaluation (default 100)
    eval_freq: 10000                 # periodic evaluations, in env steps (default: steps // 20; 0: none)
    curve_episodes: 20               # episodes of each periodic evaluation (default 10)
    hhp_conf: sb3_hhp/hyperparams/hhp.yml    # optional
    hhp_args: []                     # optional, more options for sb3_hhp.train
    hhp_variants:                    # optional, more HhP variants: name (hhp_...) -> their own options, after hhp_args
      hhp_rho0.2: [--oracle, noisy-scripted, --hyperparams, "query_kwargs:dict(oracle_kwargs=dict(rho=0.2))"]
    baselines_conf: sb3_hhp/hyperparams/baselines.yml   # optional

Needs the ``plots`` extra (pandas).
"""

import argparse
import concurrent.futures
import contextlib
import dataclasses
import difflib
import functools
import json
import multiprocessing
import os
import re
import shutil
import subprocess
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Optional, Union

import yaml

from sb3_hhp.train import CHECKPOINT_FILE, RESUMED_FILE  # the run folders' files the training command writes


@dataclasses.dataclass(frozen=True)
class Baseline:
    """A flat baseline of the runner: its algorithm and what it reads of the env.

    :param algorithm: the algorithm's class, ``module.Class``
    :param hhp_observation: it reads the observation HhP sees (:func:`sb3_hhp.goals.wrap_env`: MiniGrid's egocentric
        view, Fetch's flattened); else the env's own (Fetch: the dict of observation, achieved and desired goal)
    :param her: it relabels its replay in hindsight: its entry names ``replay_buffer_class: HerReplayBuffer``, and
        its env must observe a dict goal
    """

    algorithm: str
    hhp_observation: bool = True
    her: bool = False


#: the flat baselines, in the order of tables and plots
BASELINES = {
    "dqn": Baseline("stable_baselines3.DQN"),
    "ppo": Baseline("stable_baselines3.PPO"),
    "ppo_rnd": Baseline("stable_baselines3.PPO"),
    "ddpg": Baseline("stable_baselines3.DDPG", hhp_observation=False),
    "ddpg_her": Baseline("stable_baselines3.DDPG", hhp_observation=False, her=True),
    "tqc_her": Baseline("sb3_contrib.TQC", hhp_observation=False, her=True),
}
#: the variants a sweep may name, in the order of tables and plots
VARIANTS = ("hhp", *BASELINES)
#: the keys of a sweep file, with their defaults (None: required or computed)
SWEEP_KEYS: dict[str, Any] = {
    "name": None,
    "envs": None,
    "variants": None,
    "seeds": None,
    "variant_seeds": {},
    "steps": None,
    "eval_episodes": 100,
    "eval_freq": None,
    "curve_episodes": 10,
    "hhp_conf": None,
    "hhp_args": [],
    "hhp_variants": {},
    "baselines_conf": "sb3_hhp/hyperparams/baselines.yml",
}
#: the columns of results.csv; a row's key is (env, variant, seed, steps); steps is the budget, timesteps the steps
#: trained (PPO rounds the budget up to whole rollouts of n_steps * n_envs)
COLUMNS = (
    "env", "variant", "seed", "steps", "timesteps", "success_det", "success_stoch", "return_det", "return_stoch",
    "labels_used", "eval_episodes", "train_seconds", "wall_seconds", "curve", "summary",
)
KEY_COLUMNS = ("env", "variant", "seed", "steps")
#: keys of a baseline entry read by the runner, as RL Zoo reads them (``vec_rnd``: ppo_rnd's curiosity); the rest go
#: to the algorithm's constructor
BASELINE_RUNNER_KEYS = ("n_envs", "policy", "vec_rnd", "normalize", "noise_type", "noise_std", "env_wrapper", "frame_stack",
                        "env_kwargs")
#: the replay buffers a baseline entry may name (``replay_buffer_class``), by name: ``module.Class``
REPLAY_BUFFERS = {
    "ReplayBuffer": "stable_baselines3.common.buffers.ReplayBuffer",
    "DictReplayBuffer": "stable_baselines3.common.buffers.DictReplayBuffer",
    "HerReplayBuffer": "stable_baselines3.HerReplayBuffer",
}
#: the action noises a baseline entry may name (``noise_type``, with ``noise_std``), RL Zoo's names: ``module.Class``
ACTION_NOISES = {
    "normal": "stable_baselines3.common.noise.NormalActionNoise",
    "ornstein-uhlenbeck": "stable_baselines3.common.noise.OrnsteinUhlenbeckActionNoise",
}
#: the keys of a goal env's dict observation, which hindsight relabels (SB3's ``HerReplayBuffer``)
GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")
#: periodic evaluations per run when the sweep does not set eval_freq
DEFAULT_CURVE_POINTS = 20
#: what a run's log folder records of the code each of its parts ran (:func:`code_version`), in order
CODE_FILE = "code.json"
#: the files that make a run's result, as git pathspecs (a change there outside a commit is named in ``code``); the
#: runs' own results are not among them
CODE_PATHSPECS = ("sb3_hhp", "benchmarks", "setup.cfg", "constraints.txt", ":(exclude)benchmarks/results")


class SweepError(ValueError):
    """A sweep file that cannot be run: reported in one line, before anything is trained."""


@dataclasses.dataclass(frozen=True)
class Experiment:
    """One training run of the sweep.

    :param env: gymnasium env id
    :param variant: one of :data:`VARIANTS`
    :param seed: training seed (>= 0); evaluation seeds start at ``seed + 10000``
    :param steps: training budget, primitive env steps (>= 1)
    """

    env: str
    variant: str
    seed: int
    steps: int

    @property
    def name(self) -> str:
        """File-name-safe id of the run, e.g. ``MiniGrid-DoorKey-8x8-v0__ppo__s0``."""
        return f"{self.env.replace('/', '-')}__{self.variant}__s{self.seed}"

    @property
    def key(self) -> tuple[str, str, int, int]:
        return (self.env, self.variant, self.seed, self.steps)


@dataclasses.dataclass(frozen=True)
class Sweep:
    """A parsed and checked sweep file (see the module's docstring for its keys)."""

    name: str
    experiments: tuple[Experiment, ...]
    eval_episodes: int
    eval_freq: dict[str, int]
    curve_episodes: int
    hhp_conf: Optional[str]
    hhp_args: tuple[str, ...]
    baselines_conf: str
    hhp_variants: dict[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)

    def is_hhp(self, variant: str) -> bool:
        """Whether ``variant`` trains HhP (``hhp`` or one of the sweep's ``hhp_variants``)."""
        return variant == "hhp" or variant in self.hhp_variants

    def hhp_options(self, variant: str) -> tuple[str, ...]:
        """The options ``sb3_hhp.train`` gets for an HhP variant beyond the runner's own."""
        return self.hhp_args + self.hhp_variants.get(variant, ())


# ---------------------------------------------------------------------- sweep file


def _positive_int(value: Any, what: str, minimum: int = 1) -> int:
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise SweepError(f"{what} must be an integer >= {minimum} (e.g. 300000 or 300_000), got {value!r}")
    return value


def _string_list(value: Any, what: str) -> list[str]:
    values = [value] if isinstance(value, str) else value
    if not isinstance(values, list) or not values or not all(isinstance(v, str) for v in values):
        raise SweepError(f"{what} must be a name or a non-empty list of names, got {value!r}")
    return values


def _seeds(value: Any, what: str) -> list[int]:
    """A seed or a non-empty list of seeds (integers >= 0)."""
    seeds = [_positive_int(seed, what, minimum=0) for seed in (value if isinstance(value, list) else [value])]
    if not seeds:
        raise SweepError(f"{what} must list at least one seed")
    return seeds


def _check_file(path: Optional[str], what: str) -> None:
    if path is not None and not os.path.isfile(path):
        raise SweepError(f"{what}: no such file {path!r} (paths are relative to the working directory)")


def _hhp_variants(value: Any, where: str) -> dict[str, tuple[str, ...]]:
    """``hhp_variants``: HhP variants (``hhp_<name>``, letters, digits, ``.``, ``-``, ``_``) and their options."""
    if not isinstance(value, dict):
        raise SweepError(f"{where}: hhp_variants must map variant names to lists of options, got {value!r}")
    variants = {}
    for name, options in value.items():
        if not isinstance(name, str) or not re.fullmatch(r"hhp_[A-Za-z0-9.\-]+(_[A-Za-z0-9.\-]+)*", name):
            raise SweepError(f"{where}: hhp_variants name {name!r} must start with hhp_ and hold only letters, digits, "
                             "'.', '-' and single '_' (it names files)")
        if not isinstance(options, list) or not all(isinstance(word, (str, int, float)) for word in options):
            raise SweepError(f"{where}: hhp_variants[{name}] must be a list of command-line words, got {options!r}")
        variants[name] = tuple(str(word) for word in options)
    return variants


def load_sweep(path: Union[str, Path], check_envs: bool = True) -> Sweep:
    """Read and check a sweep file.

    :param path: the YAML file
    :param check_envs: check every env id against the gymnasium registry and every baseline against
        ``baselines_conf`` (imports the env packages, about a second)
    :return: the sweep, its experiments in the order env, variant, seed
    """
    path = Path(path)
    try:
        table = yaml.safe_load(path.read_text())
    except OSError as error:
        raise SweepError(f"Cannot read the sweep file {path}: {error}") from error
    except yaml.YAMLError as error:
        raise SweepError(f"{path} is not valid YAML: {error}".replace("\n", " ")) from error
    where = str(path)
    if not isinstance(table, dict):
        raise SweepError(f"{where} must map keys ({', '.join(SWEEP_KEYS)}) to values, got {type(table).__name__}")
    for key in table:
        if key not in SWEEP_KEYS:
            close = difflib.get_close_matches(str(key), list(SWEEP_KEYS), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise SweepError(f"{where}: unknown key {key!r}{hint}; valid keys: {', '.join(SWEEP_KEYS)}")
    settings = {**SWEEP_KEYS, **table}
    for key in ("envs", "variants", "seeds", "steps"):
        if settings[key] is None:
            raise SweepError(f"{where}: {key!r} is required")
    envs = _string_list(settings["envs"], f"{where}: envs")
    hhp_variants = _hhp_variants(settings["hhp_variants"], where)
    variants = _string_list(settings["variants"], f"{where}: variants")
    known = (*VARIANTS, *hhp_variants)
    for variant in variants:
        if variant not in known:
            close = difflib.get_close_matches(variant, known, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise SweepError(f"{where}: unknown variant {variant!r}{hint}; use some of {', '.join(known)} "
                             "(more HhP variants are named in hhp_variants)")
    seeds = _seeds(settings["seeds"], f"{where}: seeds")
    variant_seeds = settings["variant_seeds"] or {}
    if not isinstance(variant_seeds, dict) or not all(variant in variants for variant in variant_seeds):
        raise SweepError(f"{where}: variant_seeds must map some of the sweep's variants ({', '.join(variants)}) to "
                         f"their seeds, got {variant_seeds!r}")
    seeds_of = {variant: _seeds(variant_seeds[variant], f"{where}: variant_seeds[{variant}]")
                if variant in variant_seeds else seeds for variant in variants}
    steps_value = settings["steps"]
    if isinstance(steps_value, dict):
        missing = [env for env in envs if env not in steps_value]
        if missing:
            raise SweepError(f"{where}: steps has no budget for {', '.join(missing)}")
        steps = {env: _positive_int(steps_value[env], f"{where}: steps[{env}]") for env in envs}
    else:
        steps = {env: _positive_int(steps_value, f"{where}: steps") for env in envs}
    if settings["eval_freq"] is None:
        eval_freq = {env: max(budget // DEFAULT_CURVE_POINTS, 1) for env, budget in steps.items()}
    else:
        eval_freq = {env: _positive_int(settings["eval_freq"], f"{where}: eval_freq", minimum=0) for env in envs}
    hhp_args = settings["hhp_args"] or []
    if not isinstance(hhp_args, list) or not all(isinstance(arg, (str, int, float)) for arg in hhp_args):
        raise SweepError(f"{where}: hhp_args must be a list of command-line words, got {hhp_args!r}")
    _check_file(settings["hhp_conf"], f"{where}: hhp_conf")
    _check_file(settings["baselines_conf"], f"{where}: baselines_conf")
    if check_envs:
        for env in envs:
            check_env(env, where)
        for variant in variants:
            if variant not in ("hhp", *hhp_variants):
                for env in envs:
                    baseline_settings(settings["baselines_conf"], variant, env)
                    if BASELINES[variant].her:
                        check_goal_observation(variant, env, where)
    sweep = Sweep(
        name=str(settings["name"] or path.stem),
        experiments=tuple(
            Experiment(env, variant, seed, steps[env]) for env in envs for variant in variants
            for seed in seeds_of[variant]
        ),
        eval_episodes=_positive_int(settings["eval_episodes"], f"{where}: eval_episodes", minimum=0),
        eval_freq=eval_freq,
        curve_episodes=_positive_int(settings["curve_episodes"], f"{where}: curve_episodes"),
        hhp_conf=settings["hhp_conf"],
        hhp_args=tuple(str(arg) for arg in hhp_args),
        baselines_conf=str(settings["baselines_conf"]),
        hhp_variants=hhp_variants,
    )
    return sweep


def check_env(env_id: str, where: str) -> None:
    """Refuse an env id that is not registered, suggesting the closest one (:func:`sb3_hhp.train.check_env_id`)."""
    from sb3_hhp.train import ConfigError, check_env_id

    try:
        check_env_id(env_id)
    except ConfigError as error:
        raise SweepError(f"{where}: {error}") from error


def baseline_settings(config: str, variant: str, env_id: str) -> dict[str, Any]:
    """The hyperparameters of a flat baseline: ``config[variant]``'s entry for ``env_id``, its domain or ``default``.

    :param config: the baselines' YAML file (``sb3_hhp/hyperparams/baselines.yml``)
    :param variant: one of :data:`BASELINES`
    :param env_id: a registered env id
    :raises SweepError: no entry, or one that names what the runner cannot build (a replay buffer or action noise not
        in :data:`REPLAY_BUFFERS` / :data:`ACTION_NOISES`; hindsight where the variant's name does not say so)
    """
    from sb3_hhp.train import ConfigError, select_entry

    try:
        with open(config) as file:
            table = yaml.safe_load(file)
    except (OSError, yaml.YAMLError) as error:
        raise SweepError(f"Cannot read the baselines' hyperparameters {config}: {error}") from error
    if not isinstance(table, dict) or variant not in table:
        raise SweepError(f"{config} has no entry {variant!r}: add one (keys: variants, then env ids or domains)")
    try:
        entry = select_entry(table[variant], env_id, f"{config} [{variant}]")
    except ConfigError as error:
        raise SweepError(str(error)) from error
    settings = dict(table[variant][entry] or {})
    where = f"{config} [{variant}][{entry}]"
    if "vec_rnd" in settings and variant != "ppo_rnd":
        raise SweepError(f"{where}: vec_rnd belongs to ppo_rnd only")
    if settings.get("normalize") and variant == "ppo_rnd":
        raise SweepError(f"{where}: normalize and ppo_rnd's curiosity wrap the same VecEnv: RND normalizes its own "
                         "inputs, leave normalize out")
    replay = settings.get("replay_buffer_class")
    if replay is not None and replay not in REPLAY_BUFFERS:
        raise SweepError(f"{where}: unknown replay_buffer_class {replay!r}; accepted: {', '.join(REPLAY_BUFFERS)}")
    if BASELINES[variant].her and replay != "HerReplayBuffer":
        raise SweepError(f"{where}: {variant} relabels in hindsight: set replay_buffer_class: HerReplayBuffer")
    if not BASELINES[variant].her and replay == "HerReplayBuffer":
        hindsight = ", ".join(name for name, baseline in BASELINES.items() if baseline.her)
        raise SweepError(f"{where}: {variant} trains without hindsight; HerReplayBuffer is for {hindsight}")
    if not isinstance(settings.get("replay_buffer_kwargs", {}), dict):
        raise SweepError(f"{where}: replay_buffer_kwargs must be a mapping (e.g. {{n_sampled_goal: 4, "
                         f"goal_selection_strategy: future}}), got {settings['replay_buffer_kwargs']!r}")
    noise = settings.get("noise_type")
    if noise is not None and (noise not in ACTION_NOISES or "noise_std" not in settings):
        raise SweepError(f"{where}: noise_type must be one of {', '.join(ACTION_NOISES)}, with noise_std (the noise's "
                         f"standard deviation, in units of the action), got {noise!r}")
    return settings


def check_goal_observation(variant: str, env_id: str, where: str, observation_space: Any = None) -> None:
    """Refuse a hindsight variant on an env that does not observe a dict goal (:data:`GOAL_KEYS`), which SB3's
    ``HerReplayBuffer`` relabels.

    :param variant: the variant (named in the error)
    :param env_id: a registered env id
    :param where: what the error names first (the sweep file)
    :param observation_space: the env's observation space (None: that of ``gym.make(env_id)``)
    """
    import gymnasium as gym

    if observation_space is None:
        env = gym.make(env_id)
        observation_space = env.observation_space
        env.close()
    keys = set(observation_space.spaces) if isinstance(observation_space, gym.spaces.Dict) else set()
    if not set(GOAL_KEYS) <= keys:
        raise SweepError(f"{where}: {variant} relabels goals in hindsight (HerReplayBuffer) and needs an env that "
                         f"observes a dict of {', '.join(GOAL_KEYS)} (a goal env, e.g. FetchReach-v4); {env_id} "
                         f"observes {observation_space}")


# ---------------------------------------------------------------------- one experiment (in a worker process)


def die_with_parent(parent_pid: int) -> None:
    """Have this process end (SIGTERM) when ``parent_pid``, the process that started it, ends: a runner killed
    does not leave its workers, nor their training processes, running on (Linux's ``PR_SET_PDEATHSIG``; elsewhere
    nothing). Called first thing in each worker and in each training process."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # 1: PR_SET_PDEATHSIG
    if os.getppid() != parent_pid:  # the parent ended before the signal was asked for
        os.kill(os.getpid(), signal.SIGTERM)



def attempt_evaluations(log_folder: Path) -> list[Path]:
    """The ``evaluations.npz`` of every attempt of a run, oldest first: one for a run trained in one go, one per part
    for an HhP run resumed from its checkpoints (each part logs to a run folder of its own)."""
    return sorted(Path(log_folder).rglob("evaluations.npz"), key=lambda path: path.stat().st_mtime)


def _curve_from_evaluations(npz_paths: Union[Path, Sequence[Path]], csv_path: Path) -> Optional[str]:
    """Write the periodic evaluations of an EvalCallback (``evaluations.npz``), or of the parts of a resumed run
    (oldest first), as a curve CSV.

    A part that resumed from a checkpoint (its run folder's ``resumed.json``) replaces what the parts before it
    evaluated after that checkpoint: those steps were trained again. Success at an evaluation is the fraction of its
    episodes with ``is_success`` when the env reports it, else with a positive return (MiniGrid pays only on
    reaching the goal), as :func:`sb3_hhp.train.evaluate`.
    """
    import numpy as np
    import pandas as pd

    parts = []
    for npz_path in [npz_paths] if isinstance(npz_paths, (str, Path)) else list(npz_paths):
        npz_path = Path(npz_path)
        if not npz_path.is_file():
            continue
        data = np.load(npz_path)
        returns = np.asarray(data["results"], dtype=float)
        if len(returns) == 0:
            continue
        successes = data["successes"] if "successes" in data.files and np.size(data["successes"]) else returns > 0
        part = pd.DataFrame({
            "steps": np.asarray(data["timesteps"], dtype=int),
            "success": np.asarray(successes, dtype=float).mean(axis=1),
            "mean_return": returns.mean(axis=1),
        })
        resumed = npz_path.parent / RESUMED_FILE
        if resumed.is_file() and parts:
            start = int(json.loads(resumed.read_text())["timesteps"])
            parts = [earlier[earlier["steps"] <= start] for earlier in parts]
        parts.append(part)
    if not parts:
        return None
    curve = pd.concat(parts, ignore_index=True)
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    curve.to_csv(csv_path, index=False)
    return str(csv_path)


def latest_checkpoint(log_folder: Path) -> Optional[Path]:
    """The run folder holding the latest checkpoint an unfinished HhP run left (``sb3_hhp.train --checkpoint-freq``),
    None when there is none."""
    best: Optional[tuple[int, Path]] = None
    own = Path(log_folder) / CHECKPOINT_FILE  # one run folder, or a training command's -f folder (runs in hhp/*)
    for pointer in [own] if own.is_file() else Path(log_folder).glob(f"hhp/*/{CHECKPOINT_FILE}"):
        try:
            steps = int(json.loads(pointer.read_text())["timesteps"])
        except (ValueError, KeyError, TypeError):
            continue
        if best is None or steps > best[0]:
            best = (steps, pointer.parent)
    return best[1] if best else None


def run_training(command: list[str], log_file: Any) -> int:
    """Run a training command to its end, its output into ``log_file``, one OpenMP thread; it ends with the worker
    that started it (:func:`die_with_parent`). Returns its exit status."""
    completed = subprocess.run(
        command, stdout=log_file, stderr=subprocess.STDOUT, env={**os.environ, "OMP_NUM_THREADS": "1"},
        preexec_fn=functools.partial(die_with_parent, os.getpid()),
    )
    return completed.returncode


def _run_hhp(experiment: Experiment, sweep: Sweep, out: Path, log_file: Any) -> dict[str, Any]:
    summary_path = out / "runs" / f"{experiment.name}.json"
    log_folder = out / "logs" / experiment.name
    options = list(sweep.hhp_options(experiment.variant))
    oracle = [] if "--oracle" in options else ["--oracle", "scripted"]  # a variant's own oracle replaces it
    command = [
        sys.executable, "-m", "sb3_hhp.train", "--env", experiment.env, *oracle,
        "-n", str(experiment.steps), "--seed", str(experiment.seed), "--eval-both",
        "--eval-episodes", str(sweep.eval_episodes), "--summary-json", str(summary_path),
        "-f", str(log_folder), "--num-threads", "1",
        "--eval-freq", str(sweep.eval_freq[experiment.env] or -1),
        "--periodic-eval-episodes", str(sweep.curve_episodes),
        # a checkpoint at every periodic evaluation: a run stopped before its end goes on from the last one
        "--checkpoint-freq", str(sweep.eval_freq[experiment.env] or max(experiment.steps // 10, 1)),
    ]
    resume = latest_checkpoint(log_folder)
    if resume is not None:
        command += ["--resume", str(resume)]
    if sweep.hhp_conf:
        command += ["--conf-file", sweep.hhp_conf]
    command += options
    log_file.write("$ " + " ".join(command) + "\n")
    log_file.flush()
    returncode = run_training(command, log_file)
    if returncode != 0:
        raise RuntimeError(f"sb3_hhp.train exited with status {returncode}")
    summary = json.loads(summary_path.read_text())
    return {
        "summary": summary,
        "summary_path": summary_path,
        "labels_used": summary["queries_used"],
    }


def _baseline_envs(env_id: str, baseline: Baseline, n_envs: int, seed: Optional[int] = None,
                   runner: Optional[dict[str, Any]] = None) -> Any:
    """A VecEnv of ``n_envs`` envs (each in a ``Monitor``) with the observation ``baseline`` reads: the entry's
    ``env_wrapper`` (as RL Zoo names it: Atari's ``AtariWrapper``) where it has one, else HhP's observation on
    MiniGrid; its ``frame_stack`` frames stacked (``VecFrameStack``, as RL Zoo stacks Atari's); its ``env_kwargs``
    passed to ``gym.make`` (ALE's ``frameskip: 1`` under ``AtariWrapper``)."""
    from rl_zoo3.utils import get_wrapper_class
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecFrameStack

    from sb3_hhp.goals import wrap_env

    runner = runner or {}
    wrapper = get_wrapper_class(runner) if runner.get("env_wrapper") else (wrap_env if baseline.hhp_observation else None)
    envs = make_vec_env(env_id, n_envs=n_envs, seed=seed, wrapper_class=wrapper, env_kwargs=runner.get("env_kwargs"))
    return VecFrameStack(envs, int(runner["frame_stack"])) if runner.get("frame_stack") else envs


def _normalize_kwargs(normalize: Any, gamma: Optional[float]) -> Optional[dict[str, Any]]:
    """``VecNormalize``'s arguments for an entry's ``normalize`` as RL Zoo reads it (true, or a mapping of those
    arguments; the reward's discount the algorithm's ``gamma``); None: no normalization."""
    if not normalize:
        return None
    kwargs = dict(normalize) if isinstance(normalize, dict) else {}
    return {**kwargs, "gamma": gamma} if gamma is not None else kwargs


def frozen_normalization(envs: Any, trained: Any) -> Any:
    """``envs`` normalized by the statistics of ``trained``, the training env's ``VecNormalize``, which they do not
    update, with the env's own rewards (RL Zoo's evaluation envs); ``envs`` as they are when ``trained`` is None."""
    import copy

    from stable_baselines3.common.vec_env import VecNormalize

    if trained is None:
        return envs
    frozen = VecNormalize(envs, training=False, norm_obs=trained.norm_obs, norm_reward=False, clip_obs=trained.clip_obs,
                          epsilon=trained.epsilon, norm_obs_keys=trained.norm_obs_keys)
    frozen.obs_rms = copy.deepcopy(trained.obs_rms)
    return frozen


def _constructor_arguments(settings: dict[str, Any], runner: dict[str, Any], action_space: Any) -> dict[str, Any]:
    """An entry's constructor arguments as the algorithm takes them: the replay buffer's class from its name, RL
    Zoo's ``train_freq`` list as a tuple, its ``noise_type`` / ``noise_std`` as an action noise of that std on every
    action coordinate."""
    import copy

    import numpy as np
    from rl_zoo3.utils import get_class_by_name

    arguments = copy.deepcopy(settings)  # the algorithm adds to its policy_kwargs; the run's summary keeps the entry's
    if "replay_buffer_class" in arguments:
        arguments["replay_buffer_class"] = get_class_by_name(REPLAY_BUFFERS[arguments["replay_buffer_class"]])
    if isinstance(arguments.get("train_freq"), list):
        arguments["train_freq"] = tuple(arguments["train_freq"])
    if runner.get("noise_type") is not None:
        shape = action_space.shape
        arguments["action_noise"] = get_class_by_name(ACTION_NOISES[runner["noise_type"]])(
            mean=np.zeros(shape), sigma=float(runner["noise_std"]) * np.ones(shape))
    return arguments


def _run_baseline(experiment: Experiment, sweep: Sweep, out: Path) -> dict[str, Any]:
    import torch as th
    from rl_zoo3.utils import get_class_by_name
    from stable_baselines3.common.callbacks import CallbackList, EvalCallback
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
    from stable_baselines3.common.vec_env import VecNormalize

    from sb3_hhp.curiosity import VecRNDReward
    from sb3_hhp.train import (check_env_id, checkpoint_callback_class, domain_of, eval_seeds, evaluate, read_checkpoint,
                               resume_seed)

    th.set_num_threads(1)
    check_env_id(experiment.env)  # MiniGrid's, Fetch's and ALE's envs registered, as sb3_hhp.train registers them
    baseline = BASELINES[experiment.variant]
    settings = baseline_settings(sweep.baselines_conf, experiment.variant, experiment.env)
    runner = {key: settings.pop(key) for key in BASELINE_RUNNER_KEYS if key in settings}
    n_envs = int(runner.get("n_envs", 1))
    policy = runner.get("policy", "MlpPolicy")
    log_folder = out / "logs" / experiment.name
    # a run stopped before its end goes on from its last checkpoint, its envs seeded apart from its first part's
    checkpoint = read_checkpoint(str(log_folder)) if latest_checkpoint(log_folder) is not None else None
    seed = experiment.seed if checkpoint is None else resume_seed(experiment.seed, checkpoint["timesteps"])
    env = _baseline_envs(experiment.env, baseline, n_envs, seed, runner)
    if baseline.her:
        check_goal_observation(experiment.variant, experiment.env, sweep.name, env.observation_space)
    normalize = _normalize_kwargs(runner.get("normalize"), settings.get("gamma"))
    if normalize is not None:  # a resumed run's statistics go on from its checkpoint's
        resumed = checkpoint is not None and checkpoint["vec_normalize"] is not None
        env = VecNormalize.load(checkpoint["vec_normalize"], env) if resumed else VecNormalize(env, **normalize)
    vec_rnd = runner.get("vec_rnd")
    if experiment.variant == "ppo_rnd":
        vec_rnd = dict(vec_rnd or {})
        vec_rnd["rnd_kwargs"] = {"seed": experiment.seed, **(vec_rnd.get("rnd_kwargs") or {})}
        env = VecRNDReward(env, **vec_rnd)
    algo = get_class_by_name(baseline.algorithm)
    part_folder = log_folder  # where this part's periodic evaluations go
    if checkpoint is None:
        model = algo(policy, env, seed=experiment.seed, device="cpu", verbose=0,
                     **_constructor_arguments(settings, runner, env.action_space))
    else:
        print(f"Resuming {log_folder} at {checkpoint['timesteps']} steps")
        if checkpoint["vec_rnd"] is not None:
            env.load_state_dict(th.load(checkpoint["vec_rnd"], weights_only=True))
        model = algo.load(checkpoint["model"], env=env, device="cpu", verbose=0)
        if checkpoint["replay"] is not None:  # a HerReplayBuffer gets the model's env back (it relabels through it)
            with warnings.catch_warnings():  # and ends its last episode there, as this part starts a fresh one
                warnings.filterwarnings("ignore", message="The last trajectory in the replay buffer will be truncated")
                model.load_replay_buffer(checkpoint["replay"])
        model.set_random_seed(seed)
        part_folder = log_folder / f"part_{checkpoint['timesteps']}"
        part_folder.mkdir(parents=True, exist_ok=True)
        (part_folder / RESUMED_FILE).write_text(json.dumps({"timesteps": checkpoint["timesteps"], "seed": seed}) + "\n")
    earlier_seconds = checkpoint["train_seconds"] if checkpoint is not None else 0.0

    def make_envs(n: int, seed: Optional[int] = None) -> Any:  # evaluation envs, normalized as training leaves them
        return frozen_normalization(_baseline_envs(experiment.env, baseline, n, seed, runner), model.get_vec_normalize_env())

    callbacks = []
    eval_freq = sweep.eval_freq[experiment.env]
    if eval_freq > 0:
        # periodic evaluations on their own env, seeded apart from training; stochastic on MiniGrid (as RL Zoo);
        # EvalCallback records is_success where the env reports it, and keeps a VecNormalize's statistics in step
        callbacks.append(EvalCallback(
            make_envs(1, eval_seeds(experiment.seed, 1)[0]), n_eval_episodes=sweep.curve_episodes,
            eval_freq=max(eval_freq // n_envs, 1), log_path=str(part_folder),
            deterministic=domain_of(experiment.env) != "minigrid", verbose=0,
        ))
    # a checkpoint at every periodic evaluation (after it: its curve point is on disk), as HhP runs write them;
    # an off-policy baseline's at the end of the rollout, once the step's transition is in its replay
    callbacks.append(checkpoint_callback_class()(eval_freq or max(experiment.steps // 10, 1), str(log_folder),
                                                  earlier_seconds, at_rollout_end=issubclass(algo, OffPolicyAlgorithm)))
    start = time.perf_counter()
    model.learn(max(0, experiment.steps - model.num_timesteps), callback=CallbackList(callbacks),
                reset_num_timesteps=checkpoint is None)
    train_seconds = time.perf_counter() - start
    model.save(log_folder / "model.zip")
    if model.get_vec_normalize_env() is not None:  # the statistics the model's inputs need, beside it
        model.get_vec_normalize_env().save(log_folder / "vec_normalize.pkl")
    seeds = eval_seeds(experiment.seed, sweep.eval_episodes)
    summary: dict[str, Any] = {
        "env": experiment.env, "variant": experiment.variant, "seed": experiment.seed,
        "total_timesteps": int(model.num_timesteps), "train_seconds": round(train_seconds, 3),
        "fps": round((model.num_timesteps - (checkpoint or {}).get("timesteps", 0)) / train_seconds, 1)
        if train_seconds > 0 else None,
        **({"resumed_at": checkpoint["timesteps"], "train_seconds_all_parts": round(earlier_seconds + train_seconds, 3)}
           if checkpoint is not None else {}),
        "eval_episodes": len(seeds), "eval_seeds": seeds,
        "hyperparams": {**runner, "n_envs": n_envs, "policy": policy, **settings,
                        **({"vec_rnd": vec_rnd} if vec_rnd else {})},
        "log_path": str(log_folder),
    }
    for name, deterministic in (("deterministic", True), ("stochastic", False)):
        results = evaluate(model, make_envs, seeds, deterministic=deterministic)
        summary[f"success_rate_{name}"] = sum(results["successes"]) / len(seeds) if seeds else None
        summary[f"mean_return_{name}"] = sum(results["returns"]) / len(seeds) if seeds else None
    env.close()
    summary_path = out / "runs" / f"{experiment.name}.json"
    summary_path.parent.mkdir(parents=True, exist_ok=True)
    summary_path.write_text(json.dumps(summary, indent=2) + "\n")
    return {
        "summary": summary,
        "summary_path": summary_path,
        "labels_used": None,
    }


def code_version(root: Optional[Path] = None) -> Optional[dict[str, Any]]:
    """The code a run trains with: ``commit`` (the HEAD of the checkout ``root``, default this one) and ``changed``,
    the tracked files of :data:`CODE_PATHSPECS` that differ from it (an uncommitted change a result would otherwise
    hide); None outside a git checkout."""
    root = Path(__file__).resolve().parents[1] if root is None else Path(root)

    def git(*words: str) -> Optional[str]:
        try:
            done = subprocess.run(["git", "-C", str(root), *words], capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return done.stdout if done.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    if not commit:
        return None
    changed = git("status", "--porcelain", "--untracked-files=no", "--", *CODE_PATHSPECS) or ""
    return {"commit": commit.strip(), "changed": sorted(line[3:] for line in changed.splitlines() if line.strip())}


def _record_code(log_folder: Path, resume: Optional[Path]) -> list[dict[str, Any]]:
    """This part's :func:`code_version` added to the run's record in ``log_folder`` (one entry a part, with the
    step count of the checkpoint ``resume`` it goes on from, :func:`latest_checkpoint`): the record."""
    path = log_folder / CODE_FILE
    parts = json.loads(path.read_text()) if path.is_file() else []
    part = {"from_step": 0 if resume is None else int(json.loads((resume / CHECKPOINT_FILE).read_text()).get("timesteps", 0)),
            **(code_version() or {"commit": None, "changed": []})}
    parts.append(part)
    path.write_text(json.dumps(parts, indent=2) + "\n")
    return parts


def run_experiment(experiment: Experiment, sweep: Sweep, out: Union[str, Path]) -> dict[str, Any]:
    """Train and evaluate one experiment; its output goes to ``logs/<run>.log``.

    :param experiment: what to run
    :param sweep: the sweep's settings
    :param out: the sweep's output folder
    :return: its row of ``results.csv`` (paths relative to ``out``)
    """
    out = Path(out)
    log_folder = out / "logs" / experiment.name
    resume = latest_checkpoint(log_folder)
    resumes = resume is not None  # every variant goes on from its last checkpoint
    if not resumes:
        shutil.rmtree(log_folder, ignore_errors=True)  # a failed earlier attempt's files
    log_folder.mkdir(parents=True, exist_ok=True)
    code = _record_code(log_folder, resume)
    start = time.perf_counter()
    with open(out / "logs" / f"{experiment.name}.log", "a" if resumes else "w") as log_file:
        if sweep.is_hhp(experiment.variant):
            result = _run_hhp(experiment, sweep, out, log_file)
        else:
            with contextlib.redirect_stdout(log_file), contextlib.redirect_stderr(log_file):
                result = _run_baseline(experiment, sweep, out)
    summary = result["summary"]
    summary["code"] = code  # the commit of each part, in the run's summary next to its figures
    Path(result["summary_path"]).write_text(json.dumps(summary, indent=2) + "\n")
    wall_seconds = time.perf_counter() - start + earlier_parts_seconds(summary)
    curve = _curve_from_evaluations(attempt_evaluations(log_folder), out / "curves" / f"{experiment.name}.csv")
    return {
        "env": experiment.env,
        "variant": experiment.variant,
        "seed": experiment.seed,
        "steps": experiment.steps,
        "timesteps": summary.get("total_timesteps"),
        "success_det": summary.get("success_rate_deterministic"),
        "success_stoch": summary.get("success_rate_stochastic"),
        "return_det": summary.get("mean_return_deterministic"),
        "return_stoch": summary.get("mean_return_stochastic"),
        "labels_used": result["labels_used"],
        "eval_episodes": summary.get("eval_episodes"),
        "train_seconds": summary.get("train_seconds_all_parts", summary.get("train_seconds")),  # a resumed run's parts
        "wall_seconds": round(wall_seconds, 1),  # with a resumed run's earlier parts (their training)
        "curve": os.path.relpath(curve, out) if curve else None,
        "summary": os.path.relpath(result["summary_path"], out),
    }


def earlier_parts_seconds(summary: dict[str, Any]) -> float:
    """The training seconds of a resumed run's earlier parts, from its summary (0 for a run trained in one part):
    what the run's wall time adds to this part's (their evaluations are not counted)."""
    if summary.get("train_seconds_all_parts") is None:
        return 0.0
    return max(0.0, float(summary["train_seconds_all_parts"]) - float(summary.get("train_seconds") or 0.0))


# ---------------------------------------------------------------------- the sweep


def read_results(csv_path: Union[str, Path]) -> Any:
    """``results.csv`` as a DataFrame (an empty one with :data:`COLUMNS` when the file does not exist)."""
    import pandas as pd

    csv_path = Path(csv_path)
    if not csv_path.is_file():
        return pd.DataFrame(columns=list(COLUMNS))
    results = pd.read_csv(csv_path)
    missing = [column for column in KEY_COLUMNS if column not in results.columns]
    if missing:
        raise SweepError(f"{csv_path} lacks the columns {', '.join(missing)}: not a results file of this runner")
    return results


def write_results(results: Any, csv_path: Union[str, Path]) -> None:
    """Write ``results`` sorted by env, variant (in :data:`VARIANTS` order) and seed, atomically."""
    csv_path = Path(csv_path)
    order = {variant: index for index, variant in enumerate(VARIANTS)}  # HhP variants after the baselines, by name
    results = results.sort_values(
        ["env", "variant", "seed"],
        key=lambda column: column.map(lambda v: f"{order.get(v, len(order))}:{v}") if column.name == "variant" else column,
    )
    temporary = csv_path.with_suffix(".csv.tmp")
    results.to_csv(temporary, index=False)
    os.replace(temporary, csv_path)


def add_result(row: dict[str, Any], csv_path: Union[str, Path]) -> None:
    """Add one experiment's row to ``results.csv``, read again under a lock: several runners of parts of one sweep
    (``--envs``, ``--variants``, ``--seeds``) may write into the same folder, and none loses another's rows."""
    import fcntl

    import pandas as pd

    csv_path = Path(csv_path)
    with open(csv_path.with_suffix(".csv.lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        results = read_results(csv_path)
        same = pd.Series(True, index=results.index)
        for column in KEY_COLUMNS:  # a row of the same experiment (a rerun) is replaced
            same &= results[column] == row[column]
        results = pd.concat([results[~same].dropna(axis=1, how="all"), pd.DataFrame([row])], ignore_index=True)
        write_results(results.reindex(columns=list(COLUMNS)), csv_path)


def select_experiments(
    sweep: Sweep,
    envs: Optional[list[str]] = None,
    variants: Optional[list[str]] = None,
    seeds: Optional[list[int]] = None,
) -> Sweep:
    """The part of ``sweep`` with the given envs, variants and seeds (None: all), e.g. one long run at a time.

    :raises SweepError: a value the sweep does not have (the sweep's own values are named)
    """
    experiments = sweep.experiments
    for field, wanted in (("env", envs), ("variant", variants), ("seed", seeds)):
        if wanted is None:
            continue
        present = list(dict.fromkeys(getattr(experiment, field) for experiment in sweep.experiments))
        unknown = [value for value in wanted if value not in present]
        if unknown:
            raise SweepError(
                f"the sweep {sweep.name!r} has no {field} {', '.join(map(str, unknown))}; "
                f"its {field}s: {', '.join(map(str, present))}"
            )
        experiments = tuple(experiment for experiment in experiments if getattr(experiment, field) in wanted)
    return dataclasses.replace(sweep, experiments=experiments)


def pending_experiments(sweep: Sweep, results: Any) -> list[Experiment]:
    """The experiments of ``sweep`` with no row in ``results`` yet (same env, variant, seed and steps)."""
    done = {
        (str(row.env), str(row.variant), int(row.seed), int(row.steps))
        for row in results[list(KEY_COLUMNS)].itertuples(index=False)
    }
    return [experiment for experiment in sweep.experiments if experiment.key not in done]


def run_sweep(
    sweep: Sweep,
    out: Union[str, Path],
    jobs: int = 1,
    runner: Callable[[Experiment, Sweep, Path], dict[str, Any]] = run_experiment,
) -> tuple[Path, list[str]]:
    """Run the experiments of ``sweep`` that have no row yet, ``jobs`` at a time, each in a fresh process.

    :param sweep: the sweep
    :param out: output folder (created)
    :param jobs: worker processes (>= 1)
    :param runner: runs one experiment and returns its row (:func:`run_experiment`); a module-level function,
        as it is sent to the worker processes
    :return: the CSV's path and one message per failed experiment
    """
    import pandas as pd
    from tqdm import tqdm

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / "results.csv"
    results = read_results(csv_path)
    todo = pending_experiments(sweep, results)
    skipped = len(sweep.experiments) - len(todo)
    if skipped:
        print(f"{skipped} of {len(sweep.experiments)} experiments already in {csv_path}: skipped")
    failures: list[str] = []
    if not todo:
        return csv_path, failures
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(max_workers=jobs, mp_context=context, max_tasks_per_child=1,
                                                initializer=die_with_parent, initargs=(os.getpid(),)) as pool:
        futures = {pool.submit(runner, experiment, sweep, out): experiment for experiment in todo}
        progress = tqdm(concurrent.futures.as_completed(futures), total=len(futures), desc=sweep.name, unit="run")
        for future in progress:
            experiment = futures[future]
            try:
                row = future.result()
            except Exception as error:  # one failed run must not stop the sweep; its log says why
                log = out / "logs" / f"{experiment.name}.log"
                failures.append(f"{experiment.name}: {type(error).__name__}: {error} (log: {log})")
                progress.write(f"failed: {failures[-1]}")
                continue
            add_result(row, csv_path)
            det, stoch = (row.get(key) for key in ("success_det", "success_stoch"))
            progress.write(f"{experiment.name}: success det {det} stoch {stoch}, {row.get('wall_seconds')} s")
    return csv_path, failures


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.run",
        description="Run a sweep of experiments (env x variant x seed) in parallel; one CSV of results.",
    )
    parser.add_argument("config", help="the sweep's YAML file (e.g. benchmarks/experiments/doorkey8x8.yml)")
    parser.add_argument("--jobs", type=int, default=1, help="experiments at once, one process each (default 1)")
    parser.add_argument("--out", default=None, help="output folder (default benchmarks/results/<sweep name>)")
    parser.add_argument("--envs", nargs="+", default=None, help="run only these of the sweep's env ids")
    parser.add_argument("--variants", nargs="+", default=None, help="run only these of the sweep's variants")
    parser.add_argument("--seeds", nargs="+", type=int, default=None, help="run only these of the sweep's seeds")
    args = parser.parse_args(argv)
    try:
        if args.jobs < 1:
            raise SweepError(f"--jobs must be >= 1, got {args.jobs}")
        sweep = select_experiments(load_sweep(args.config), args.envs, args.variants, args.seeds)
        out = Path(args.out) if args.out else Path("benchmarks") / "results" / sweep.name
        start = time.perf_counter()
        csv_path, failures = run_sweep(sweep, out, args.jobs)
    except SweepError as error:
        print(f"python -m benchmarks.run: error: {error}", file=sys.stderr)
        return 2
    print(f"Results: {csv_path} ({time.perf_counter() - start:.0f} s); report: python benchmarks/report.py {csv_path}")
    if failures:
        print(f"{len(failures)} experiments failed (rerun the same command to retry them):", file=sys.stderr)
        for failure in failures:
            print(f"  {failure}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
