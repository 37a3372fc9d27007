"""Tests of the benchmark runner (python -m benchmarks.run) and its report (benchmarks/report.py), without training."""

import contextlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from benchmarks import report
from benchmarks.run import (
    COLUMNS,
    Experiment,
    Sweep,
    SweepError,
    _curve_from_evaluations,
    _run_hhp,
    attempt_evaluations,
    code_version,
    earlier_parts_seconds,
    latest_checkpoint,
    load_sweep,
    main,
    add_result,
    pending_experiments,
    read_results,
    run_experiment,
    run_sweep,
    run_training,
    select_experiments,
)

EXPERIMENTS = Path(__file__).resolve().parent.parent / "benchmarks" / "experiments"


def write(tmp_path: Path, text: str, name: str = "sweep.yml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def fake_row(experiment: Experiment, sweep: Sweep, out: Path) -> dict[str, Any]:
    """Stands in for run_experiment: a row that records the seed as the success rate."""
    return {
        "env": experiment.env, "variant": experiment.variant, "seed": experiment.seed, "steps": experiment.steps,
        "success_det": experiment.seed / 10, "success_stoch": 0.5, "wall_seconds": 1.0,
    }


def failing_row(experiment: Experiment, sweep: Sweep, out: Path) -> dict[str, Any]:
    raise RuntimeError("sb3_hhp.train exited with status 1")


def test_the_shipped_sweeps_parse():
    doorkey = load_sweep(EXPERIMENTS / "doorkey8x8.yml")
    assert doorkey.name == "doorkey8x8"
    assert {(e.variant, e.seed) for e in doorkey.experiments} == {
        (variant, seed) for variant in ("hhp", "dqn", "ppo", "ppo_rnd") for seed in (0, 1, 2)
    }
    assert {e.steps for e in doorkey.experiments} == {300_000}
    assert doorkey.eval_episodes == 100
    ablations = load_sweep(EXPERIMENTS / "minigrid_ablations.yml")
    assert ablations.name == "minigrid_tasks"  # its rows join the four tasks' table
    assert {e.env for e in ablations.experiments} == {"MiniGrid-KeyCorridorS4R3-v0"}  # the task HhP learns
    assert {e.variant for e in ablations.experiments} == {
        "hhp_rho0.1", "hhp_rho0.2", "hhp_no_preferences", "hhp_no_curiosity", "hhp_random_discovery"}
    assert all(ablations.is_hhp(e.variant) for e in ablations.experiments) and not ablations.is_hhp("ppo")
    assert ablations.hhp_options("hhp_rho0.2") == ("--oracle", "noisy-scripted", "--hyperparams", "query_kwargs:dict(oracle_kwargs=dict(rho=0.2))")
    smoke = load_sweep(EXPERIMENTS / "smoke.yml")
    assert [e.variant for e in smoke.experiments] == ["hhp", "dqn", "ppo", "ppo_rnd"]
    assert {e.steps for e in smoke.experiments} == {2000}
    count_doors = load_sweep(EXPERIMENTS / "minigrid_count_doors.yml")
    assert count_doors.hhp_options("hhp_count_doors") == (
        "--hyperparams", "goal_space:'minigrid_count_doors'", "meta_kwargs:dict(success_bonus='best')")
    fetch = load_sweep(EXPERIMENTS / "fetch_reach.yml")  # HhP and DDPG + HER on 3 seeds, TQC + HER and DDPG on 1
    assert [(e.variant, e.seed) for e in fetch.experiments] == [
        ("hhp", 0), ("hhp", 1), ("hhp", 2), ("ddpg_her", 0), ("ddpg_her", 1), ("ddpg_her", 2), ("tqc_her", 0),
        ("ddpg", 0)]
    for path in sorted(EXPERIMENTS.glob("*.yml")):  # every sweep shipped parses
        assert load_sweep(path, check_envs=False).experiments, path.name


def test_grid_defaults_and_per_env_budgets(tmp_path):
    sweep = load_sweep(write(tmp_path, """
        envs: [MiniGrid-Empty-5x5-v0, MiniGrid-DoorKey-5x5-v0]
        variants: [ppo, hhp]
        seeds: [0, 1]
        steps: {MiniGrid-Empty-5x5-v0: 2000, MiniGrid-DoorKey-5x5-v0: !!float 4e3}
    """), check_envs=False)
    assert sweep.name == "sweep"
    assert len(sweep.experiments) == 8
    assert sweep.experiments[0] == Experiment("MiniGrid-Empty-5x5-v0", "ppo", 0, 2000)
    assert sweep.experiments[-1] == Experiment("MiniGrid-DoorKey-5x5-v0", "hhp", 1, 4000)
    assert sweep.eval_freq == {"MiniGrid-Empty-5x5-v0": 100, "MiniGrid-DoorKey-5x5-v0": 200}
    assert sweep.baselines_conf == "sb3_hhp/hyperparams/baselines.yml"


GRID = "envs: [MiniGrid-Empty-5x5-v0]\nvariants: [ppo]\nseeds: [0]\n"


@pytest.mark.parametrize(
    "text, message",
    [
        ("envs: [MiniGrid-Empty-5x5-v0\nvariants: [ppo]", "is not valid YAML"),
        ("- a\n- b", "must map keys"),
        (GRID.replace("variants", "variant") + "steps: 10", "unknown key 'variant' \\(did you mean 'variants'\\?\\)"),
        (GRID.replace("[ppo]", "[ppo_rdn]") + "steps: 10", "unknown variant 'ppo_rdn' \\(did you mean 'ppo_rnd'\\?\\)"),
        (GRID, "'steps' is required"),
        (GRID + "steps: 3e5", "steps must be an integer >= 1 .*'3e5'"),
        (GRID.replace("[0]", "[-1]") + "steps: 10", "seeds must be an integer >= 0"),
        (GRID + "steps: 10\nhhp_conf: nowhere.yml", "no such file 'nowhere.yml'"),
        (
            GRID.replace("v0", "v1") + "steps: 10",
            "Unknown env id 'MiniGrid-Empty-5x5-v1' \\(did you mean 'MiniGrid-Empty-5x5-v0'",
        ),
        (GRID.replace("MiniGrid-Empty-5x5-v0", "CartPole-v1") + "steps: 10", "No hyperparameters for CartPole-v1"),
        (GRID.replace("[ppo]", "[hhp_rho0.3]") + "steps: 10\nhhp_variants: {hhp_rho0.2: []}",
         "unknown variant 'hhp_rho0.3' \\(did you mean 'hhp_rho0.2'\\?\\)"),
        (GRID + "steps: 10\nhhp_variants: {noisy: []}", "name 'noisy' must start with hhp_"),
        (GRID + "steps: 10\nhhp_variants: {hhp__x: []}", "single '_'"),
        (GRID + "steps: 10\nhhp_variants: {hhp_x: --oracle}", "hhp_variants\\[hhp_x\\] must be a list"),
        (GRID + "steps: 10\nvariant_seeds: {dqn: [0]}", "variant_seeds must map some of the sweep's variants \\(ppo\\)"),
        (GRID + "steps: 10\nvariant_seeds: {ppo: [-2]}", "variant_seeds\\[ppo\\] must be an integer >= 0"),
    ],
)
def test_sweep_errors_say_what_to_fix(tmp_path, text, message):
    with pytest.raises(SweepError, match=message):
        load_sweep(write(tmp_path, text))


@pytest.mark.parametrize(
    "variant, env, entry, message",
    [
        ("ddpg_her", "MiniGrid-Empty-5x5-v0", "{replay_buffer_class: HerReplayBuffer}",
         "ddpg_her relabels goals in hindsight \\(HerReplayBuffer\\) and needs an env that observes a dict of "
         "observation, achieved_goal, desired_goal .*; MiniGrid-Empty-5x5-v0 observes Dict"),
        ("ddpg", "FetchReach-v4", "{replay_buffer_class: HerBuffer}",
         "\\[ddpg\\]\\[default\\]: unknown replay_buffer_class 'HerBuffer'; accepted: ReplayBuffer, DictReplayBuffer, "
         "HerReplayBuffer"),
        ("tqc_her", "FetchReach-v4", "{policy: MultiInputPolicy}",
         "tqc_her relabels in hindsight: set replay_buffer_class: HerReplayBuffer"),
        ("ddpg", "FetchReach-v4", "{replay_buffer_class: HerReplayBuffer}",
         "ddpg trains without hindsight; HerReplayBuffer is for ddpg_her, tqc_her"),
        ("ddpg", "FetchReach-v4", "{noise_type: gaussian, noise_std: 0.1}",
         "noise_type must be one of normal, ornstein-uhlenbeck"),
        ("ddpg_her", "FetchReach-v4", "{replay_buffer_class: HerReplayBuffer, replay_buffer_kwargs: 'dict(n_sampled_goal=4)'}",
         "replay_buffer_kwargs must be a mapping"),
    ],
)
def test_baseline_entries_say_what_to_fix(tmp_path, variant, env, entry, message):
    """A hindsight variant on an env that observes no dict goal names the variant and the env; a replay buffer or an
    action noise the runner does not know is named with those it accepts; hindsight goes with the _her variants only."""
    write(tmp_path, f"{variant}:\n  default: {entry}\n", "baselines.yml")
    with pytest.raises(SweepError, match=message):
        load_sweep(write(tmp_path, f"envs: [{env}]\nvariants: [{variant}]\nseeds: [0]\nsteps: 10\n"
                                   f"baselines_conf: {tmp_path / 'baselines.yml'}\n"))


@pytest.mark.parametrize("variant", ["ddpg", "ddpg_her", "tqc_her"])
@pytest.mark.parametrize("env", ["FetchReach-v4", "FetchPush-v4", "FetchPickAndPlace-v4", "FetchSlide-v4"])
def test_the_fetch_baselines_settings_are_their_algorithms_arguments(variant, env):
    """Every key of the shipped Fetch entries is the runner's or an argument of the variant's algorithm, and the
    replay buffer is the one the variant's name says."""
    import inspect

    from rl_zoo3.utils import get_class_by_name

    from benchmarks.run import BASELINE_RUNNER_KEYS, BASELINES, baseline_settings

    settings = baseline_settings(str(EXPERIMENTS.parents[1] / "sb3_hhp" / "hyperparams" / "baselines.yml"), variant, env)
    arguments = inspect.signature(get_class_by_name(BASELINES[variant].algorithm)).parameters
    assert set(settings) - set(BASELINE_RUNNER_KEYS) <= set(arguments), set(settings) - set(arguments)
    assert settings["policy"] == "MultiInputPolicy" and not BASELINES[variant].hhp_observation
    assert (settings["replay_buffer_class"] == "HerReplayBuffer") == variant.endswith("_her")


def test_command_line_reports_errors_in_one_line(tmp_path, capsys):
    assert main([str(write(tmp_path, "envs: [x]\nvariants: [sac]\nseeds: [0]\nsteps: 10"))]) == 2
    assert "error:" in capsys.readouterr().err
    assert main([str(tmp_path / "missing.yml")]) == 2


def test_sweep_is_resumable_and_writes_one_tidy_csv(tmp_path):
    sweep = load_sweep(write(tmp_path, """
        name: tiny
        envs: [MiniGrid-Empty-5x5-v0]
        variants: [ppo_rnd, hhp]
        seeds: [0, 1]
        steps: 100
    """), check_envs=False)
    out = tmp_path / "out"
    out.mkdir()
    done = fake_row(Experiment("MiniGrid-Empty-5x5-v0", "hhp", 1, 100), sweep, out)
    pd.DataFrame([done]).reindex(columns=list(COLUMNS)).to_csv(out / "results.csv", index=False)
    assert len(pending_experiments(sweep, read_results(out / "results.csv"))) == 3
    csv_path, failures = run_sweep(sweep, out, jobs=2, runner=fake_row)
    assert failures == []
    results = pd.read_csv(csv_path)
    assert list(results.columns) == list(COLUMNS)
    # sorted by env, variant (hhp before the baselines) and seed, one row each
    assert list(zip(results["variant"], results["seed"])) == [("hhp", 0), ("hhp", 1), ("ppo_rnd", 0), ("ppo_rnd", 1)]
    assert results["success_det"].tolist() == [0.0, 0.1, 0.0, 0.1]
    assert pending_experiments(sweep, results) == []
    # a finished sweep runs nothing: a runner that fails would be noticed
    assert run_sweep(sweep, out, jobs=1, runner=failing_row)[1] == []
    # a bigger budget is a new experiment; a failed one leaves no row, so the next run retries it
    bigger = load_sweep(write(tmp_path, GRID.replace("ppo", "hhp") + "steps: 200"), check_envs=False)
    _, failures = run_sweep(bigger, out, jobs=1, runner=failing_row)
    assert len(failures) == 1 and "exited with status 1" in failures[0]
    assert len(pd.read_csv(csv_path)) == 4


def test_hhp_variants_train_hhp_with_their_own_options(tmp_path, monkeypatch):
    sweep = load_sweep(write(tmp_path, """
        envs: [MiniGrid-Empty-5x5-v0]
        variants: [ppo, hhp_rho0.2, hhp]
        seeds: [0]
        steps: 100
        hhp_args: [--hyperparams, "n_envs:2"]
        hhp_variants:
          hhp_rho0.2: [--oracle, noisy-scripted, --hyperparams, "query_kwargs:dict(oracle_kwargs=dict(rho=0.2))"]
    """), check_envs=False)
    commands = []
    monkeypatch.setattr("subprocess.run", lambda command, **kwargs: commands.append(command) or FailedRun())
    for variant in ("hhp", "hhp_rho0.2"):
        with open(tmp_path / "run.log", "w") as log_file, pytest.raises(RuntimeError):
            _run_hhp(Experiment("MiniGrid-Empty-5x5-v0", variant, 0, 100), sweep, tmp_path, log_file)
    plain, noisy = commands
    assert plain[-2:] == ["--hyperparams", "n_envs:2"] and "noisy-scripted" not in plain
    assert plain[plain.index("--oracle") + 1] == "scripted" and plain.count("--oracle") == 1
    # the variant's own oracle is the only one the command names, and its options come last
    assert noisy.count("--oracle") == 1 and "scripted" not in noisy
    assert noisy[-6:] == ["--hyperparams", "n_envs:2", "--oracle", "noisy-scripted", "--hyperparams",
                          "query_kwargs:dict(oracle_kwargs=dict(rho=0.2))"]
    # rows: HhP, then the baselines, then the sweep's HhP variants; named "HhP, <rest>" in tables
    out = tmp_path / "out"
    out.mkdir()
    csv_path, failures = run_sweep(sweep, out, jobs=1, runner=fake_row)
    assert failures == [] and pd.read_csv(csv_path)["variant"].tolist() == ["hhp", "ppo", "hhp_rho0.2"]
    assert report.variant_name("hhp_rho0.2") == "HhP, rho0.2"
    assert report.variant_name("hhp_no_curiosity") == "HhP, no curiosity" and report.variant_name("ppo_rnd") == "PPO + RND"


def test_parts_of_a_sweep_run_apart_and_share_one_csv(tmp_path):
    # the four MiniGrid tasks take hours a run: each part is started on its own, into the same folder
    sweep = load_sweep(EXPERIMENTS / "minigrid_tasks.yml", check_envs=False)
    part = select_experiments(sweep, envs=["MiniGrid-DoorKey-16x16-v0"], variants=["hhp"], seeds=[0])
    assert [e.key for e in part.experiments] == [("MiniGrid-DoorKey-16x16-v0", "hhp", 0, 2_000_000)]
    assert len(select_experiments(sweep, variants=["ppo", "ppo_rnd"]).experiments) == 4 * 2 * 3
    with pytest.raises(SweepError, match="no variant dqn; its variants: hhp, ppo, ppo_rnd"):
        select_experiments(sweep, variants=["dqn"])
    with pytest.raises(SweepError, match="no seed 7"):
        select_experiments(sweep, seeds=[0, 7])
    # two runners of different parts, each started before the other wrote: neither loses the other's row
    small = load_sweep(write(tmp_path, GRID.replace("[ppo]", "[hhp, ppo]") + "steps: 100"), check_envs=False)
    out = tmp_path / "out"
    out.mkdir()
    first, second = (select_experiments(small, variants=[variant]) for variant in ("hhp", "ppo"))
    assert pending_experiments(first, read_results(out / "results.csv")) == list(first.experiments)
    assert pending_experiments(second, read_results(out / "results.csv")) == list(second.experiments)
    run_sweep(first, out, jobs=1, runner=fake_row)
    run_sweep(second, out, jobs=1, runner=fake_row)
    assert sorted(pd.read_csv(out / "results.csv")["variant"]) == ["hhp", "ppo"]
    # a row written again for the same experiment replaces the old one
    row = fake_row(small.experiments[0], small, out)
    add_result({**row, "success_det": 0.75}, out / "results.csv")
    results = pd.read_csv(out / "results.csv")
    assert len(results) == 2 and results.loc[results["variant"] == "hhp", "success_det"].tolist() == [0.75]


def test_curve_from_periodic_evaluations(tmp_path):
    npz = tmp_path / "evaluations.npz"
    np.savez(npz, timesteps=np.array([100, 200]), results=np.array([[0.0, 0.5], [0.9, 0.8]]), ep_lengths=np.ones((2, 2)))
    path = _curve_from_evaluations(npz, tmp_path / "curves" / "run.csv")
    curve = pd.read_csv(path)
    assert curve["steps"].tolist() == [100, 200]
    assert curve["success"].tolist() == [0.5, 1.0]  # a positive return is a success when is_success is not reported
    np.testing.assert_allclose(curve["mean_return"], [0.25, 0.85])
    assert _curve_from_evaluations(tmp_path / "absent.npz", tmp_path / "x.csv") is None


def synthetic_results(folder: Path) -> Path:
    rows = []
    for variant, successes, labels in (("ppo", (0.2, 0.4), (None, None)), ("hhp", (0.9, 1.0), (40, 60))):
        for seed, (success, used) in enumerate(zip(successes, labels)):
            curve = f"curves/{variant}_s{seed}.csv"
            (folder / "curves").mkdir(exist_ok=True)
            steps = np.array([0, 500, 1000]) + 10 * seed  # seeds evaluated at slightly different steps
            pd.DataFrame({"steps": steps, "success": [0.0, success / 2, success], "mean_return": 0.0}).to_csv(
                folder / curve, index=False
            )
            rows.append({
                "env": "MiniGrid-DoorKey-8x8-v0", "variant": variant, "seed": seed, "steps": 1000,
                "success_det": success, "success_stoch": success / 2, "labels_used": used, "eval_episodes": 100,
                "wall_seconds": 1200.0 + 600 * seed, "curve": curve,
            })
    path = folder / "results.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


def test_report_table_and_plots(tmp_path):
    csv_path = synthetic_results(tmp_path)
    table, markdown, plots = report.report(csv_path)
    lines = table.splitlines()
    assert "wall time (min)" in lines[0]
    assert lines[2] == "| MiniGrid-DoorKey-8x8-v0 | HhP | 2 | 1,000 | 0.95 ± 0.07 | 0.47 ± 0.04 | 50 ± 14 | 25.0 ± 7.1 |"
    assert lines[3] == "| MiniGrid-DoorKey-8x8-v0 | PPO | 2 | 1,000 | 0.30 ± 0.14 | 0.15 ± 0.07 | – | 25.0 ± 7.1 |"
    assert markdown.read_text().count("|") > 20
    assert [plot.name for plot in plots] == ["curves_MiniGrid-DoorKey-8x8-v0.png"]
    assert plots[0].stat().st_size > 1000
    assert plots[0].name in markdown.read_text()
    assert "plain greedy" not in markdown.read_text()  # no summaries: nothing to say


def test_report_names_hhp_runs_evaluated_plain_greedy(tmp_path):
    """A run evaluated before ``break_cycles`` existed (no key in its summary) or with it off is named under the table,
    so a mean over seeds evaluated both ways is not taken for one policy's."""
    import json

    csv_path = synthetic_results(tmp_path)
    results = pd.read_csv(csv_path)
    (tmp_path / "runs").mkdir()
    summaries = {0: {"env": "x"}, 1: {"break_cycles": True, "stochastic_breaks_cycles": True}}
    results["summary"] = None
    for index, row in results.iterrows():
        path = f"runs/{row.variant}_s{row.seed}.json"
        (tmp_path / path).write_text(json.dumps(summaries[int(row.seed)]))
        results.loc[index, "summary"] = path
    results.to_csv(csv_path, index=False)
    table, markdown, _ = report.report(csv_path)
    text = markdown.read_text()
    assert "evaluated plain greedy only" in text
    assert "MiniGrid-DoorKey-8x8-v0 HhP seed 0" in text
    assert "HhP seed 1" not in text and "PPO seed" not in text  # breaking cycles; a baseline has no such policy
    assert "| HhP | 2 | 1,000 | 0.95 ± 0.07 |" in table  # the runner's figures, as written
    # seed 0's stochastic figure is plain epsilon-greedy, and named so (its summary predates the key)
    assert "stochastic figures are plain epsilon-greedy, evaluated before it did: MiniGrid-DoorKey-8x8-v0 HhP seed 0." in text
    # a run whose deterministic policy broke cycles but whose stochastic one did not is named for the latter only
    (tmp_path / "runs" / "hhp_s1.json").write_text(json.dumps({"break_cycles": True}))
    text = report.report(csv_path)[1].read_text()
    assert "evaluated before it did: MiniGrid-DoorKey-8x8-v0 HhP seed 0; MiniGrid-DoorKey-8x8-v0 HhP seed 1." in text
    (tmp_path / "runs" / "hhp_s1.json").write_text(json.dumps(summaries[1]))

    # evaluate.py's figures for seed 0 on the runner's episodes replace its plain greedy one; those with cycles not
    # broken, on other episodes, or of other runs do not
    model = "logs/{}/hhp/MiniGrid-DoorKey-8x8-v0_1/MiniGrid-DoorKey-8x8-v0.zip"
    hhp0, ppo0 = "MiniGrid-DoorKey-8x8-v0__hhp__s0", "MiniGrid-DoorKey-8x8-v0__ppo__s0"
    (tmp_path / "a_other_episodes.json").write_text(json.dumps({"env": "x", "episodes": 20, "runs": [
        {"seed": 0, "model": model.format(hhp0), "load_options": {}, "deterministic": 0.10}]}))
    (tmp_path / "b_cycles.json").write_text(json.dumps({"env": "x", "episodes": 100, "runs": [
        {"seed": 0, "model": model.format(hhp0), "load_options": {"break_cycles": False}, "deterministic": 0.90},
        {"seed": 0, "model": model.format(hhp0), "load_options": {}, "break_cycles": False, "deterministic": 0.30},
        {"seed": 0, "model": model.format(ppo0), "load_options": {}, "deterministic": 0.70}]}))
    (tmp_path / "c_variants.json").write_text(json.dumps({"env": "x", "episodes": 100, "variants": {"hhp": [
        {"seed": 0, "model": model.format(hhp0), "load_options": {}, "deterministic": 0.96}]}}))  # rows by variant
    table, markdown, _ = report.report(csv_path)
    text = markdown.read_text()
    assert "| HhP | 2 | 1,000 | 0.98 ± 0.03 |" in table  # 0.96 and 1.00
    assert "| PPO | 2 | 1,000 | 0.30 ± 0.14 |" in table
    assert "MiniGrid-DoorKey-8x8-v0 HhP seed 0 (0.96; plain greedy 0.90; `c_variants.json`)" in text
    assert "plain greedy only" not in text and "epsilon-greedy, evaluated before it did: MiniGrid-DoorKey-8x8-v0 HhP seed 0." in text
    assert pd.read_csv(csv_path)["success_det"].tolist() == [0.2, 0.4, 0.9, 1.0]  # the results file is left as written


def write_evaluations(path: Path, steps: list, returns: list) -> None:
    """An EvalCallback's evaluations.npz: one row of episode returns per periodic evaluation."""
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, timesteps=np.array(steps), results=np.array(returns, dtype=float),
             ep_lengths=np.ones((len(steps), len(returns[0]))))


