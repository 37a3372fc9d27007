"""Tests of the benchmarks' report (benchmarks/report.py): the results page and the summaries it copies into
README.md, docs/modules/hhp.rst and benchmarks/README.md are what the results files give, and follow them."""

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from benchmarks import report

ROOT = Path(__file__).resolve().parent.parent


def test_the_results_page_and_the_summaries_are_up_to_date(capsys):
    """Fails when a results file changed without ``python benchmarks/report.py`` (or a marked block was edited)."""
    assert report.main(["--check"]) == 0, capsys.readouterr().err
    assert report.write_or_check(ROOT, check=True) == []


def copy_tree(tmp_path: Path) -> Path:
    """The files the report reads and writes, copied under ``tmp_path`` (a repository root of their own) as a clean
    clone has them: without the run folders (``logs``, gigabytes of checkpoints where runs were trained) and the
    curves of runs in progress."""
    for folder in (report.RESULTS, report.EXPERIMENTS):
        shutil.copytree(ROOT / folder, tmp_path / folder, ignore=shutil.ignore_patterns("logs", "*.partial.csv"))
    for path in (report.PAGE, *report.BLOCKS):
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / path, tmp_path / path)
    return tmp_path


def block(path: Path, markup: str) -> str:
    begin, end = report.MARKERS[markup]
    text = path.read_text()
    return text[text.index(begin) + len(begin):text.index(end)]


def figures(text: str) -> list[str]:
    """The figures of a summary, in order: ``mean ± std`` and single means."""
    return re.findall(r"\d+\.\d\d(?: ± \d+\.\d\d)?", text)


def test_a_changed_figure_changes_the_page_and_every_summary(tmp_path):
    root = copy_tree(tmp_path)
    assert report.write_or_check(root, check=True) == []
    csv_path = root / report.RESULTS / "doorkey8x8_entry" / "results.csv"
    results = pd.read_csv(csv_path)
    assert results["success_det"].tolist() == [1.0] * 6  # DoorKey-8x8's row of its former own entry in the summary
    results.loc[results["seed"] == 0, "success_det"] = 0.5
    results.to_csv(csv_path, index=False)

    stale = report.write_or_check(root, check=True)
    assert sorted(stale) == sorted([root / report.PAGE, *(root / path for path in report.BLOCKS)])
    assert report.main(["--check", "--root", str(root)]) == 1
    assert report.main(["--root", str(root)]) == 0
    assert report.write_or_check(root, check=True) == []

    row = ("|  | HhP, the task's former own entry | `doorkey8x8_entry`: `hhp` | 300,000 | 0-5 | 0.92 ± 0.20 | 1.00 ± 0.00 | "
           "76 ± 3 | no / yes |")
    readme = block(root / "README.md", "md")
    assert row in readme and row in (root / report.PAGE).read_text()
    assert block(root / "benchmarks" / "README.md", "md") == readme
    rst = block(root / "docs" / "modules" / "hhp.rst", "rst")
    assert "0.92 ± 0.20" in rst and figures(rst) == figures(readme)  # the three agree to the digit
    # the sweep's own section on the page follows too; the real tree is left as it was
    assert "| MiniGrid-DoorKey-8x8-v0 | HhP | 6 | 300,000 | 0.92 ± 0.20 |" in (root / report.PAGE).read_text()
    assert pd.read_csv(ROOT / report.RESULTS / "doorkey8x8_entry" / "results.csv")["success_det"].min() == 1.0


def test_every_figure_of_the_summary_names_its_seeds_steps_and_labels():
    header, _, *rows = report.markdown_summary(report.summary_rows()).split("\n\n")[0].splitlines()
    assert "steps" in header and "seeds" in header and "labels" in header
    for row in rows:
        cells = [cell.strip() for cell in row.strip("|").split("|")]
        if cells[5] != "not run yet":
            assert re.fullmatch(r"[\d,]+", cells[3]) and re.fullmatch(r"[\d, -]+", cells[4]), row
            assert cells[7] != "" and cells[8] in {"yes / yes", "yes / no", "no / yes", "no / no"}, row
    assert "python benchmarks/report.py" in report.results_page()
    assert "python -m benchmarks.run benchmarks/experiments/doorkey8x8_entry.yml" in report.results_page()


