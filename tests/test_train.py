"""Tests of ``python -m sb3_hhp.train``: the RL Zoo entry point, its YAML handling, errors and summary."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import optuna
import pytest
import yaml

from sb3_hhp import HhP, train
from sb3_hhp.zoo.config import (
    ZOO_KEYS,
    ConfigError,
    check_env_id,
    default_config_path,
    hhp_arguments,
    select_entry,
    validate_hyperparams,
)
from sb3_hhp.zoo.evaluation import eval_seeds

REPO = Path(__file__).resolve().parent.parent
SUMMARY_KEYS = {
    "env", "seed", "total_timesteps", "success_rate", "mean_return", "eval_episodes", "eval_seeds", "queries_used",
    "query_budget", "num_subgoals", "subgoals", "fps", "train_seconds", "preference_db", "log_path", "model_path",
    "config_entry", "deterministic_eval", "break_cycles", "stochastic_breaks_cycles", "num_threads",
}


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run the training CLI; the generous timeout only guards against a hang on a loaded machine."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return subprocess.run(
        [sys.executable, "-m", "sb3_hhp.train", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


def test_eval_seeds_never_reuse_training_seeds() -> None:
    seed = 7
    seeds = eval_seeds(seed, 5)
    assert seeds == [10_007, 10_008, 10_009, 10_010, 10_011]
    training_seeds = {seed}  # RL Zoo seeds env i with seed + i, and HhP runs one env
    assert training_seeds.isdisjoint(seeds)
    assert len(set(eval_seeds(0, 1_000))) == 1_000  # one fresh seed per episode
    assert eval_seeds(3, 0) == []
    with pytest.raises(ValueError, match="offset"):
        eval_seeds(3, 2, offset=0)
    with pytest.raises(ValueError, match="n_episodes"):
        eval_seeds(3, -1)


@pytest.mark.slow
def test_short_run_writes_summary_and_rl_zoo_outputs(tmp_path: Path) -> None:
    summary_path = tmp_path / "summary.json"
    result = _cli(
        "--env", "MiniGrid-Empty-5x5-v0", "--oracle", "scripted", "-n", "3000", "--seed", "5", "--eval-episodes", "5",
        "--eval-freq", "1500", "--save-freq", "1500", "--periodic-eval-episodes", "2", "--num-threads", "1",
        "--verbose", "0", "-f", str(tmp_path / "logs"), "--summary-json", str(summary_path),
        cwd=tmp_path,  # the default YAML is found from the package, not the working directory
    )
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads(summary_path.read_text())
    assert SUMMARY_KEYS <= set(summary)
    assert summary["env"] == "MiniGrid-Empty-5x5-v0" and summary["seed"] == 5
    assert summary["config_entry"] == "MiniGrid-Empty-5x5-v0" and summary["deterministic_eval"] is True
    assert summary["break_cycles"] is True  # the deterministic policy as it acted (the default)
    assert summary["stochastic_breaks_cycles"] is True  # and the stochastic one
    # total_timesteps counts primitive steps: at least -n, past it by less than one episode (HhP learns per
    # episode; MiniGrid-Empty-5x5 ends after 100 steps)
    assert 3000 <= summary["total_timesteps"] <= 3000 + 100
    assert summary["eval_episodes"] == 5 and len(summary["eval_seeds"]) == 5
    assert min(summary["eval_seeds"]) >= 5 + 10_000 and 5 not in summary["eval_seeds"]
    assert summary["query_budget"] == 20 and 0 < summary["queries_used"] <= 20
    assert summary["num_subgoals"] == len(summary["subgoals"]) >= 1
    assert all(isinstance(name, str) and name for name in summary["subgoals"])
    assert summary["fps"] == pytest.approx(summary["total_timesteps"] / summary["train_seconds"], rel=0.01)
    assert "success_rate" in result.stdout and "queries_used" in result.stdout

    run_dir = Path(summary["log_path"])
    assert run_dir.parent == tmp_path / "logs" / "hhp"
    assert Path(summary["model_path"]).is_file()
    assert Path(summary["preference_db"]) == run_dir / "preferences.sqlite" and Path(summary["preference_db"]).is_file()
    config = yaml.unsafe_load((run_dir / "MiniGrid-Empty-5x5-v0" / "config.yml").read_text())
    assert dict(config)["oracle"] == "scripted"
    assert dict(config)["n_timesteps"] == 3000  # -n, not the file's 20000
    # RL Zoo's EvalCallback and CheckpointCallback ran every 1500 primitive steps (callbacks are called once per
    # primitive step of the env)
    timesteps = np.load(run_dir / "evaluations.npz")["timesteps"]
    assert len(timesteps) == 2 and 1500 <= timesteps[0] <= 1600 and 3000 <= timesteps[1] <= 3100
    assert len(list(run_dir.glob("rl_model_*_steps.zip"))) == 2

    # the saved model is the one evaluated: SB3's evaluate_policy, on one fresh env per evaluation seed built here,
    # gives the summary's figures (MiniGrid reports no is_success: an episode succeeds when its return is > 0)
    import gymnasium as gym
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    from sb3_hhp.goals.minigrid import MiniGridEgocentricObs

    model = HhP.load(summary["model_path"])
    assert len(model.subgoals) == summary["num_subgoals"]
    assert model.query_selector.used == summary["queries_used"]
    assert dict(config)["env_wrapper"] == "sb3_hhp.goals.minigrid.MiniGridEgocentricObs"  # as the envs built here
    returns, lengths = [], []
    for seed in summary["eval_seeds"]:
        env = make_vec_env(lambda: MiniGridEgocentricObs(gym.make("MiniGrid-Empty-5x5-v0")), n_envs=1)
        env.seed(seed)
        episode_returns, episode_lengths = evaluate_policy(model, env, n_eval_episodes=1, deterministic=True,
                                                           return_episode_rewards=True, warn=False)
        returns += episode_returns
        lengths += episode_lengths
    assert summary["mean_return"] == pytest.approx(np.mean(returns))
    assert summary["std_return"] == pytest.approx(np.std(returns))
    assert summary["mean_episode_length"] == pytest.approx(np.mean(lengths))
    assert summary["success_rate"] == pytest.approx(np.mean(np.asarray(returns) > 0))


@pytest.mark.slow
def test_domain_entry_serves_ids_without_their_own(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    summary = train.run(
        ["--env", "MiniGrid-Empty-6x6-v0", "-n", "300", "--seed", "1", "--eval-episodes", "2", "--eval-freq", "-1",
         "--num-threads", "1", "--verbose", "0", "-f", str(tmp_path), "--hyperparams", "predictor_kwargs:dict(n_masks=10)"]
    )
    assert "MiniGrid-Empty-6x6-v0" not in yaml.safe_load((REPO / "sb3_hhp" / "hyperparams" / "hhp.yml").read_text())
    assert summary is not None and summary["env"] == "MiniGrid-Empty-6x6-v0"
    assert summary["config_entry"] == "minigrid"
    assert summary["query_budget"] == 100  # the minigrid entry's value
    assert "Using the 'minigrid' entry for MiniGrid-Empty-6x6-v0" in capsys.readouterr().out


@pytest.mark.slow
def test_atari_ids_train_from_the_atari_entry_on_frames(tmp_path: Path) -> None:
    """An Atari id takes the atari entry (AtariWrapper frames, CnnPolicy, the image goal space), through RL Zoo,
    whose image envs come wrapped in VecTransposeImage."""
    summary = train.run(
        ["--env", "ALE/Pong-v5", "--oracle", "none", "-n", "200", "--seed", "3", "--eval-episodes", "1", "--eval-freq",
         "-1", "--num-threads", "1", "--verbose", "0", "-f", str(tmp_path),
         "--hyperparams", "predictor_kwargs:dict(n_masks=4)", "buffer_size:2000", "max_subgoal_steps:50", "learning_starts:50"]
    )
    assert summary is not None and summary["config_entry"] == "atari"
    assert summary["total_timesteps"] >= 200 and summary["num_subgoals"] >= 1
    assert all(name.startswith("cell ") or name == "task solved" for name in summary["subgoals"])
    assert summary["mean_return"] < 0  # Pong: an untrained agent loses its points


@pytest.mark.slow
def test_fetch_ids_train_from_the_fetch_entry_with_the_scripted_oracle(tmp_path: Path) -> None:
    """A Fetch id takes the fetch entry (the flat observation, the Fetch goal space, the goal-conditioned learner);
    the scripted oracle answers from the positions; success is the env's own ``is_success``."""
    pytest.importorskip("gymnasium_robotics", reason='needs the [fetch] extra: pip install "sb3_hhp[fetch]"')
    summary = train.run(
        ["--env", "FetchReach-v4", "--oracle", "scripted", "-n", "400", "--seed", "4", "--eval-episodes", "2",
         "--eval-freq", "-1", "--num-threads", "1", "--verbose", "0", "-f", str(tmp_path), "--hyperparams",
         "predictor_kwargs:dict(n_masks=10)", "subpolicy_kwargs:dict(learning_starts=64, batch_size=32)"]
    )
    assert summary is not None and summary["config_entry"] == "fetch"
    assert summary["total_timesteps"] >= 300 and summary["num_subgoals"] >= 2
    assert summary["queries_used"] > 0  # answered by FetchScriptedOracle, which refuses questions without positions
    assert all(name == "task solved" or (name.startswith("at (") and name.endswith(") cm")) for name in summary["subgoals"])
    assert summary["mean_episode_length"] == 50  # FetchReach's time limit: no episode is cut short or run on


