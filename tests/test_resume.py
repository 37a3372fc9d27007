"""Going on with training where it stopped: HhP's replays in a file (``save_replay_buffer`` /
``load_replay_buffer``) and ``python -m sb3_hhp.train --checkpoint-freq`` / ``--resume``."""

import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.save_util import save_to_pkl

from sb3_hhp import HhP
from sb3_hhp.goals import wrap_env
from sb3_hhp.zoo.checkpoints import resume_seed
from sb3_hhp.zoo.evaluation import eval_seeds

ENV = "MiniGrid-DoorKey-5x5-v0"


def make_model(seed: int = 0, **kwargs) -> HhP:
    env = make_vec_env(ENV, n_envs=2, wrapper_class=wrap_env, seed=seed)
    return HhP("MlpPolicy", env, seed=seed, oracle="scripted", learning_starts=100,
               **{"buffer_size": 20_000, **kwargs})


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A model trained 2,500 steps, saved with its replays."""
    folder = tmp_path_factory.mktemp("saved")
    model = make_model()
    model.learn(2_500)
    model.save(folder / "model.zip")
    model.save_replay_buffer(folder / "replay.pkl")
    return model, folder


def test_replays_are_saved_and_loaded_whole(trained):
    model, folder = trained
    loaded = HhP.load(folder / "model.zip", env=make_vec_env(ENV, n_envs=2, wrapper_class=wrap_env, seed=1))
    loaded.load_replay_buffer(folder / "replay.pkl")
    shared, shared_loaded = model.subpolicies.replay, loaded.subpolicies.replay
    rows = shared.size()
    assert rows > 1000 and shared_loaded.size() == rows and shared_loaded.full == shared.full
    for name in ("observations", "next_observations", "actions", "key_ids", "terminated", "gave_up", "acting", "intrinsic"):
        np.testing.assert_array_equal(getattr(shared_loaded, name)[:rows], getattr(shared, name)[:rows], err_msg=name)
    np.testing.assert_array_equal(shared_loaded.trees._sum, shared.trees._sum)  # every sub-goal's priorities
    assert shared_loaded.goal_keys == shared.goal_keys and shared_loaded.keys == shared.keys
    # training goes on from fresh episodes: the newest transition of each env ends its returns (a time-limit cut)
    newest = rows - 1
    assert (shared_loaded.truncated[newest] | shared_loaded.terminated[newest]).all()
    np.testing.assert_array_equal(shared_loaded.truncated[:newest], shared.truncated[:newest])  # the rest as saved
    # the next draws are the ones the saved model would have made
    goals = np.arange(len(shared.goal_keys))
    np.testing.assert_array_equal(shared_loaded.sample(goals, 16).leaves, shared.sample(goals, 16).leaves)
    meta, meta_loaded = model.replay_buffer, loaded.replay_buffer
    assert meta.pos > 100 and meta_loaded.pos == meta.pos
    np.testing.assert_array_equal(meta_loaded.observations[: meta.pos], meta.observations[: meta.pos])
    np.testing.assert_array_equal(meta_loaded.rewards[: meta.pos], meta.rewards[: meta.pos])
    np.testing.assert_array_equal(meta_loaded.tree._sum, meta.tree._sum)  # the priorities
    # only the rows in use are written: R_H is allocated for 20,000 choices and holds a few hundred
    with open(folder / "replay.pkl", "rb") as file:
        saved = pickle.load(file)
    assert len(saved["meta"]["attributes"]["observations"]) == meta.pos < meta.buffer_size
    assert len(saved["subgoal_learners"]["replay"]["attributes"]["observations"]) == rows < shared.capacity
    loaded.learn(300, reset_num_timesteps=False)  # and training goes on from them
    assert loaded.num_timesteps >= model.num_timesteps + 300


def test_load_replay_buffer_refuses_what_does_not_fit(trained, tmp_path):
    model, folder = trained
    fresh = make_model()  # no sub-goals yet: the file's replay belongs to another model
    with pytest.raises(ValueError, match="load the replay saved with this model"):
        fresh.load_replay_buffer(folder / "replay.pkl")
    loaded = HhP.load(folder / "model.zip", env=make_vec_env(ENV, n_envs=2, wrapper_class=wrap_env), buffer_size=30_000)
    with pytest.raises(ValueError, match="buffer size it was saved with"):
        loaded.load_replay_buffer(folder / "replay.pkl")
    four = HhP.load(folder / "model.zip", env=make_vec_env(ENV, n_envs=4, wrapper_class=wrap_env))
    with pytest.raises(ValueError, match="transitions of 2 envs, the model steps 4: give the model as many envs"):
        four.load_replay_buffer(folder / "replay.pkl")
    save_to_pkl(tmp_path / "other.pkl", {"something": 1})
    with pytest.raises(ValueError, match="not a replay saved by HhP.save_replay_buffer"):
        model.load_replay_buffer(tmp_path / "other.pkl")
    (tmp_path / "damaged.pkl").write_bytes((folder / "replay.pkl").read_bytes()[:5000])
    with pytest.raises(ValueError, match="damaged or truncated"):
        model.load_replay_buffer(tmp_path / "damaged.pkl")


def test_an_sb3_replay_file_is_taken_as_the_meta_replay(trained, tmp_path):
    model, folder = trained
    save_to_pkl(tmp_path / "meta.pkl", model.replay_buffer)  # what SB3's own save_replay_buffer writes
    loaded = HhP.load(folder / "model.zip", env=make_vec_env(ENV, n_envs=2, wrapper_class=wrap_env))
    loaded.load_replay_buffer(tmp_path / "meta.pkl")
    assert loaded.replay_buffer.pos == model.replay_buffer.pos
    assert loaded.subpolicies.replay.size() == 0  # the sub-goal learners' replay is not in such a file


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "sb3_hhp.train", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=600)


def test_a_resumed_part_is_seeded_apart_from_the_run_and_its_evaluations():
    seeds = {resume_seed(seed, steps) for seed in range(5) for steps in (0, 1000, 10_000, 2_000_000)}
    assert len(seeds) == 20  # every (seed, checkpoint) resumes differently
    assert resume_seed(3, 1000) == resume_seed(3, 1000)  # and the same checkpoint the same way
    assert min(seeds) >= 2**30 and max(seeds) + 64 < 2**32  # any env's rank added, still a 32-bit seed
    training_and_eval = set(range(5 + 64)) | {s for seed in range(5) for s in eval_seeds(seed, 1000)}
    assert all(seed + rank not in training_and_eval for seed in seeds for rank in range(64))
    with pytest.raises(ValueError, match=">= 0"):
        resume_seed(-1, 0)


@pytest.mark.slow
def test_a_run_goes_on_from_its_checkpoint(tmp_path):
    """A run stopped at its checkpoint goes on with --resume: the step count goes on to -n, answers go to the same
    preference database and no question is asked twice, the evaluations go on from the checkpoint's steps; resumed
    once more, from the second part, the same again."""
    common = ["--env", ENV, "--oracle", "scripted", "--seed", "3", "--eval-episodes", "2", "--num-threads", "1",
              "--verbose", "0", "-f", str(tmp_path / "logs"), "--eval-freq", "1000", "--periodic-eval-episodes", "1",
              "--checkpoint-freq", "1000", "--hyperparams", "n_envs:2"]
    first = _cli(*common, "-n", "2000", "--summary-json", str(tmp_path / "first.json"), cwd=tmp_path)
    assert first.returncode == 0, first.stderr[-3000:]
    summary1 = json.loads((tmp_path / "first.json").read_text())
    run1 = Path(summary1["log_path"])
    checkpoint = json.loads((run1 / "checkpoint.json").read_text())
    assert checkpoint["timesteps"] == summary1["total_timesteps"]  # written at the end of training too
    assert 0 < checkpoint["train_seconds"] <= summary1["train_seconds"]
    assert [path.name for path in (run1 / "checkpoints").iterdir()] == [str(checkpoint["timesteps"])]  # the last only

    second = _cli(*common, "-n", "4000", "--resume", str(run1), "--summary-json", str(tmp_path / "second.json"),
                  cwd=tmp_path)
    assert second.returncode == 0, second.stderr[-3000:]
    summary2 = json.loads((tmp_path / "second.json").read_text())
    run2 = Path(summary2["log_path"])
    part_seed = resume_seed(3, checkpoint["timesteps"])  # the part's layouts are not the ones the run began with
    assert run2 != run1 and summary2["resumed_from"] == {"run_folder": str(run1), "timesteps": checkpoint["timesteps"],
                                                         "seed": part_seed}
    assert summary2["seed"] == 3  # the run's seed, which the evaluation seeds come from
    assert summary2["train_seconds_all_parts"] == pytest.approx(checkpoint["train_seconds"] + summary2["train_seconds"],
                                                                abs=0.01)
    assert json.loads((run2 / "checkpoint.json").read_text())["train_seconds"] > checkpoint["train_seconds"]
    # a rollout goes on until an episode ends: at most one DoorKey-5x5 episode (250 steps) of each of the 2 envs more
    assert 4000 <= summary2["total_timesteps"] <= 4000 + 2 * 250
    assert summary2["preference_db"] == summary1["preference_db"]
    assert summary2["queries_used"] >= summary1["queries_used"]
    assert summary2["queries_asked"] == summary2["queries_distinct"] == summary2["queries_used"]  # none asked twice
    assert json.loads((run2 / "resumed.json").read_text()) == {"run_folder": str(run1), "timesteps": checkpoint["timesteps"],
                                                               "seed": part_seed}
    timesteps = np.load(run2 / "evaluations.npz")["timesteps"]
    assert timesteps[0] > checkpoint["timesteps"]
    # resumed again, from the second part's folder (which holds no database of its own): the answers still go to the
    # first part's database, and still no question is asked twice
    assert not (run2 / "preferences.sqlite").exists()
    third = _cli(*common, "-n", "6000", "--resume", str(run2), "--summary-json", str(tmp_path / "third.json"),
                 cwd=tmp_path)
    assert third.returncode == 0, third.stderr[-3000:]
    summary3 = json.loads((tmp_path / "third.json").read_text())
    assert summary3["resumed_from"]["run_folder"] == str(run2)
    assert summary3["preference_db"] == summary1["preference_db"] and not (run2 / "preferences.sqlite").exists()
    assert summary3["queries_used"] >= summary2["queries_used"]
    assert summary3["queries_asked"] == summary3["queries_distinct"] == summary3["queries_used"]

    missing = _cli(*common, "-n", "4000", "--resume", str(tmp_path), cwd=tmp_path)
    assert missing.returncode == 2 and "has no checkpoint.json" in missing.stderr and "--checkpoint-freq" in missing.stderr


def test_a_checkpoint_the_disk_cannot_hold_is_skipped_and_training_goes_on(trained, tmp_path, monkeypatch):
    """Disk full while a checkpoint is written: its partial files go, the pointer keeps the last complete checkpoint,
    a warning says so and training is not stopped; with less free space than the last checkpoint took, the next one is
    not even begun. Nothing already saved is lost."""
    import shutil

    from sb3_hhp.zoo.checkpoints import checkpoint_callback_class, read_checkpoint

    model, _ = trained
    callback = checkpoint_callback_class()(save_freq=100, save_path=str(tmp_path))
    callback.init_callback(model)
    callback.save()  # a complete checkpoint at the model's step count
    first = read_checkpoint(str(tmp_path))
    assert first["timesteps"] == model.num_timesteps and os.path.isfile(first["replay"])
    size = sum(path.stat().st_size for path in (tmp_path / "checkpoints").rglob("*") if path.is_file())

    def disk_full(path, *args, **kwargs):
        Path(path).write_bytes(b"partial")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(model, "save_replay_buffer", disk_full)
    monkeypatch.setattr(model, "num_timesteps", first["timesteps"] + 100)
    with pytest.warns(UserWarning, match=rf"No checkpoint at {first['timesteps'] + 100} steps .*No space left.*"
                                         rf"last complete checkpoint \({first['timesteps']} steps\)"):
        callback.save()
    assert read_checkpoint(str(tmp_path)) == first  # the pointer and its files as they were
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == [str(first["timesteps"])]
    # less free space than the last checkpoint took: not begun
    monkeypatch.undo()
    free = shutil.disk_usage(tmp_path)._replace(free=size - 1)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: free)
    monkeypatch.setattr(model, "num_timesteps", first["timesteps"] + 200)
    with pytest.warns(UserWarning, match="GB free on its disk, the last checkpoint took"):
        callback.save()
    assert read_checkpoint(str(tmp_path)) == first
    assert not (tmp_path / "checkpoints" / str(first["timesteps"] + 200)).exists()
    assert callback.saved_at == first["timesteps"] + 200  # not tried again at every step until the next one is due