def test_a_missing_marker_is_named(tmp_path):
    root = copy_tree(tmp_path)
    readme = root / "README.md"
    readme.write_text(readme.read_text().replace("<!-- results:end -->", ""))
    with pytest.raises(SystemExit, match="README.md needs one block"):
        report.write_or_check(root, check=True)


def fetch_reach_rows(root: Path) -> list[list[str]]:
    """The summary's FetchReach rows: HhP, DDPG + HER, TQC + HER."""
    rows = report.summary_rows(root)
    start = next(index for index, row in enumerate(rows) if row[0] == "FetchReach-v4")
    return rows[start:start + 3]


def test_a_baseline_its_sweep_names_has_its_row_once_it_ran(tmp_path):
    """A baseline of the summary that its sweep file names reads "not run yet", with the sweep and variant its figures
    will come from, until the sweep's results file has its rows, then their figures; one that no sweep file names and
    no results file has is an error that says what to change."""
    root = copy_tree(tmp_path)
    csv_path = root / report.RESULTS / "fetch_reach" / "results.csv"
    results = pd.read_csv(csv_path)
    results = results[results["variant"] == "hhp"]  # the sweep before its baselines ran (the real one may hold them)
    results.to_csv(csv_path, index=False)
    _, ddpg_her, tqc_her = fetch_reach_rows(root)
    assert ddpg_her[1:3] == ["DDPG + HER", "`fetch_reach`: `ddpg_her`"] and ddpg_her[5:7] == ["not run yet"] * 2
    assert tqc_her[1:3] == ["TQC + HER", "`fetch_reach`: `tqc_her`"] and tqc_her[5] == "not run yet"
    ran = results.iloc[[0]].assign(variant="tqc_her", success_det=1.0, success_stoch=0.98, labels_used=None,
                                   curve=None, summary=None)
    pd.concat([results, ran], ignore_index=True).to_csv(csv_path, index=False)
    _, ddpg_her, tqc_her = fetch_reach_rows(root)
    assert tqc_her == ["", "TQC + HER", "`fetch_reach`: `tqc_her`", "50,000", "0", "1.00", "0.98", "–", "yes / yes"]
    assert ddpg_her[5] == "not run yet"
    sweep = root / report.EXPERIMENTS / "fetch_reach.yml"
    sweep.write_text(sweep.read_text().replace("variants: [hhp, ddpg_her, tqc_her", "variants: [hhp, tqc_her"))
    with pytest.raises(SystemExit, match="has no FetchReach-v4 ddpg_her row: change report.SUMMARY or run that sweep"):
        report.summary_rows(root)


def test_a_sweep_table_counts_the_sub_goals_its_hhp_runs_found(tmp_path):
    """From each HhP run's summary (``num_subgoals``): the mean ± std over seeds; a baseline, or a run without a
    summary, has none; a table without the counts has no such column."""
    folder = tmp_path / "sweep"
    (folder / "runs").mkdir(parents=True)
    for seed, count in ((0, 10), (1, 14)):
        (folder / "runs" / f"hhp_s{seed}.json").write_text(json.dumps({"num_subgoals": count}))
    results = pd.DataFrame({
        "env": ["E"] * 3, "variant": ["hhp", "hhp", "dqn"], "seed": [0, 1, 0], "steps": [100] * 3,
        "success_det": [1.0] * 3, "success_stoch": [1.0] * 3, "labels_used": [5, 5, None], "wall_seconds": [60] * 3,
        "summary": ["runs/hhp_s0.json", "runs/hhp_s1.json", None]})
    counts = report.subgoal_counts(results, folder)
    assert counts.iloc[:2].tolist() == [10.0, 14.0] and np.isnan(counts.iloc[2])
    lines = report.markdown_table(results.assign(subgoals=counts)).splitlines()
    assert lines[0].split(" | ")[7] == "sub-goals"
    rows = {line.split(" | ")[1]: line.split(" | ") for line in lines[2:]}
    assert rows["HhP"][7] == "12 ± 3" and rows["DQN"][7] == "–"
    assert "sub-goals" not in report.markdown_table(results)