@pytest.mark.slow
def test_label_server_runs_beside_training(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    summary = train.run(
        ["--env", "MiniGrid-Empty-5x5-v0", "--label-server", "--label-port", "0", "-n", "200", "--seed", "2",
         "--eval-episodes", "1", "--eval-freq", "-1", "--num-threads", "1", "--verbose", "0", "-f", str(tmp_path)]
    )
    out = capsys.readouterr().out
    assert summary is not None and summary["oracle"] == "web"  # --label-server implies --oracle web
    assert "Labeling page: http://127.0.0.1:" in out
    assert Path(summary["preference_db"]).is_file() and Path(summary["preference_db"]).parent == Path(summary["log_path"])


@pytest.mark.slow
@pytest.mark.parametrize("args, before, threads",
                         [([], 2, 1), (["--num-threads", "2"], 1, 2), (["--num-threads", "-1"], 2, 2)])
def test_torch_threads_are_one_unless_the_command_line_says(tmp_path: Path, args: list, before: int,
                                                            threads: int) -> None:
    """One torch thread by default (torch's own default stalls small networks beside any busy process); --num-threads
    N gives N; -1 leaves torch's setting as it was."""
    import torch

    outside = torch.get_num_threads()
    torch.set_num_threads(before)  # not what the run must leave, except for -1
    try:
        summary = train.run(["--env", "MiniGrid-Empty-5x5-v0", "-n", "200", "--seed", "0", "--eval-episodes", "0",
                             "--eval-freq", "-1", "--verbose", "0", "-f", str(tmp_path), *args])
        assert torch.get_num_threads() == threads
        assert summary is not None and summary["num_threads"] == threads
    finally:
        torch.set_num_threads(outside)


def test_num_threads_must_be_positive_or_minus_one(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert train.main(["--env", "MiniGrid-Empty-5x5-v0", "--num-threads", "0", "-f", str(tmp_path)]) == 2
    assert "--num-threads must be >= 1, or -1 for torch's own default, got 0" in capsys.readouterr().err


def test_select_entry_order() -> None:
    table = {"minigrid": {}, "default": {}, "MiniGrid-DoorKey-5x5-v0": {}}
    assert select_entry(table, "MiniGrid-DoorKey-5x5-v0") == "MiniGrid-DoorKey-5x5-v0"
    assert select_entry(table, "MiniGrid-KeyCorridorS3R1-v0") == "minigrid"
    assert select_entry(table, "CartPole-v1") == "default"
    with pytest.raises(ConfigError, match="No hyperparameters for CartPole-v1"):
        select_entry({"minigrid": {}}, "CartPole-v1")


def test_default_config_is_found_from_the_package() -> None:
    path = default_config_path()
    assert path.is_file() and path.name == "hhp.yml"
    table = yaml.safe_load(path.read_text())
    entry = table["minigrid"]
    assert entry["env_wrapper"] == "sb3_hhp.goals.minigrid.MiniGridEgocentricObs"
    assert entry["n_envs"] == 8 and entry["policy"] == "MlpPolicy" and entry["query_budget"] == 100
    for key, hyperparams in table.items():  # every shipped entry passes the key check
        validate_hyperparams(dict(hyperparams), key)


def test_unknown_yaml_key_is_refused_before_training(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    conf = tmp_path / "bad.yml"
    conf.write_text(yaml.safe_dump({"minigrid": {"policy": "MlpPolicy", "n_timesteps": 100, "query_budgt": 3}}))
    status = train.main(["--env", "MiniGrid-Empty-5x5-v0", "--conf-file", str(conf), "-f", str(tmp_path / "logs")])
    error = capsys.readouterr().err.strip()
    assert status == 2
    assert len(error.splitlines()) == 1
    assert "'query_budgt'" in error and "did you mean 'query_budget'" in error
    assert "query_kwargs" in error and "n_timesteps" in error  # the valid keys are listed
    assert not list((tmp_path / "logs").rglob("*.zip"))  # nothing was trained


@pytest.mark.parametrize(
    "hyperparams, message",
    [
        ({"n_envs": 0}, "n_envs must be an integer >= 1"),
        ({"normalize": True}, "env_wrapper"),
        ({"frame_stack": 4}, "env_wrapper"),
        ({"seed": 3}, "--seed"),
        ({"oracle": "wizard"}, "unknown oracle 'wizard'"),
    ],
)
def test_validate_hyperparams_refuses(hyperparams: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        validate_hyperparams({"policy": "MlpPolicy", **hyperparams}, "test")


def test_unknown_oracle_gives_one_line_and_nonzero_exit(tmp_path: Path) -> None:
    result = _cli("--env", "MiniGrid-Empty-5x5-v0", "--oracle", "wizard", "-f", str(tmp_path), cwd=tmp_path)
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Unknown oracle 'wizard'" in lines[0] and "scripted" in lines[0]


def test_unknown_env_gives_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert train.main(["--env", "MiniGrid-Emtpy-5x5-v0", "-f", str(tmp_path)]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1
    assert "Unknown env id 'MiniGrid-Emtpy-5x5-v0'" in error and "MiniGrid-Empty-5x5-v0" in error


def test_constructor_refusal_is_a_config_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    status = train.main(["--env", "MiniGrid-Empty-5x5-v0", "--hyperparams", "beta:2.0", "-n", "10", "--eval-freq", "-1",
                         "-f", str(tmp_path), "--verbose", "0"])
    assert status == 2
    error = capsys.readouterr().err
    assert "--hyperparams: beta must be in [0, 1], got 2.0" in error and "hhp.yml" not in error
    assert not (tmp_path / "hhp").exists()  # refused before the run's folder was made
    assert train.main(["--env", "MiniGrid-Empty-5x5-v0", "--hyperparams", "wizard:3", "-f", str(tmp_path)]) == 2
    assert "--hyperparams: unknown hyperparameter 'wizard'" in capsys.readouterr().err


def test_help_lists_each_option_once(capsys: pytest.CaptureFixture) -> None:
    assert train.main(["--help"]) == 0
    text = capsys.readouterr().out
    assert text.count("  --eval-episodes EVAL_EPISODES") == 1 and text.count("[--eval-episodes EVAL_EPISODES]") == 1
    assert text.count("  --num-threads N ") == 1 and "NUM_THREADS" not in text  # this entry point's, not RL Zoo's
    assert "--eval-freq" in text  # RL Zoo's options are listed too


def test_hhp_is_registered_with_rl_zoo() -> None:
    from rl_zoo3.hyperparams_opt import HYPERPARAMS_CONVERTER, HYPERPARAMS_SAMPLER
    from rl_zoo3.utils import ALGOS

    from sb3_hhp import HhP

    train.register()
    assert ALGOS["hhp"] is HhP
    assert HYPERPARAMS_SAMPLER["hhp"] is train.sample_hhp_params
    fixed = optuna.trial.FixedTrial(
        {"query_budget": 80, "query_mode": "fixed", "beta": 0.6, "alpha": 0.3, "learning_rate": 1e-3, "t_qry": 0.2,
         "center_bonus": "max", "meta_input": "auto"}
    )
    sampled = HYPERPARAMS_SAMPLER["hhp"](fixed, 0, 1, {})
    assert sampled == {"query_budget": 80, "query_kwargs": {"mode": "fixed", "threshold": 0.2}, "beta": 0.6, "alpha": 0.3,
                       "learning_rate": 1e-3, "meta_kwargs": {"center_bonus": "max", "input": "auto"}}
    assert set(sampled) <= set(hhp_arguments())
    assert HYPERPARAMS_CONVERTER["hhp"](fixed.params) == sampled  # a stored trial's values, as HhP's arguments
    # the adaptive mode sets its own threshold: no t_qry is sampled
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(10):
        params = train.sample_hhp_params(study.ask(), 0, 1, {})
        assert ("threshold" in params["query_kwargs"]) == (params["query_kwargs"]["mode"] == "fixed")
        HhP("MlpPolicy", None, _init_setup_model=False, **params)  # every trial's values are HhP's arguments, valid


#: what the one minigrid entry's learners read on each of the paper's tasks: the view, the overview's blocks, the
#: indicators (object types and door states its grids hold)
DERIVED_INPUTS = {
    "MiniGrid-DoorKey-16x16-v0": (15, (7, 7, 3), 4 + 2),  # walls, doors, keys, goal squares; closed, locked
    "MiniGrid-KeyCorridorS4R3-v0": (None, None, 4 + 2),  # the 15 x 15 inner canvas; walls, doors, keys, balls
    # boxes too, and the keys they hold; whether a cell has the carried object's colour (keys of two colours); the
    # mission's ball marked (green balls beside it)
    "MiniGrid-ObstructedMaze-1Q-v1": (15, (7, 7, 3), 5 + 1 + 2 + 1),
    "MiniGrid-MultiRoom-N12-S10-v0": (15, (11, 11, 3), 3 + 1),  # walls, doors, goal squares; closed only
}


@pytest.mark.parametrize("env_id", sorted(DERIVED_INPUTS))
def test_the_papers_four_minigrid_tasks_take_the_one_minigrid_entry(env_id: str) -> None:
    import gymnasium as gym

    assert check_env_id(env_id) == env_id  # MultiRoom-N12-S10 is registered by sb3_hhp
    table = yaml.safe_load(default_config_path().read_text())
    # each task's entry is the minigrid entry itself: nothing chosen per task
    assert select_entry(table, env_id) == env_id and table[env_id] == table["minigrid"]
    assert table["minigrid"]["n_timesteps"] == 2e6
    hyperparams = {key: value for key, value in table[env_id].items() if key not in ZOO_KEYS}
    model = HhP("MlpPolicy", gym.make(env_id), **{**hyperparams, "oracle": None, "predictor_kwargs": dict(n_masks=2)})
    view, overview, indicators = DERIVED_INPUTS[env_id]
    learners = model.subpolicies
    assert learners.view == (view if view is not None else "inner")
    assert (learners._overview.shape if learners._overview is not None else None) == overview
    assert learners._one_hot.n_indicators == indicators
    side = model.observation_space.shape[0] - 2 if view is None else view
    cells = side * side + (overview[0] * overview[1] if overview else 0)
    assert learners._template.q_net[0].in_features == cells * indicators
    assert model.goal_space.keep_doors_open and model.success_bonus == "best"
    # two keys of different colours: colours read as they relate (a key and the door it opens)
    assert model.goal_space.use_color == model.goal_space.relative_color == (env_id == "MiniGrid-ObstructedMaze-1Q-v1")
    assert (learners.input.codes is not None) == model.goal_space.relative_color  # the learners read the relation
    assert model.discovery.percentile_of == "new"
    # the learners' reward and horizon are the class's: curiosity in their reward, unclipped, discount 0.9, 50-step tries
    assert model.alpha == 0.5 and learners.target_range is None
    assert model.max_subgoal_steps == 50 and learners.gamma == 0.9
    if env_id == "MiniGrid-MultiRoom-N12-S10-v0":
        base = model.env.envs[0].unwrapped
        assert (base.minNumRooms, base.maxNumRooms, base.maxRoomSize, base.width) == (12, 12, 10, 25)