def test_a_stopped_hhp_run_goes_on_from_its_last_checkpoint(tmp_path, monkeypatch):
    """An HhP run longer than a session is trained in parts: the runner passes the newest checkpoint to --resume, keeps
    the log folder, and joins the parts' periodic evaluations, a part's replacing what the part before it evaluated
    after its checkpoint (those steps were trained again)."""
    sweep = load_sweep(EXPERIMENTS / "minigrid_tasks.yml", check_envs=False)
    experiment = Experiment("MiniGrid-DoorKey-16x16-v0", "hhp", 0, 2_000_000)
    log = tmp_path / "logs" / experiment.name
    # part 1 evaluated at 200k, 400k and 600k, its last checkpoint at 400k (stopped while writing the next one)
    write_evaluations(log / "hhp" / "MiniGrid-DoorKey-16x16-v0_1" / "evaluations.npz", [200_000, 400_000, 600_000],
                      [[0.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    (log / "hhp" / "MiniGrid-DoorKey-16x16-v0_1" / "checkpoint.json").write_text('{"timesteps": 400000}')
    assert latest_checkpoint(log) == log / "hhp" / "MiniGrid-DoorKey-16x16-v0_1"
    assert latest_checkpoint(tmp_path / "nothing") is None
    # part 2 resumed there and evaluated at 600k again (a later file), with its own checkpoint further on
    part2 = log / "hhp" / "MiniGrid-DoorKey-16x16-v0_2"
    write_evaluations(part2 / "evaluations.npz", [600_000], [[0.0, 0.0]])
    (part2 / "resumed.json").write_text('{"timesteps": 400000}')
    (part2 / "checkpoint.json").write_text('{"timesteps": 600000}')
    os.utime(part2 / "evaluations.npz", (1e10, 1e10))
    assert latest_checkpoint(log) == part2
    parts = attempt_evaluations(log)
    assert [path.parent.name for path in parts] == ["MiniGrid-DoorKey-16x16-v0_1", "MiniGrid-DoorKey-16x16-v0_2"]
    curve = pd.read_csv(_curve_from_evaluations(parts, tmp_path / "curve.csv"))
    assert curve["steps"].tolist() == [200_000, 400_000, 600_000]
    assert curve["success"].tolist() == [0.0, 0.5, 0.0]  # part 1's 600k evaluation is replaced by part 2's
    # the training command the runner starts: a checkpoint at every periodic evaluation, and the newest one resumed
    commands = []
    monkeypatch.setattr("subprocess.run", lambda command, **kwargs: commands.append(command) or FailedRun())
    with open(tmp_path / "run.log", "w") as log_file, pytest.raises(RuntimeError, match="status 1"):
        _run_hhp(experiment, sweep, tmp_path, log_file)
    command = commands[0]
    assert command[command.index("--checkpoint-freq") + 1] == "200000"
    assert command[command.index("--resume") + 1] == str(part2)
    # the row's wall time counts the earlier parts' training too
    assert earlier_parts_seconds({"train_seconds": 300.0, "train_seconds_all_parts": 1000.0}) == 700.0
    assert earlier_parts_seconds({"train_seconds": 300.0}) == 0.0


class FailedRun:
    returncode = 1


TINY_BASELINES = """
ppo_rnd:
  default:
    n_envs: 2
    n_steps: 32
    batch_size: 32
    n_epochs: 1
    vec_rnd: {intrinsic_coef: 0.5, update_every: 16, rnd_kwargs: {hidden_dim: 16, embedding_dim: 8}}
dqn:
  default:
    n_envs: 1
    learning_starts: 64
    buffer_size: 1000
    batch_size: 16
    train_freq: 4
    target_update_interval: 100
ddpg_her:
  default:
    policy: MultiInputPolicy
    learning_starts: 64
    buffer_size: 1000
    batch_size: 16
    train_freq: [4, step]
    noise_type: normal
    noise_std: 0.2
    normalize: {norm_reward: false, clip_obs: 5.0}
    policy_kwargs: {net_arch: [16]}
    replay_buffer_class: HerReplayBuffer
    replay_buffer_kwargs: {n_sampled_goal: 2, goal_selection_strategy: future}
"""


@pytest.mark.parametrize("variant, env", [("ppo_rnd", "MiniGrid-Empty-5x5-v0"), ("dqn", "MiniGrid-Empty-5x5-v0"),
                                          ("ddpg_her", "FetchReach-v4")])
def test_a_stopped_baseline_run_goes_on_from_its_last_checkpoint(tmp_path, variant, env):
    """The flat baselines write a checkpoint at every periodic evaluation (the model; an off-policy one's replay, a
    HerReplayBuffer given the model's env back; PPO + RND's curiosity state; a VecNormalize's statistics) and a run
    stopped before its end goes on from it: the step count, the curiosity's state, the statistics and the replay carry
    on, the curve joins both parts, the training time counts both."""
    import pickle

    import torch as th

    from sb3_hhp.train import read_checkpoint

    def observations_counted(path: str) -> float:  # a VecNormalize's statistics (saved without its env)
        with open(path, "rb") as file:
            return float(pickle.load(file).obs_rms["observation"].count)

    write(tmp_path, TINY_BASELINES, "baselines.yml")
    sweep = load_sweep(write(tmp_path, f"""
        name: tiny
        envs: [{env}]
        variants: [{variant}]
        seeds: [0]
        steps: 512
        eval_freq: 256
        curve_episodes: 2
        eval_episodes: 2
        baselines_conf: {tmp_path / "baselines.yml"}
    """))
    out = tmp_path / "out"
    # part 1: a budget of 256 steps stands for a run stopped after its first checkpoint
    first = Experiment(env, variant, 0, 256)
    run_experiment(first, sweep, out)
    log = out / "logs" / first.name
    checkpoint = read_checkpoint(str(log))
    assert checkpoint["timesteps"] == 256
    assert (checkpoint["vec_rnd"] is not None) == (variant == "ppo_rnd")
    assert (checkpoint["replay"] is not None) == (variant != "ppo_rnd")
    assert (checkpoint["vec_normalize"] is not None) == (variant == "ddpg_her")
    counted = observations_counted(checkpoint["vec_normalize"]) if variant == "ddpg_her" else None
    # part 2: the whole budget, from that checkpoint
    row = run_experiment(Experiment(env, variant, 0, 512), sweep, out)
    assert row["timesteps"] == 512
    summary = pd.read_json(out / row["summary"], typ="series")
    assert summary["resumed_at"] == 256
    assert summary["train_seconds_all_parts"] > summary["train_seconds"] > 0
    assert (log / "part_256" / "resumed.json").is_file()
    # each part's code: the commit it ran (this checkout's HEAD) and the package files changed from it
    head = subprocess.run(["git", "-C", str(Path(__file__).resolve().parents[1]), "rev-parse", "HEAD"],
                          capture_output=True, text=True).stdout.strip()
    parts = json.loads((out / row["summary"]).read_text())["code"]
    assert [part["from_step"] for part in parts] == [0, 256]
    assert all(part["commit"] == (head or None) and isinstance(part["changed"], list) for part in parts)
    curve = pd.read_csv(out / row["curve"])
    assert curve["steps"].tolist() == [256, 512]  # one point from each part
    checkpoint = read_checkpoint(str(log))
    assert checkpoint["timesteps"] == 512
    if variant == "ppo_rnd":  # 512 steps of 2 envs, an update every 16: the first part's updates are counted on
        assert th.load(checkpoint["vec_rnd"], weights_only=True)["n_updates"] == 512 // 2 // 16
    else:  # the replay holds both parts' transitions
        from stable_baselines3 import HerReplayBuffer
        from stable_baselines3.common.save_util import load_from_pkl

        replay = load_from_pkl(checkpoint["replay"])
        assert replay.size() == 512 and isinstance(replay, HerReplayBuffer) == (variant == "ddpg_her")
    if variant == "ddpg_her":  # the statistics count on from part 1's; success is the env's is_success
        assert observations_counted(checkpoint["vec_normalize"]) >= counted + 256
        assert all("successes" in np.load(path).files for path in attempt_evaluations(log))
        assert summary["hyperparams"]["replay_buffer_class"] == "HerReplayBuffer"


def test_an_atari_baseline_reads_the_frames_of_its_wrapper_stacked(tmp_path):
    """PPO + RND on an ALE game: the entry's env_wrapper (AtariWrapper) and frame_stack build its envs, as RL Zoo's
    Atari entries do; the shipped atari entry is RL Zoo's PPO with RND."""
    pytest.importorskip("ale_py", reason='needs the [atari] extra: pip install "sb3_hhp[atari]"')
    from benchmarks.run import baseline_settings

    shipped = baseline_settings(str(EXPERIMENTS.parents[1] / "sb3_hhp" / "hyperparams" / "baselines.yml"), "ppo_rnd",
                                "ALE/MontezumaRevenge-v5")
    assert (shipped["env_wrapper"], shipped["frame_stack"], shipped["policy"]) == (
        "stable_baselines3.common.atari_wrappers.AtariWrapper", 4, "CnnPolicy")
    write(tmp_path, """
        ppo_rnd:
          atari:
            env_wrapper: stable_baselines3.common.atari_wrappers.AtariWrapper
            frame_stack: 4
            n_envs: 2
            policy: CnnPolicy
            n_steps: 32
            batch_size: 32
            n_epochs: 1
            policy_kwargs: {features_extractor_kwargs: {features_dim: 16}}
            vec_rnd: {intrinsic_coef: 0.5, update_every: 16, rnd_kwargs: {hidden_dim: 16, embedding_dim: 8}}
    """, "baselines.yml")
    sweep = load_sweep(write(tmp_path, f"""
        name: tiny
        envs: [ALE/MontezumaRevenge-v5]
        variants: [ppo_rnd]
        seeds: [0]
        steps: 128
        eval_freq: 0
        eval_episodes: 0
        baselines_conf: {tmp_path / "baselines.yml"}
    """))
    row = run_experiment(Experiment("ALE/MontezumaRevenge-v5", "ppo_rnd", 0, 128), sweep, tmp_path / "out")
    assert row["timesteps"] == 128
    from stable_baselines3 import PPO

    model = PPO.load(tmp_path / "out" / "logs" / Experiment("ALE/MontezumaRevenge-v5", "ppo_rnd", 0, 128).name / "model.zip")
    assert model.observation_space.shape == (4, 84, 84)  # 4 stacked 84x84 frames, channels first as SB3 reads them


def test_a_run_records_the_code_it_ran(tmp_path):
    """code_version: the checkout's commit and the tracked package files that differ from it (not untracked files, not
    files outside the package's folders, not the runs' results); None outside a git checkout."""
    def git(*words: str) -> str:
        return subprocess.run(["git", "-C", str(tmp_path), *words], capture_output=True, text=True, check=True).stdout

    assert code_version(tmp_path) is None
    git("init", "-q")
    (tmp_path / "sb3_hhp").mkdir()
    (tmp_path / "sb3_hhp" / "a.py").write_text("x = 1\n")
    (tmp_path / "notes.txt").write_text("notes\n")
    (tmp_path / "benchmarks" / "results").mkdir(parents=True)
    (tmp_path / "benchmarks" / "results" / "results.csv").write_text("env\n")
    git("add", "sb3_hhp/a.py", "notes.txt", "benchmarks/results/results.csv")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "first")
    head = git("rev-parse", "HEAD").strip()
    assert code_version(tmp_path) == {"commit": head, "changed": []}
    (tmp_path / "sb3_hhp" / "a.py").write_text("x = 2\n")
    (tmp_path / "sb3_hhp" / "new.py").write_text("y = 1\n")
    (tmp_path / "notes.txt").write_text("more notes\n")
    (tmp_path / "benchmarks" / "results" / "results.csv").write_text("env,seed\n")  # a result, not code
    assert code_version(tmp_path) == {"commit": head, "changed": ["sb3_hhp/a.py"]}


def sleeping_row(experiment: Experiment, sweep: Sweep, out: Path) -> dict[str, Any]:
    """Stands in for run_experiment: starts a training process that records its pid and sleeps."""
    (out / "worker.pid").write_text(str(os.getpid()))
    script = f"import os, time; open({str(out / 'child.pid')!r}, 'w').write(str(os.getpid())); time.sleep(120)"
    with open(out / "child.log", "w") as log_file:
        run_training([sys.executable, "-c", script], log_file)
    return fake_row(experiment, sweep, out)


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"  # a zombie has ended


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_killing_the_runner_stops_its_workers_and_their_training(tmp_path):
    sweep = write(tmp_path, GRID.replace("ppo", "hhp") + "steps: 100\n")
    out = tmp_path / "out"
    out.mkdir()
    script = ("import sys; from pathlib import Path; from benchmarks.run import load_sweep, run_sweep; "
              "from test_benchmark_runner import sleeping_row; "
              f"run_sweep(load_sweep({str(sweep)!r}, check_envs=False), Path({str(out)!r}), runner=sleeping_row)")
    root = Path(__file__).resolve().parent.parent
    runner = subprocess.Popen([sys.executable, "-c", script], cwd=root,
                              env={**os.environ, "PYTHONPATH": os.pathsep.join([str(root), str(root / "tests")])})
    try:
        deadline = time.monotonic() + 60
        while not (out / "child.pid").is_file() or not (out / "child.pid").read_text():
            assert runner.poll() is None and time.monotonic() < deadline, "the runner did not start its training"
            time.sleep(0.1)
        worker, child = (int((out / name).read_text()) for name in ("worker.pid", "child.pid"))
        assert alive(worker) and alive(child)
        runner.send_signal(signal.SIGTERM)
        runner.wait(timeout=30)
        deadline = time.monotonic() + 30
        while (alive(worker) or alive(child)) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not alive(worker), "the worker outlived the runner"
        assert not alive(child), "the training process outlived the runner"
    finally:
        for pid_file in ("worker.pid", "child.pid"):
            with contextlib.suppress(OSError, ValueError):
                os.kill(int((out / pid_file).read_text()), signal.SIGKILL)
        runner.kill()


def test_report_shows_runs_that_have_no_row_yet(tmp_path):
    """A sweep of runs that take hours is looked at while it runs: a run with a log folder and no row is listed with
    the steps its periodic evaluations reached and drawn dashed; a finished run's log folder is not."""
    csv_path = synthetic_results(tmp_path)
    # HhP seed 0 finished (it has a row); a third HhP seed stopped after two evaluations; a PPO seed has not evaluated
    write_evaluations(tmp_path / "logs" / "MiniGrid-DoorKey-8x8-v0__hhp__s0" / "evaluations.npz", [500], [[1.0]])
    write_evaluations(tmp_path / "logs" / "MiniGrid-DoorKey-8x8-v0__hhp__s2" / "hhp" / "run_1" / "evaluations.npz",
                      [200, 400], [[0.0, 0.0, 0.0, 0.0], [0.9, 0.0, 0.8, 0.0]])
    (tmp_path / "logs" / "MiniGrid-DoorKey-8x8-v0__ppo__s7").mkdir(parents=True)
    # seed 0's curve from while it ran, left over from a report made before its row was written
    stale = tmp_path / "curves" / "MiniGrid-DoorKey-8x8-v0__hhp__s0.partial.csv"
    stale.parent.mkdir(parents=True, exist_ok=True)
    stale.write_text("steps,success\n200,0.0\n")
    table, markdown, plots = report.report(csv_path)
    assert not stale.exists(), "a finished run's partial curve outlived its row"
    assert "| MiniGrid-DoorKey-8x8-v0 HhP seed 2 | 400 | 0.50 |" in table
    assert "| MiniGrid-DoorKey-8x8-v0 PPO seed 7 | 0 | – |" in table
    assert "seed 0 |" not in table
    partial = pd.read_csv(tmp_path / "curves" / "MiniGrid-DoorKey-8x8-v0__hhp__s2.partial.csv")
    assert partial["steps"].tolist() == [200, 400] and partial["success"].tolist() == [0.0, 0.5]
    assert [plot.name for plot in plots] == ["curves_MiniGrid-DoorKey-8x8-v0.png"]
    # a sweep with no finished run yet: the unfinished ones alone
    only = tmp_path / "running"
    write_evaluations(only / "logs" / "ALE-Pong-v5__ppo__s0" / "evaluations.npz", [100], [[-21.0]])
    table, _, plots = report.report(only / "results.csv")
    assert "| ALE-Pong-v5 PPO seed 0 | 100 | 0.00 |" in table and [plot.name for plot in plots] == ["curves_ALE-Pong-v5.png"]


def test_report_speed_section_rows_from_the_speed_files(tmp_path):
    """``speed.py``'s JSON files under ``results/speed`` make one row each: HhP's and its baseline's (DQN or DDPG + HER)
    steps/s and their ratio."""
    speed = tmp_path / report.RESULTS / "speed"
    speed.mkdir(parents=True)
    (speed / "atari.json").write_text(json.dumps(dict(
        env="ALE/MontezumaRevenge-v5", n_envs=1, window=[1000, 2000], hhp_kwargs={"meta_kwargs": {"n_opt": 4}},
        hhp_fps=30.04, dqn_fps=90.0, ratio=0.334, num_subgoals=1, load_average_start=1.02, load_average_end=2.0,
        code=dict(commit="abcdef0123", changed=["sb3_hhp/hhp/hhp.py"]))))
    text = report.speed_section(tmp_path)
    assert text.startswith("## Speed beside SB3's DQN")
    assert ('| `atari.json` | abcdef0+ | ALE/MontezumaRevenge-v5 | 1 | 1,000-2,000 | `{"meta_kwargs": {"n_opt": 4}}` | 30.0 | DQN 90.0 | '
            '0.33 | 1 | 1.0-2.0 |') in text
    (speed / "push.json").write_text(json.dumps(dict(
        env="FetchPush-v4", n_envs=1, window=[2000, 4000], hhp_kwargs={}, hhp_fps=24.0, her_fps=40.0, ratio=0.6,
        num_subgoals=3, load_average_start=1.0, load_average_end=1.2)))
    assert "| `push.json` | – | FetchPush-v4 | 1 | 2,000-4,000 | `{}` | 24.0 | DDPG + HER 40.0 | 0.60 | 3 | 1.0-1.2 |" in (
        report.speed_section(tmp_path))
    (speed / "push.json").unlink()
    assert "many sub-goals" not in text
    (speed / "costs.json").write_text(json.dumps(dict(
        env="ALE/MontezumaRevenge-v5", window=[500, 1500], hhp_kwargs={}, cost_ratio=3.136, memory_ratio=1.899,
        rows=[dict(k=2, ms_per_step=31.254, replay_mb=674.0), dict(k=32, ms_per_step=98.002, replay_mb=674.0)])))
    text = report.speed_section(tmp_path)
    assert "| `atari.json` |" in text and "## The cost of many sub-goals" in text  # each file in its own table
    assert "| `costs.json` | – | ALE/MontezumaRevenge-v5 | 500-1,500 | `{}` | 2 / 32 | 31.3 / 98.0 | 3.14 | 674 / 674 | 1.90 |" in text
    assert report.speed_section(tmp_path / "elsewhere") == ""  # no files, no section


def test_report_mean_curve_over_seeds():
    a = pd.DataFrame({"steps": [0, 100], "success": [0.0, 1.0]})
    b = pd.DataFrame({"steps": [0, 100], "success": [0.0, 0.5]})
    curve = report.mean_curve([a, b])
    assert curve["steps"].iloc[0] == 0 and curve["steps"].iloc[-1] == 100
    assert curve["mean"].iloc[-1] == pytest.approx(0.75)
    assert curve["std"].iloc[-1] == pytest.approx(np.std([1.0, 0.5], ddof=1))
    assert report.mean_curve([]) is None


def test_report_command_line(tmp_path, capsys):
    synthetic_results(tmp_path)
    assert report.main([str(tmp_path)]) == 0
    assert "| HhP |" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="No results file"):
        report.main([str(tmp_path / "nothing.csv")])


def test_the_speed_script_times_an_entry_as_it_trains() -> None:
    """``speed.py entry`` builds HhP from the env's YAML entry (its policy, wrapper and n_envs) and times a window."""
    import argparse

    from benchmarks import speed

    result = speed.entry_speed(argparse.Namespace(env="MiniGrid-Empty-5x5-v0", hhp_kwargs='{"device": "cpu"}', seed=0,
                                                  start=100, stop=300, n_envs=None, vs_dqn=True, vs_her=False))
    assert result["n_envs"] == 1 and result["policy"] == "MlpPolicy" and result["device"] == "cpu"  # the entry's
    assert result["window"] == [100, 300] and result["hhp_fps"] > 0 and result["num_subgoals"] >= 1
    # SB3's DQN timed over the same window before and after HhP, HhP against their mean
    assert result["dqn_fps_before"] > 0 and result["dqn_fps_after"] > 0
    assert result["ratio"] == pytest.approx(result["hhp_fps"] / result["dqn_fps"], rel=0.01)


def test_the_speed_script_times_a_fetch_entry_beside_ddpg_with_her() -> None:
    """``speed.py entry --vs-her``: SB3's DDPG with a HerReplayBuffer on the same Fetch env, timed before and after."""
    import argparse

    from stable_baselines3 import DDPG
    from stable_baselines3.her import HerReplayBuffer

    from benchmarks import speed

    args = argparse.Namespace(env="FetchReach-v4", hhp_kwargs='{"device": "cpu"}', seed=0, start=20, stop=60,
                              n_envs=None, vs_dqn=False, vs_her=True)
    baseline, settings = speed.her_baseline(args, speed.hhp_kwargs(speed.yaml_entry(args.env)[1], args.hhp_kwargs), 1)
    assert isinstance(baseline, DDPG) and isinstance(baseline.replay_buffer, HerReplayBuffer)
    assert baseline.replay_buffer.n_sampled_goal == 4 and settings["algo"] == "DDPG + HER"
    result = speed.entry_speed(args)
    assert result["her_fps_before"] > 0 and result["her_fps_after"] > 0 and "dqn_fps" not in result
    assert result["ratio"] == pytest.approx(result["hhp_fps"] / result["her_fps"], rel=0.01)


def test_the_speed_script_splits_a_learner_call() -> None:
    """``speed.py call`` times the sub-goal learners' grouped update from a saved state and splits it into the batched
    products, torch's other operators and what runs outside torch; with call_ab, two settings of the learners timed
    in alternating blocks too (here the written-out backward pass against autograd's)."""
    import argparse

    from benchmarks import speed

    args = argparse.Namespace(env="MiniGrid-DoorKey-5x5-v0", hhp_kwargs='{"device": "cpu"}', seed=0, start=800, n_envs=8,
                              repeats=2, call_ab=True, learners_a='{"_relu_mlp": true}', learners_b='{"_relu_mlp": false}',
                              model=None, replay=None)
    result = speed.learner_call(args)
    assert len(result["call_ms_a"]) == len(result["call_ms_b"]) == 2 and min(result["call_ms_a"] + result["call_ms_b"]) > 0
    assert result["learners_b"] == {"_relu_mlp": False} and result["median_ratio_b_to_a"] > 0
    assert result["rounds"] == 2 and 1 <= result["learners_per_round"] <= result["snapshot_subgoals"]
    assert result["products_ms"] > 0 and result["other_torch_ms"] > 0
    assert "aten::baddbmm" in result["top_torch_ops_ms"]
    # the parts are measured apart (torch's own times, and the profiled calls' wall time less them)
    assert result["outside_torch_ms"] > 0 and result["products_ms"] < result["profiled_call_ms"]
    assert result["top_torch_ops_ms"]["aten::baddbmm"] <= result["products_ms"]
    # from a saved run's model and replays instead (late in a run): that state's learners, their replay as saved
    saved, folder = speed.snapshot(args, speed.entry_kwargs(args.env, args.hhp_kwargs)[1], "call_test_")
    args.model, args.replay, args.call_ab, args.repeats = str(folder / "snapshot.zip"), str(folder / "snapshot_replay.pkl"), False, 1
    loaded = speed.saved_run(args)
    assert loaded.subpolicies.replay.size() == saved.subpolicies.replay.size() > 0 and loaded.oracle is None
    result = speed.learner_call(args)
    assert result["model"] == args.model and result["snapshot_steps"] == saved.num_timesteps
    assert result["snapshot_subgoals"] == len(saved.subgoals) and result["call_ms"] > 0
    # ``late``'s clocks around the parts of a step: every part named, nested parts within theirs, the methods restored
    shares = speed.timed_parts(loaded, 400)
    parts = shares["parts"]
    assert shares["steps"] >= 400 and shares["fps"] > 0 and set(parts) == {label for _, _, label in speed.PARTS}
    assert parts["sub-goal learners' updates"]["seconds"] > 0  # due every few steps (an episode may not end in 400)
    meta = parts["meta-controller updates"]["seconds"]
    assert parts["meta-controller updates: eq. 3 rewards"]["seconds"] <= meta
    assert parts["meta-controller updates: Double DQN targets"]["seconds"] <= meta
    assert sum(parts[label]["seconds"] for label in ("meta-controller updates", "sub-goal learners' updates",
                                                   "between episodes")) <= shares["seconds"]
    assert not {"train", "_rewards", "_target", "after_episode"} & set(vars(loaded))
    assert "train_rounds" not in vars(loaded.subpolicies)


def test_the_evaluation_script_replays_a_runs_episodes_with_load_options(tmp_path, monkeypatch, capsys) -> None:
    """``benchmarks/evaluate.py`` evaluates a run's model on the episodes the run was evaluated on (seeds seed + 10000,
    ...), once as saved and once with each ``--compare`` setting given to ``HhP.load``; a log folder resolves to the
    run's final model, else its newest checkpoint."""
    import gymnasium as gym

    from benchmarks import evaluate as script
    from sb3_hhp import HhP

    run = tmp_path / "logs" / "run"
    (run / "checkpoints" / "100").mkdir(parents=True)
    model = HhP("MlpPolicy", gym.make("MiniGrid-Empty-5x5-v0"), seed=0, buffer_size=1000, learning_starts=10)
    model.save(run / "checkpoints" / "100" / "model.zip")
    (run / "checkpoint.json").write_text('{"timesteps": 100, "model": "checkpoints/100/model.zip"}')  # as runs write it
    assert script.model_file(str(run), "MiniGrid-Empty-5x5-v0") == run / "checkpoints" / "100" / "model.zip"
    model.save(run / "hhp" / "MiniGrid-Empty-5x5-v0_1" / "MiniGrid-Empty-5x5-v0.zip")
    final = run / "hhp" / "MiniGrid-Empty-5x5-v0_1" / "MiniGrid-Empty-5x5-v0.zip"
    assert script.model_file(str(run), "MiniGrid-Empty-5x5-v0") == final
    calls = []

    def fake_evaluate(model, make_envs, seeds, deterministic=True):
        calls.append((model.break_cycles, list(seeds), deterministic))
        return {"successes": [model.break_cycles] * len(seeds), "returns": [0.5] * len(seeds)}

    monkeypatch.setattr(script, "evaluate", fake_evaluate)
    out = tmp_path / "figures.json"
    assert script.main(["MiniGrid-Empty-5x5-v0", f"3={run}", "--episodes", "4", "--compare", '{"break_cycles": false}',
                        "--out", str(out)]) == 0
    seeds = [10_003, 10_004, 10_005, 10_006]
    assert calls == [(True, seeds, True), (True, seeds, False), (False, seeds, True), (False, seeds, False)]
    runs = pd.read_json(out, typ="series")["runs"]
    assert [(row["load_options"], row["deterministic"], row["stochastic"]) for row in runs] == [
        ({}, 1.0, 1.0), ({"break_cycles": False}, 0.0, 0.0)]
    assert [row["break_cycles"] for row in runs] == [True, False]  # what report.py reads: the policy each row measured
    assert all(row["model"] == str(final) and row["seed"] == 3 for row in runs)
    calls.clear()
    script.main(["MiniGrid-Empty-5x5-v0", f"3={final}", "--episodes", "2", "--deterministic-only"])
    assert calls == [(True, [10_003, 10_004], True)]
    calls.clear()
    script.main(["MiniGrid-Empty-5x5-v0", f"3={final}", "--episodes", "2", "--stochastic-only"])
    assert calls == [(True, [10_003, 10_004], False)]
    with pytest.raises(SystemExit, match="nothing to evaluate"):
        script.main(["MiniGrid-Empty-5x5-v0", f"3={final}", "--deterministic-only", "--stochastic-only"])
    with pytest.raises(SystemExit, match="SEED=PATH"):
        script.main(["MiniGrid-Empty-5x5-v0", str(final)])