def test_the_fetch_contact_files_make_a_table(tmp_path):
    """Each ``contact_*.json`` beside a sweep's results: its shares, and its sub-goals with the gripper at the object."""
    folder = tmp_path / report.RESULTS / "fetch_sweep"
    folder.mkdir(parents=True)
    assert report.contact_section(tmp_path) == ""
    data = {"env": "FetchPush-v4", "num_timesteps": 100000, "episodes": 20, "deterministic": False,
            "gripper_at_object": 0.85, "object_moved": 0.9, "success": 0.1,
            "subgoals": [{"name": "task solved"}, {"name": "at (1.0, 2.0, 42.5) cm, the gripper at it"},
                         {"name": "at (5.0, 2.0, 42.5) cm, the gripper away"}]}
    (folder / "contact_run.json").write_text(json.dumps(data))
    row = report.contact_section(tmp_path).splitlines()[-1]
    assert row == ("| `fetch_sweep/contact_run.json` | FetchPush-v4 | 100,000 | 20 | stochastic | 0.85 | 0.90 | 0.10 "
                   "| 3 (1) |")


def test_steps_to_the_baselines_level_time_each_seeds_periodic_evaluations(tmp_path):
    """The level is min(DDPG + HER's mean final deterministic success, 0.5); each seed's first periodic evaluation at
    or above it, mean ± std over the seeds that reached it; an env whose baseline solved nothing has no row."""
    folder = tmp_path / "sweep"
    (folder / "curves").mkdir(parents=True)
    curves = {  # run -> success at 10k, 20k, 30k, 40k
        "her_s0": [0.1, 0.3, 0.4, 0.4], "her_s1": [0.0, 0.2, 0.3, 0.3],  # final 0.4 and 0.3: the level is 0.35
        "hhp_s0": [0.35, 0.0, 0.9, 1.0], "hhp_s1": [0.0, 0.0, 0.36, 1.0], "hhp_s2": [0.0, 0.1, 0.2, 0.3],
        "low_her": [0.0, 0.0, 0.0, 0.0], "low_hhp": [0.0, 0.5, 1.0, 1.0],
    }
    for run, success in curves.items():
        pd.DataFrame({"steps": [10_000, 20_000, 30_000, 40_000], "success": success}).to_csv(
            folder / "curves" / f"{run}.csv", index=False)
    rows = [("E", "ddpg_her", 0, 0.4, "her_s0"), ("E", "ddpg_her", 1, 0.3, "her_s1"), ("E", "hhp", 0, 1.0, "hhp_s0"),
            ("E", "hhp", 1, 1.0, "hhp_s1"), ("E", "hhp", 2, 0.3, "hhp_s2"), ("F", "ddpg_her", 0, 0.0, "low_her"),
            ("F", "hhp", 0, 1.0, "low_hhp")]
    results = pd.DataFrame([dict(env=env, variant=variant, seed=seed, steps=40_000, success_det=final, success_stoch=final,
                                 labels_used=None, wall_seconds=60, curve=f"curves/{run}.csv")
                            for env, variant, seed, final, run in rows])
    assert report.first_reach(pd.read_csv(folder / "curves" / "hhp_s1.csv"), 0.35) == 30_000
    assert report.first_reach(pd.read_csv(folder / "curves" / "hhp_s2.csv"), 0.35) is None
    table = report.steps_to_level(results, folder).splitlines()
    cells = {line.split(" | ")[2]: line.strip("| ").split(" | ") for line in table[2:]}
    assert set(cells) == {"DDPG + HER", "HhP"} and all(line.startswith("| E | 0.35 |") for line in table[2:])
    assert cells["DDPG + HER"][3:] == ["30,000", "1 of 2"]  # its second seed never reached its own mean
    assert cells["HhP"][3:] == ["20,000 ± 14,142", "2 of 3"]  # 10k (at the level exactly) and 30k
    only_f = results[results["env"] == "F"]
    assert report.steps_to_level(only_f, folder) is None  # DDPG + HER solved nothing there
    assert report.steps_to_level(results[results["variant"] == "hhp"], folder) is None  # no baseline
