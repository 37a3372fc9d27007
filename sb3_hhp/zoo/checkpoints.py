"""Checkpoints of a run (``--checkpoint-freq``) and going on from them (``--resume``).

A run folder keeps one complete checkpoint, ``checkpoints/<steps>/`` (the model, its replays, a curiosity wrapper's
state, a ``VecNormalize``'s statistics), and ``checkpoint.json`` pointing at it, written last: a run stopped at any
moment can go on from there. A resumed part writes ``resumed.json`` (the run folder and checkpoint it went on from)
and keeps its answers in the first part's preference database (:func:`answers_database`). It draws its episodes
from :func:`resume_seed`.
"""

import json
import os
import shutil
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from sb3_hhp.zoo.config import PREFERENCE_DB_NAME, ConfigError


#: the run folder's latest checkpoint (--checkpoint-freq, --resume)
CHECKPOINT_FILE = "checkpoint.json"
#: a resumed part's folder: the run folder and checkpoint it went on from
RESUMED_FILE = "resumed.json"


def checkpoint_callback_class() -> type:
    """``LatestCheckpoint``, a :class:`~stable_baselines3.common.callbacks.BaseCallback` (built on first use,
    so that importing this module does not import SB3)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class LatestCheckpoint(BaseCallback):
        """Every ``save_freq`` primitive steps (and at the end of training), the model (:meth:`HhP.save`), its
        replays (:meth:`HhP.save_replay_buffer`; any off-policy model's), the state of a
        :class:`~sb3_hhp.curiosity.vec_rnd.VecRNDReward` around its env (an on-policy baseline's curiosity) and the
        statistics of a ``VecNormalize`` around it (a baseline's normalized inputs) in
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
            """The checkpoint's files (model, replays, curiosity state, normalization statistics) in ``folder``;
            their paths for the pointer."""
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
            normalization = self.model.get_vec_normalize_env()
            if normalization is not None:
                normalization.save(folder / "vec_normalize.pkl")
                files["vec_normalize"] = f"checkpoints/{steps}/vec_normalize.pkl"
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
    """The :class:`~sb3_hhp.curiosity.vec_rnd.VecRNDReward` among the VecEnv wrappers of ``env``, None when there is none."""
    from stable_baselines3.common.vec_env import unwrap_vec_wrapper

    from sb3_hhp.curiosity import VecRNDReward

    return unwrap_vec_wrapper(env, VecRNDReward) if env is not None else None


def read_checkpoint(run_folder: str) -> dict[str, Any]:
    """The latest checkpoint of a run folder (``checkpoint.json``): its step count and the paths of the model, the
    replays (off-policy models), a curiosity wrapper's state (``vec_rnd``) and a ``VecNormalize``'s statistics
    (``vec_normalize``), each where the run had one (None otherwise). A clear error when there is none or its files
    are gone."""
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
                         for what in ("replay", "vec_rnd", "vec_normalize")},
                      "run_folder": str(folder), "train_seconds": float(checkpoint.get("train_seconds", 0.0))}
    except (ValueError, KeyError, TypeError) as error:
        raise ConfigError(f"--resume {run_folder}: {pointer} is damaged ({error})") from error
    for what in ("model", "replay", "vec_rnd", "vec_normalize"):
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


def resume_seed(seed: int, timesteps: int) -> int:
    """The seed of a run's part resumed at ``timesteps``: its envs' layouts, exploration and torch draws.

    A resumed part seeded with the run's own seed would replay the episodes the run began with. This seed is drawn
    from ``(seed, timesteps)`` (the same checkpoint resumes the same way) in ``[2**30, 2**31)``: above every
    training seed ``seed .. seed + n_envs - 1`` and evaluation seed (:func:`~sb3_hhp.zoo.evaluation.eval_seeds`) of a
    run seeded below ``2**30 - 10**6``, and below ``2**32`` with any env's rank added.

    :param seed: the run's training seed (>= 0)
    :param timesteps: the checkpoint's step count (>= 0)
    """
    if seed < 0 or timesteps < 0:
        raise ValueError(f"seed and timesteps must be >= 0, got {seed} and {timesteps}")
    state = int(np.random.SeedSequence([int(seed), int(timesteps)]).generate_state(1)[0])
    return (1 << 30) + state % (1 << 30)
